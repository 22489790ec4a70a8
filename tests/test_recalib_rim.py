"""Geometry first: re-centring the crop on the gel rim of a rest image (tools/recalib/rim.py).

Real twin renderings (tools.twin: the unit's cv2.fisheye camera with its centre offset and focal
scale, LED brightness and sensor noise) and synthetic images for the refusals."""
import numpy as np
import pytest
from tensortouch.contracts.errors import CalibrationError
from tensortouch.tools.recalib.rim import RimConfig, crop_changes, fit_rim, recrop, rest_image


def _twin(serial, offset=(0.0, 0.0), focal=1.0):
    from tensortouch.tools.twin.unit import TwinUnit

    return TwinUnit(serial, override={"center_offset_px": list(offset), "focal_scale": focal, "stiffness_scale": 1.0})


def _rest(unit, n=3):
    r = unit.renderer
    r = r() if callable(r) else r
    return rest_image([r.render(None, 1.0, np.random.default_rng(i)) for i in range(n)])


@pytest.fixture(scope="module")
def nominal():
    return _twin("TWIN-RIM0")


@pytest.mark.parametrize("offset,focal", [((4.0, -3.0), 0.97), ((-5.0, 2.0), 1.03), ((0.0, -6.0), 1.0)])
def test_rim_finds_the_twin_units_centre_and_radius_from_the_nominal_crop(nominal, offset, focal):
    unit = _twin("TWIN-RIM1", offset, focal)
    fit = fit_rim(_rest(unit), nominal.gel_center_px, nominal.gel_radius_px)
    err = np.hypot(fit.center[0] - unit.gel_center_px[0], fit.center[1] - unit.gel_center_px[1])
    assert err < 0.3, (fit, unit.gel_center_px)                       # was 4.7–6 px off
    assert fit.radius == pytest.approx(unit.gel_radius_px, rel=0.004)
    assert fit.shift_px == pytest.approx(np.hypot(*offset), abs=0.3)
    assert fit.rms_px < 0.5 and fit.points > 0.9 * RimConfig().rays


def test_unit_without_offset_keeps_its_crop(nominal):
    fit = fit_rim(_rest(nominal), nominal.gel_center_px, nominal.gel_radius_px)

    class Cal:
        meta = {"gel_center_px": list(nominal.gel_center_px), "gel_radius_px": nominal.gel_radius_px}

    assert crop_changes(Cal, fit) == {}
    assert recrop(Cal, {}) is Cal


def test_recrop_changes_only_the_crop(nominal):
    from dataclasses import dataclass

    unit = _twin("TWIN-RIM2", (4.0, -3.0), 0.97)
    fit = fit_rim(_rest(unit), nominal.gel_center_px, nominal.gel_radius_px)

    @dataclass
    class Cal:
        meta: dict
        theta: np.ndarray

    cal = Cal({"gel_center_px": list(nominal.gel_center_px), "gel_radius_px": nominal.gel_radius_px, "x": 1},
              np.ones((4, 4)))
    ch = crop_changes(cal, fit)
    assert set(ch) == {"gel_center_px", "gel_radius_px"}
    new = recrop(cal, ch)
    assert new.theta is cal.theta and new.meta["x"] == 1
    assert new.meta["gel_center_px"] == pytest.approx(list(fit.center)) and cal.meta["gel_center_px"] != new.meta["gel_center_px"]


def _disc(center, radius, shape=(240, 320)):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    img = np.where((xx - center[0]) ** 2 + (yy - center[1]) ** 2 <= radius ** 2, 150.0, 0.0)
    return img + np.random.default_rng(0).normal(0, 1.0, shape)


def test_dark_image_is_refused_with_a_clear_message():
    with pytest.raises(CalibrationError, match="rim was found on"):
        fit_rim(np.zeros((240, 320)), (160, 120), 100, where="camera /dev/video0")


def test_rim_far_from_the_stored_crop_is_refused():
    with pytest.raises(CalibrationError, match="recalibrate at the bench"):
        fit_rim(_disc((160 + 25, 120), 100), (160, 120), 100)


def test_gel_that_fills_no_circle_is_refused():
    img = _disc((160, 120), 100)
    img[:, 160:] = 0.0                               # half the disc dark (occluded / unlit)
    with pytest.raises(CalibrationError):
        fit_rim(img, (160, 120), 100)


def test_synthetic_disc_centre_is_subpixel():
    fit = fit_rim(_disc((161.3, 118.6), 98.0), (160, 120), 100)
    assert fit.center == pytest.approx((161.3, 118.6), abs=0.3)
    assert fit.radius == pytest.approx(98.0, abs=0.7)
