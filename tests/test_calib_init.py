"""`tensortouch calib init`: the gel rim found with no prior crop, nominal θ/φ from the lens model.

Real parts: the shipped demo recording (a twin unit with an off-centre, rescaled lens) through the
replay camera, the calibration store in tmp. The unit's exact tables (calibration_store/TWIN-DEMO,
written from the twin's own ray tracing) are the reference.
"""
import argparse

import numpy as np
import pytest
from tensortouch.contracts import paths
from tensortouch.contracts.errors import CalibrationError, TensorTouchError
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.calib.bringup import GelShape, LensModel, find_gel, nominal_tables
from tensortouch.runtime.shells import commands

pytestmark = pytest.mark.skipif(not (paths.demo_dir() / "session.json").is_file(), reason="no demo recording")


def parse(argv):
    parser = argparse.ArgumentParser()
    commands.register(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


def test_calib_init_finds_the_rim_and_writes_nominal_tables(tmp_path, capsys):
    store = CalibrationStore(tmp_path / "store")
    args = parse(["calib", "init", "--source", f"replay:{paths.demo_dir()}?realtime=0", "--sensor", "NEW-7",
                  "--store", str(store.root)])
    assert args.func(args) == 0
    assert "nominal calibration v0001" in capsys.readouterr().out
    cal = store.load("NEW-7")
    truth = CalibrationStore().load("TWIN-DEMO")
    assert np.hypot(*np.subtract(cal.gel_center_px, truth.gel_center_px)) < 0.5
    assert abs(cal.gel_radius_px / truth.gel_radius_px - 1) < 0.005
    prov = cal.meta["provenance"]
    assert prov["method"] == "nominal-lens" and prov["lens"]["model"] == "equidistant" and prov["lens"]["fov_deg"] == 220.0
    assert prov["rim"]["rms_px"] < 1.0 and prov["source"].startswith("replay:")
    assert cal.meta["camera"] == {"width": 320, "height": 240} and cal.model_size == truth.model_size
    both = cal.mask & truth.mask
    assert both.sum() > 0.75 * truth.mask.sum()
    err = np.degrees(np.abs(cal.theta - truth.theta)[both])
    assert err.max() < 1.0 and err.mean() < 0.3, (err.max(), err.mean())   # a 0.2 px rim error, nothing else
    off_axis = both & (truth.theta > np.radians(10))           # φ is ill-defined at the apex
    dphi = np.angle(np.exp(1j * (cal.phi - truth.phi)))[off_axis]
    assert np.degrees(np.abs(dphi)).mean() < 1.0
    # where each pixel lands on the gel: within 0.25 mm everywhere (the rim fit is 0.2 px off)
    dist = np.linalg.norm(cal.surface_xyz - truth.surface_xyz, axis=-1)[both]
    assert dist.max() < 0.25, dist.max()
    assert abs(cal.pixel_area[both].sum() / truth.pixel_area[both].sum() - 1) < 0.02
    # a second init on a known sensor is refused without --force
    with pytest.raises(CalibrationError, match="already has calibration v0001"):
        args.func(args)


def test_a_wrong_lens_model_gives_a_different_theta():
    """The tables come from the lens model: a narrower gel or a camera lower down changes θ."""
    a = nominal_tables((160, 120), 110, (64, 64))
    b = nominal_tables((160, 120), 110, (64, 64), LensModel(camera_z_mm=-4.0))
    c = nominal_tables((160, 120), 110, (64, 64), gel=GelShape(base_radius_mm=12, cap_height_mm=12, skirt_mm=0))
    m = a["mask"] & b["mask"] & c["mask"]
    assert np.abs(a["theta"] - b["theta"])[m].max() > 0.02 and np.abs(a["theta"] - c["theta"])[m].max() > 0.02


def test_no_gel_in_view_is_a_clear_error():
    with pytest.raises(CalibrationError, match="gel"):
        find_gel(np.full((120, 160), 40.0))
    noise = np.random.default_rng(0).uniform(0, 255, (120, 160))
    with pytest.raises(CalibrationError):
        find_gel(noise)


def test_bad_gel_argument(tmp_path):
    args = parse(["calib", "init", "--source", f"replay:{paths.demo_dir()}", "--sensor", "X", "--gel", "12,6",
                  "--store", str(tmp_path)])
    with pytest.raises(TensorTouchError, match="--gel '12,6': expected BASE,CAP,SKIRT"):
        args.func(args)
