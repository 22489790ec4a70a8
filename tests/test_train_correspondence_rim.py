"""Stage 3's crop at the unit's measured rim (`crop = "rim"`, issue #42): the calibration session's rest
frames give the unit's rim radius, as `calib init` finds it on a rig, instead of the design's. Real chain on
a tiny twin calibration session (analytic twin physics)."""
import numpy as np
import pytest

pytest.importorskip("cv2")


def _calibration_session(tmp_path, serial):
    from tensortouch.tools.train.build import Build, BuildConfig, SessionSpec
    from tensortouch.tools.train.correspondence import CorrespondenceConfig, record_calibration_session

    b = Build(BuildConfig(train=[SessionSpec(serial, 1, 1)], heldout=[], tables="gpr", physics="hertz-fallback"),
              tmp_path)
    return record_calibration_session(b, serial, CorrespondenceConfig(pokes=1))


@pytest.mark.parametrize("serial", ["TWIN-T05", "TWIN-H07"])
def test_session_rim_finds_the_units_rim_not_the_design_radius(tmp_path, serial):
    from tensortouch.tools.train.correspondence import session_rim
    from tensortouch.tools.twin.unit import TwinUnit, VariationConfig

    unit, nominal = TwinUnit(serial), TwinUnit(serial, variation=VariationConfig(0.0, 0.0, 0.0, 0.0))
    assert abs(unit.gel_radius_px - nominal.gel_radius_px) > 1.5          # these units' focal differs from the design
    rim = session_rim(_calibration_session(tmp_path, serial), nominal.gel_center_px, nominal.gel_radius_px)
    assert abs(rim.radius - unit.gel_radius_px) < 0.5                     # px; the design radius is > 1.5 px off
    assert np.hypot(*(np.asarray(rim.center) - unit.gel_center_px)) < 0.5


def test_a_session_that_starts_in_contact_has_no_rest_frames(tmp_path):
    from tensortouch.contracts.session import load_session
    from tensortouch.tools.train.correspondence import CorrespondenceConfig, CorrespondenceError, session_rim

    path = _calibration_session(tmp_path, "TWIN-T05")
    t0 = float(load_session(path).table("frames")[0, 0])
    with pytest.raises(CorrespondenceError, match="no frame before the first contact"):
        session_rim(path, (160.0, 120.0), 110.0, CorrespondenceConfig(rest_margin_s=1e3 + t0))


def test_crop_enters_the_correspondence_key_only_when_not_nominal():
    from tensortouch.tools.train.build import BuildConfig, stage_keys

    base, rim = stage_keys(BuildConfig()), stage_keys(BuildConfig(crop="rim"))
    assert base["correspondence"] != rim["correspondence"] and base["fe"] == rim["fe"]
    assert base == stage_keys(BuildConfig(crop="nominal"))
