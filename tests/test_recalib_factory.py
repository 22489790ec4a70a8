"""Factory correction (the model's own error shape, fitted on a nominal unit) and a field scale on top of it."""
import numpy as np
import pytest

from runtime.contacts import Cluster
from runtime.correction import ForceCorrection
from runtime.errors import CalibrationError
from tools.recalib.factory import FactoryConfig, fit_factory, frame_samples, write
from tools.recalib.fit import (FitConfig, PokeSet, error_stats, fit_correction, scale_gain_onnx, fit_forest, to_onnx)
from tools.recalib.synthetic import SyntheticUnit

# the model reads the rim low (radial gain) on every unit; units differ by their gel's stiffness
NOMINAL = SyntheticUnit(stiffness_ratio=1.0, center_shift=(0.0, 0.0), radial_bias=0.4)
STIFF = SyntheticUnit(stiffness_ratio=1.2, center_shift=(0.0, 0.0), radial_bias=0.4)


def _sessions(unit, seeds, n=400):
    return [(f"s{k}", unit.held_out(np.random.default_rng(k), n)) for k in seeds]


def _runtime(tmp_path, spec, onnx, name="correction.onnx"):
    (tmp_path / name).write_bytes(onnx)
    return ForceCorrection(tmp_path / name, dict(spec, file=name))


def test_scaled_gain_model_is_the_factor_times_the_original_and_scales_again(tmp_path):
    pokes = STIFF.held_out(np.random.default_rng(1), 60)
    cfg = FitConfig(inputs=("fmag", "theta"), candidates=())
    onnx = to_onnx(fit_forest(pokes, cfg), 2, cfg)
    spec = {"inputs": ["fmag", "theta"], "output": "gain", "kind": "random_forest_gain"}
    base = _runtime(tmp_path, spec, onnx, "a.onnx")
    twice = _runtime(tmp_path, spec, scale_gain_onnx(scale_gain_onnx(onnx, 1.25), 0.5), "b.onnx")
    f0 = np.linalg.norm(base(pokes.pred_force, pokes.uv, pokes.theta_phi), axis=1)
    f1 = np.linalg.norm(twice(pokes.pred_force, pokes.uv, pokes.theta_phi), axis=1)
    assert np.allclose(f1, 0.625 * f0, rtol=1e-5)


def test_factory_correction_learns_the_model_error_shape_held_out(tmp_path):
    fit = fit_factory(_sessions(NOMINAL, (1, 2, 3)))
    h = fit["heldout"]
    assert fit["onnx"] is not None and h["after"]["mae_n"] < 0.5 * h["before"]["mae_n"], h
    assert fit["spec"]["source"] == "factory correction" and fit["spec"]["frames"] == 1200
    write(tmp_path / "f", fit)
    assert (tmp_path / "f" / "correction.onnx").is_file() and (tmp_path / "f" / "factory.json").is_file()
    test = NOMINAL.held_out(np.random.default_rng(9), 300)
    corr = _runtime(tmp_path, fit["spec"], fit["onnx"])
    after = np.linalg.norm(corr(test.pred_force, test.uv, test.theta_phi), axis=1)
    assert error_stats(after, test.ref_force)["mae_n"] < 0.5 * error_stats(test.pred_mag, test.ref_force)["mae_n"]


def test_a_model_without_an_error_shape_gets_no_factory_correction():
    flat = SyntheticUnit(stiffness_ratio=1.0, center_shift=(0.0, 0.0), radial_bias=0.0, magnitude_exp=0.0)
    fit = fit_factory(_sessions(flat, (1, 2)))
    assert fit["onnx"] is None and fit["spec"] is None
    with pytest.raises(CalibrationError, match="usable contact frames"):
        fit_factory(_sessions(flat, (1, 2), n=50))
    with pytest.raises(CalibrationError, match="at least 2 sessions"):
        fit_factory(_sessions(flat, (1,), n=400))


@pytest.mark.parametrize("n", [5, 7])
def test_five_pokes_refit_one_scale_on_top_of_the_factory_correction(tmp_path, n):
    fac = fit_factory(_sessions(NOMINAL, (1, 2, 3)))
    spec, onnx = fac["spec"], fac["onnx"]
    active = _runtime(tmp_path, spec, onnx, "factory.onnx")
    rng = np.random.default_rng(40 + n)
    pokes = STIFF.guided_pokes(rng, n)
    g_act = np.linalg.norm(active(pokes.pred_force, pokes.uv, pokes.theta_phi), axis=1) / pokes.pred_mag
    on_top = fit_correction(PokeSet(pokes.pred_force, pokes.ref_force, pokes.uv, pokes.theta_phi, g_act),
                            FitConfig(), active=(spec, onnx))
    alone = fit_correction(pokes)
    assert on_top.spec["scale"] == pytest.approx(1.2, abs=0.06) and on_top.spec["inputs"] == spec["inputs"]
    test = STIFF.held_out(rng, 400)
    err = {}
    for name, fit in (("on_top", on_top), ("alone", alone), ("factory", None)):
        corr = active if fit is None else _runtime(tmp_path, fit.spec, fit.onnx_bytes, f"{name}.onnx")
        err[name] = error_stats(np.linalg.norm(corr(test.pred_force, test.uv, test.theta_phi), axis=1), test.ref_force)["mae_n"]
    before = error_stats(test.pred_mag, test.ref_force)["mae_n"]
    assert err["on_top"] < 0.8 * err["alone"] and err["on_top"] < 0.5 * err["factory"] and err["alone"] < before, (err, before)


def test_an_active_correction_needs_its_gains_at_the_pokes():
    pokes = STIFF.guided_pokes(np.random.default_rng(2), 5)
    with pytest.raises(CalibrationError, match="active_gain"):
        fit_correction(pokes, FitConfig(), active=({"inputs": ["fmag"]}, b""))


def _cluster(force, uv, mm=(0.0, 0.0, 10.0)):
    return Cluster(id=1, centroid_px=uv, centroid_mm=mm, normal=(0, 0, 1), area_mm2=5.0,
                   force_n=force, force_mag_n=float(np.linalg.norm(force)), pixels=20, perimeter_px=10.0, circularity=1.0)


class _Cal:
    model_size = (32, 32)
    theta = np.tile(np.linspace(0, 1, 32), (32, 1))
    phi = np.zeros((32, 32))


def test_frame_samples_keep_single_contacts_above_the_reference_floor():
    cfg = FactoryConfig()
    frames = [(0.0, []),                                                        # no contact
              (0.1, [_cluster((0, 0, -1.0), (16.0, 16.0))]),                    # counts
              (0.2, [_cluster((0, 0, -1.0), (16.0, 16.0)),
                     _cluster((0, 0, -0.5), (2.0, 2.0), (9.0, 0.0, 5.0))]),     # a second contact far away
              (0.3, [_cluster((0, 0, -0.2), (8.0, 16.0))])]                     # reference below 0.3 N
    ref_t, ref_mag = np.array([0.0, 0.25, 0.3]), np.array([1.2, 1.2, 0.1])
    s = frame_samples(frames, ref_t, ref_mag, _Cal(), cfg)
    assert len(s) == 1 and s.ref_force[0] == pytest.approx(1.2) and s.pred_mag[0] == pytest.approx(1.0)
    assert np.allclose(s.uv[0], [0.5, 0.5]) and s.theta_phi[0, 0] == pytest.approx(np.interp(15.5, np.arange(32), np.linspace(0, 1, 32)))
