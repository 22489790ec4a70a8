"""Sim-to-real force ratios (tools/train/simreal.py): per-component scales recovered, a fallback, applied
per owner."""
import numpy as np
import pytest
from tensortouch.tools.train.simreal import SimRealError, apply_ratios, fit_ratios


def test_fit_ratios_recovers_per_component_scale_and_falls_back():
    rng = np.random.default_rng(3)
    fe = np.column_stack([rng.uniform(0.5, 2, 50), rng.uniform(-0.01, 0.01, 50), -rng.uniform(2, 6, 50)])
    true = np.array([1.1, 0.7, 0.9])
    sensor = fe * true + rng.normal(0, 0.01, fe.shape)           # the measured force on the gel: RF's sign
    r = fit_ratios(sensor, fe)
    assert abs(r["ratio"][0] - 1.1) < 0.02 and abs(r["ratio"][2] - 0.9) < 0.01
    assert r["component_fitted"] == [True, False, True] and r["ratio"][1] == r["magnitude"]
    with pytest.raises(SimRealError):
        fit_ratios(sensor * 0.0, fe * 0.01)
    forces = np.ones((4, 3))
    out = apply_ratios(forces, np.array([0, 1, -1, 1]), np.array([[2.0, 2, 2], [0.5, 1, 1.5]]))
    np.testing.assert_allclose(out, [[2, 2, 2], [0.5, 1, 1.5], [1, 1, 1], [0.5, 1, 1.5]])
