"""Twin rig signals (tools/twin/signals.py): the F/T reading and quaternions by hand, the gel skin's slow
recovery."""
import numpy as np
import pytest
from tensortouch.tools.twin.signals import Hysteresis, RigConfig, ft_reading, quat_wxyz


def test_hysteresis_slow_return():
    h = Hysteresis(0.2, 1.0, (1,))
    loading = [h.step(t, np.array([1.0]))[0] for t in np.arange(0, 10, 0.01)]
    assert loading[1] == pytest.approx(0.8, abs=0.01) and loading[-1] == pytest.approx(1.0, abs=1e-3)
    after = [h.step(t, np.array([0.0]))[0] for t in np.arange(10.0, 15, 0.01)]
    assert after[0] == pytest.approx(0.2, rel=0.05)                 # the slow part remains at release
    assert after[100] == pytest.approx(0.2 * np.exp(-1.0), rel=0.05)  # one tau later
    assert after[-1] < 0.002


def test_ft_reading_by_hand():
    """A lateral reaction of 1 N at the tip, F/T origin 44 mm up the indenter: the F/T sees -1 N along x
    and 44 N·mm about y; turned 90° about the indenter axis, the same in its own axes."""
    rf, rm, tip, rot = np.array([[1.0, 0, 0]]), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3))
    np.testing.assert_allclose(ft_reading(rf, rm, tip, rot, RigConfig(ft_yaw_rad=0.0)), [[-1, 0, 0, 0, 44, 0]],
                               atol=1e-12)
    np.testing.assert_allclose(ft_reading(rf, rm, tip, rot, RigConfig(ft_yaw_rad=np.pi / 2)), [[0, 1, 0, 44, 0, 0]],
                               atol=1e-12)
    d = RigConfig(ft_yaw_rad=np.pi / 2).ft_to_indenter_dict()
    np.testing.assert_allclose(d["rotation_wxyz"], [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12)
    assert d["translation_mm"] == [0.0, 0.0, 44.0]


def test_quaternions_keep_w_non_negative():
    q = quat_wxyz(np.array([[0, 0, np.pi / 2], [0, 0, 3 * np.pi / 2], [0, 0, 0]]))
    s = np.sqrt(0.5)
    np.testing.assert_allclose(q, [[s, 0, 0, s], [s, 0, 0, -s], [1, 0, 0, 0]], atol=1e-12)
