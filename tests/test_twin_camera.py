"""Twin camera and unit: fisheye model vs cv2.fisheye, rendering sanity, true calibration."""
import cv2
import numpy as np
import pytest
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.stages.preprocess import Preprocessor
from tensortouch.tools.twin.camera import CameraConfig, FisheyeModel
from tensortouch.tools.twin.geometry import GelSurface
from tensortouch.tools.twin.unit import TwinUnit, true_tables, unit_params, write_true_calibration


def test_projection_matches_cv2_fisheye():
    gel = GelSurface()
    k = (0.02, -0.01, 0.003, 0.0)
    m = FisheyeModel(CameraConfig(k=k))
    P = gel.samples(1.0)
    K = np.array([[m.cfg.focal_px, 0, m.cfg.cx], [0, m.cfg.focal_px, m.cfg.cy], [0, 0, 1.0]])
    uv, _ = cv2.fisheye.projectPoints((P - m.center).reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.array(k))
    np.testing.assert_allclose(m.project(P), uv.reshape(-1, 2), atol=1e-9)
    dirs, ok = m.rays(m.project(P))
    back, hit = gel.intersect(m.center, dirs)
    assert ok.all() and hit.all()
    np.testing.assert_allclose(back, P, atol=1e-8)


def test_fov_and_rim():
    gel, m = GelSurface(), FisheyeModel(CameraConfig())
    rim = m.rim_radius_px(gel)
    assert 80 < rim < min(m.cfg.width, m.cfg.height) / 2  # the whole gel is in the frame
    _, ok = m.rays(np.array([[m.cfg.cx + m.cfg.focal_px * np.radians(115), m.cfg.cy]]))
    assert not ok[0]  # beyond the 220 degree field


@pytest.fixture(scope="module")
def renderer():
    return TwinUnit("TWIN-CAM").renderer


def _press(r, depth, sigma=2.0, shift=0.0):
    X = r.view.points
    rr2 = (X[..., 0] - 1.0) ** 2 + X[..., 1] ** 2
    u = np.zeros_like(X)
    bump = np.exp(-rr2 / (2 * sigma ** 2)) * r.view.mask
    u[..., 2] = -depth * bump
    u[..., 0] = shift * bump
    return u


def test_zero_contact_equals_rest_up_to_noise(renderer):
    rest = renderer.render_float(None)
    sigma = renderer.noise.read_sigma
    frames = [renderer.render(np.zeros_like(renderer.view.points), 1.0, np.random.default_rng(i)) for i in range(3)]
    for f in frames:
        d = f.astype(np.float64) / 255 - rest
        assert abs(d.mean()) < 0.002
        assert d.std() < 2.5 * np.sqrt(sigma ** 2 + renderer.noise.shot_sigma ** 2) + 1 / 255
    assert not np.array_equal(frames[0], frames[1])  # noise is on


def test_deeper_press_larger_image_difference(renderer):
    rest = renderer.render_float(None)
    diffs = [np.abs(renderer.render_float(_press(renderer, d)) - rest).mean() for d in (0.25, 0.5, 1.0, 2.0)]
    assert all(a < b for a, b in zip(diffs, diffs[1:])), diffs


def test_in_plane_motion_visible(renderer):
    """Pure in-plane skin motion moves the dots: visible even without normal deformation."""
    rest = renderer.render_float(None)
    moved = renderer.render_float(_press(renderer, 0.0, shift=0.5))
    assert np.abs(moved - rest).max() > 0.2


def test_render_speed_reasonable(renderer):
    import time

    u = _press(renderer, 1.5)
    t = time.perf_counter()
    for i in range(5):
        renderer.render(u, 1.0, np.random.default_rng(i))
    assert (time.perf_counter() - t) / 5 < 0.25  # camera rate is benchmarked in docs/BENCHMARKS.md


def test_unit_variation_reproducible():
    a, b, c = unit_params("TWIN-A"), unit_params("TWIN-A"), unit_params("TWIN-B")
    assert a == b and a != c
    assert 0.85 < a.stiffness_scale < 1.15 and len(a.led_brightness) == 9


def test_true_calibration_consistent(tmp_path):
    unit = TwinUnit("TWIN-CAL")
    t = true_tables(unit, 64)
    m = t["mask"]
    assert 0.6 < m.mean() < 0.8
    # θ/φ follow runtime.stages.geometry.DomeProfile on the cap
    prof = unit.gel.profile
    cap = m & (t["surface_xyz"][..., 2] > unit.gel.skirt + 1e-6)
    np.testing.assert_allclose(prof.point(t["theta"], t["phi"])[cap], t["surface_xyz"][cap], atol=1e-6)
    # each model pixel's surface point projects back to that pixel's raw camera position
    pre = Preprocessor(*unit.gel_center_px, unit.gel_radius_px, 64)
    v, u = np.mgrid[0:64, 0:64]
    raw = np.stack(pre.to_raw(u, v), -1)
    np.testing.assert_allclose(unit.model.project(t["surface_xyz"])[m], raw[m], atol=1e-6)
    # total area = dome area (cap + skirt), within the pixel discretisation
    g = unit.gel
    area = 2 * np.pi * g.profile.radius_mm * g.cap_height + 2 * np.pi * g.radius * g.skirt
    assert abs(t["pixel_area"][m].sum() / area - 1) < 0.03
    version = write_true_calibration(unit, tmp_path, 64)
    cal = CalibrationStore(tmp_path).load("TWIN-CAL")
    assert cal.version == version and cal.meta["provenance"]["method"] == "twin-truth"
    np.testing.assert_allclose(cal.gel_center_px, unit.gel_center_px)
    np.testing.assert_array_equal(cal.mask, m)
    assert write_true_calibration(unit, tmp_path, 64) == version              # unchanged: kept
    assert write_true_calibration(unit, tmp_path, 64, force=True) != version  # forced: new version
