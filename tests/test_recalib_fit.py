"""Zero-constrained RF force correction on synthetic pokes (known true force vs a biased model)."""
import numpy as np
import pytest
from tensortouch.contracts.errors import CalibrationError
from tensortouch.runtime.stages.correction import ForceCorrection
from tensortouch.tools.recalib.fit import (
    FitConfig,
    PokeSet,
    corrected_magnitude,
    decide,
    error_stats,
    fit_correction,
    fit_forest,
    gain_targets,
    to_onnx,
)
from tensortouch.tools.recalib.synthetic import SyntheticUnit

STIFF_SHIFTED = SyntheticUnit(stiffness_ratio=1.2, center_shift=(0.06, -0.04), radial_bias=0.25)


def _runtime_correction(tmp_path, fit):
    path = tmp_path / "correction.onnx"
    path.write_bytes(fit.onnx_bytes)
    return ForceCorrection(path, fit.spec)


@pytest.mark.parametrize("n", [5, 6, 7])
def test_pokes_cut_held_out_error_on_stiffer_shifted_gel(n):
    rng = np.random.default_rng(100 + n)
    pokes = STIFF_SHIFTED.guided_pokes(rng, n)
    fit = fit_correction(pokes)
    assert fit.loo["after"]["mae_n"] < 0.6 * fit.loo["before"]["mae_n"]
    test = STIFF_SHIFTED.held_out(rng, 300)
    g = fit_forest(pokes).predict(test.features(FitConfig().inputs))
    before = error_stats(test.pred_mag, test.ref_force)["mae_n"]
    after = error_stats(corrected_magnitude(test.pred_mag, g), test.ref_force)["mae_n"]
    assert after <= 0.4 * before, (before, after)


def test_onnx_model_runs_in_the_runtime_and_matches_sklearn(tmp_path):
    rng = np.random.default_rng(3)
    pokes = STIFF_SHIFTED.guided_pokes(rng, 6)
    fit = fit_correction(pokes)
    corr = _runtime_correction(tmp_path, fit)
    test = STIFF_SHIFTED.held_out(rng, 50)
    out = corr(test.pred_force, test.uv, test.theta_phi)
    chosen = FitConfig(inputs=tuple(fit.spec["inputs"]), candidates=())      # the inputs the selection chose
    g = fit_forest(pokes, chosen).predict(test.features(chosen.inputs))
    assert np.allclose(np.linalg.norm(out, axis=1), corrected_magnitude(test.pred_mag, g), rtol=1e-4)
    # direction kept: gain only
    cos = np.sum(out * test.pred_force, axis=1) / (np.linalg.norm(out, axis=1) * test.pred_mag)
    assert np.allclose(cos, 1.0)


def test_zero_constraint_no_contact_gives_exactly_zero(tmp_path):
    rng = np.random.default_rng(4)
    fit = fit_correction(STIFF_SHIFTED.guided_pokes(rng, 6))
    corr = _runtime_correction(tmp_path, fit)
    forces = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.5], [0.0, 0.0, 0.0]])
    uv = np.array([[0.5, 0.5], [0.3, 0.6], [0.9, 0.1]])
    out = corr(forces, uv, np.zeros((3, 2)))
    assert np.all(out[0] == 0.0) and np.all(out[2] == 0.0)
    assert out[1, 2] < -1.5   # stiffer gel: the correction raises the force
    # the forest itself predicts a non-zero gain at zero force: the constraint is what zeroes it
    zero = PokeSet(np.zeros((1, 3)), [0.0], [[0.5, 0.5]], [[0.0, 0.0]]).features(FitConfig().inputs)
    g0 = fit_forest(STIFF_SHIFTED.guided_pokes(rng, 6)).predict(zero)
    assert g0[0] > 0.5


def test_correction_worse_than_the_active_one_is_refused(tmp_path):
    """The active calibration already corrects well (fitted on 400 bench pokes): 5 noisy field pokes
    give a held-out error above the active correction's error on the same pokes → refused unless forced."""
    rng = np.random.default_rng(7)
    noisy = SyntheticUnit(stiffness_ratio=1.2, center_shift=(0.06, -0.04), radial_bias=0.25, gauge_rel_noise=0.05)
    cfg = FitConfig(max_depth=None)
    path = tmp_path / "bench.onnx"
    path.write_bytes(to_onnx(fit_forest(STIFF_SHIFTED.held_out(rng, 400), cfg), len(cfg.inputs), cfg))
    active = ForceCorrection(path, {"inputs": list(cfg.inputs), "output": "gain"})
    pokes = noisy.guided_pokes(rng, 5)
    fit = fit_correction(pokes)
    active_err = error_stats(np.linalg.norm(active(pokes.pred_force, pokes.uv, pokes.theta_phi), axis=1),
                             pokes.ref_force)
    d = decide(fit.loo["after"], active_err)
    assert not d.store and "--force" in d.reason, d
    forced = decide(fit.loo["after"], active_err, force=True)
    assert forced.store and "stored anyway" in forced.reason


