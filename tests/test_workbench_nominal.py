"""The nominal correction's choices on synthetic calibration pokes (real scikit-learn forests):
cross-fitting folds, input selection, and 'no correction' when no forest beats the raw network."""
import numpy as np
from tensortouch.tools.recalib.fit import PokeSet
from tensortouch.tools.workbench.nominal import NominalConfig, choose_inputs, folds_of

CFG = NominalConfig(n_estimators=20)


def _pokes(gain_fn, n=400, seed=0):
    rng = np.random.default_rng(seed)
    f = rng.normal(size=(n, 3)) * rng.uniform(0.5, 4.0, (n, 1))
    uv, tp = rng.uniform(0, 1, (n, 2)), np.column_stack([rng.uniform(0, 1.2, n), rng.uniform(-3, 3, n)])
    mag = np.linalg.norm(f, axis=1)
    return PokeSet(f, mag * gain_fn(mag, tp, rng), uv, tp)


def test_folds_are_sessions_when_there_are_several_else_time_halves():
    t = np.linspace(0, 10, 8)
    assert folds_of(t, np.zeros(8)).tolist() == [0, 0, 0, 0, 1, 1, 1, 1]
    assert folds_of(t, np.array([0, 0, 1, 1, 2, 2, 0, 1])).tolist() == [0, 0, 1, 1, 2, 2, 0, 1]


def test_a_magnitude_gain_is_learned_with_the_simplest_inputs():
    pokes = _pokes(lambda m, tp, rng: 0.6 + 0.1 * np.tanh(m - 2) + rng.normal(0, 0.01, len(m)))
    cfg, checks = choose_inputs(pokes, np.arange(len(pokes)) % 2, CFG)
    assert cfg.inputs == ("fmag",)
    assert checks["fmag"]["after"]["mae_n"] < 0.3 * checks["none"]["after"]["mae_n"]


def test_no_correction_when_the_gain_is_noise():
    pokes = _pokes(lambda m, tp, rng: 1.0 + rng.normal(0, 0.1, len(m)))
    cfg, checks = choose_inputs(pokes, np.arange(len(pokes)) % 2, CFG)
    assert cfg.inputs == ()
