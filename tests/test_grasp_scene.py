"""Object placement in the grasp scene (tools/grasp/scene.py)."""
import numpy as np
import pytest


def test_placement_lets_both_objects_touch_one_pinch():
    pytest.importorskip("mujoco")
    from tensortouch.tools.grasp.scene import placement

    R, gap = 0.011, 0.005
    for r1, r2 in ((0.00109, 0.00109), (0.00109, 0.0015), (0.00109, 0.004), (0.004, 0.004)):
        x1, x2 = placement(r1, r2, R, gap)
        assert x2 - x1 >= r1 + r2 + gap - 1e-9
        # same sphere distance D closes on both: D = 2r + 2√(R² − x²) for each
        D1 = 2 * r1 + 2 * np.sqrt(R * R - x1 * x1)
        D2 = 2 * r2 + 2 * np.sqrt(R * R - x2 * x2)
        assert D1 == pytest.approx(D2, abs=1e-7)