def test_decide_accepts_improvement():
    d = decide({"mae_n": 0.1}, {"mae_n": 0.5})
    assert d.store and d.after_mae_n == 0.1 and d.before_mae_n == 0.5


def test_too_few_pokes_and_invisible_pokes_are_errors():
    rng = np.random.default_rng(5)
    pokes = STIFF_SHIFTED.guided_pokes(rng, 4)
    with pytest.raises(CalibrationError, match="need at least 5"):
        fit_correction(pokes)
    p = STIFF_SHIFTED.guided_pokes(rng, 5)
    p.pred_force[2] = 0.0
    with pytest.raises(CalibrationError, match=r"pokes \[2\]: predicted force below"):
        gain_targets(p)


def test_gain_clipped_like_the_runtime():
    p = PokeSet(np.array([[0, 0, -1.0]] * 5), np.array([10.0, 1, 1, 1, 1]), np.full((5, 2), 0.5), np.zeros((5, 2)))
    assert gain_targets(p)[0] == FitConfig().max_gain


def test_input_selection_takes_position_only_when_leave_one_out_supports_it():
    from tensortouch.tools.recalib.fit import select_inputs

    rng = np.random.default_rng(11)
    n = 7
    pf = np.c_[np.zeros((n, 2)), -rng.uniform(0.5, 3.0, n)]
    tp = np.c_[np.linspace(0.0, 0.6, n), rng.uniform(-3, 3, n)]
    uv = rng.uniform(0.2, 0.8, (n, 2))
    # gain depends strongly on θ only (×0.6 at the apex → ×1.4 at the rim): position is chosen
    ref = np.linalg.norm(pf, axis=1) * np.where(tp[:, 0] > 0.3, 1.4, 0.6)
    inputs, scores = select_inputs(PokeSet(pf, ref, uv, tp))
    assert "theta" in inputs and scores["fmag+theta"] < 0.85 * scores["fmag"], scores
    # a constant gain: the simplest candidate, unless a richer set is clearly (15 %) better
    ref = np.linalg.norm(pf, axis=1) * 0.7
    inputs, scores = select_inputs(PokeSet(pf, ref, uv, tp))
    assert inputs == (), scores
    fit = fit_correction(PokeSet(pf, ref, uv, tp))
    assert fit.spec["inputs"] == ["fmag"] and fit.spec["constant"] and fit.spec["n_estimators"] == 1
    assert set(fit.spec["selection_loo_mae_n"]) == {"constant", "fmag", "fmag+theta", "fmag+theta+u+v"}
    assert fit.loo["after"]["mae_n"] < 1e-9 + 0.01 * fit.loo["before"]["mae_n"]
    assert np.allclose(fit.train_gain, 0.7)        # one gain everywhere, exactly the pokes' gain


def test_a_constant_gain_beats_a_forest_over_force_with_few_noisy_pokes():
    """A gel 20 % stiffer with 10 % per-poke scatter (the model's own error): one gain from 6 pokes
    predicts new pokes better than piecewise gains over |F|, and the selection takes it."""
    from tensortouch.tools.recalib.fit import select_inputs

    rng = np.random.default_rng(3)
    errs = {"constant": [], "fmag": []}
    chosen = []
    for _trial in range(20):
        n = 6
        pf = np.c_[np.zeros((n, 2)), -rng.uniform(0.5, 3.0, n)]
        tp = np.c_[rng.uniform(0.0, 0.6, n), rng.uniform(-3, 3, n)]
        uv = rng.uniform(0.2, 0.8, (n, 2))
        ref = np.linalg.norm(pf, axis=1) * 1.2 * rng.normal(1.0, 0.1, n)
        inputs, scores = select_inputs(PokeSet(pf, ref, uv, tp))
        chosen.append(inputs)
        for k in errs:
            errs[k].append(scores[k])
    assert np.mean(errs["constant"]) < 0.9 * np.mean(errs["fmag"]), {k: np.mean(v) for k, v in errs.items()}
    assert chosen.count(()) >= 15, chosen          # 16 / 20 measured (13 with the mean alone): LOO on 6 pokes is noisy


def test_a_richer_set_carried_by_one_lucky_poke_is_not_chosen():
    from tensortouch.tools.recalib.fit import paired_t, simplest_adequate

    simple = np.array([0.10, 0.12, 0.09, 0.11, 0.60, 0.10])
    lucky = np.array([0.11, 0.13, 0.10, 0.12, 0.05, 0.11])      # 62 % lower mean, all from poke 4
    steady = simple * 0.7                                          # 30 % lower on every poke
    errors = {"constant": simple, "lucky": lucky, "steady": steady}
    assert paired_t(lucky, simple) < 1.5 < paired_t(steady, simple)
    assert simplest_adequate(["constant", "lucky"], errors.get, 0.15, 1.5) == "constant"
    assert simplest_adequate(["constant", "lucky"], errors.get, 0.15) == "lucky"       # the mean alone
    assert simplest_adequate(["constant", "steady"], errors.get, 0.15, 1.5) == "steady"
