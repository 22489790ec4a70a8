"""GPR refresh of θ/φ tables and gel centre from poke correspondences (seed §III.G) on synthetic fisheyes."""
import numpy as np
import pytest
from tensortouch.contracts.errors import CalibrationError
from tensortouch.runtime.stages.preprocess import Preprocessor
from tensortouch.tools.recalib.gpr_geometry import camera_to_model, model_to_camera, refresh_geometry, theta_phi_from_xyz

R = 220.0                       # crop radius, camera px (640x480 camera)
SIZE = (64, 64)
C_NOMINAL = (320.0, 240.0)


class Fisheye:
    """Truth: r = f·(θ + k1·θ³) around a shifted centre, rotated by rot about the dome axis."""

    def __init__(self, center, k1, rot, theta_edge=np.deg2rad(100.0)):
        self.c, self.k1, self.rot = center, k1, rot
        self.f = R / (theta_edge + k1 * theta_edge ** 3)
        self._tg = np.linspace(0, 2.2, 20000)

    def project(self, theta, phi):
        r = self.f * (theta + self.k1 * theta ** 3)
        return np.stack([self.c[0] + r * np.cos(phi - self.rot), self.c[1] + r * np.sin(phi - self.rot)], 1)

    def theta_at(self, x, y):
        d = np.hypot(x - self.c[0], y - self.c[1])
        return np.interp(d, self.f * (self._tg + self.k1 * self._tg ** 3), self._tg)


def _pokes(rng, cam, n, noise_px):
    """The guided session's spread: apex, 4 near the rim, then mid-range (θ jittered by 2°)."""
    theta = np.deg2rad(np.array([4, 75, 75, 75, 75, 47, 47, 60, 30])[:n] + rng.normal(0, 2, n))
    phi = np.r_[0.0, np.arange(1, n) * np.pi / 2 + 0.6] + rng.normal(0, 0.1, n)
    return cam.project(theta, phi) + noise_px * rng.standard_normal((n, 2)), theta, phi


def _theta_error_deg(fit, cam, theta_max):
    vv, uu = np.mgrid[0:SIZE[0], 0:SIZE[1]].astype(float)
    x, y = Preprocessor(*fit.center, R, SIZE).to_raw(uu, vv)
    truth = cam.theta_at(x, y)
    sel = truth <= theta_max
    return float(np.degrees(np.abs(fit.theta - truth)[sel]).max())


@pytest.mark.parametrize("k1,label", [(0.0, "equidistant"), (-0.03, "measured (distorted)")])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_theta_recovered_within_half_a_degree(k1, label, seed):
    rng = np.random.default_rng(seed)
    cam = Fisheye((C_NOMINAL[0] + 6.4, C_NOMINAL[1] - 4.2), k1, rot=0.04)
    xy, th, ph = _pokes(rng, cam, 7, noise_px=0.3)
    fit = refresh_geometry(xy, th, ph, C_NOMINAL, R, SIZE)
    assert np.hypot(fit.center[0] - cam.c[0], fit.center[1] - cam.c[1]) < 1.0
    assert abs(fit.phi0 - 0.04) < np.deg2rad(0.5)
    assert _theta_error_deg(fit, cam, th.max()) < 0.5, label
    # φ table: the azimuth the camera pixel really sees
    vv, uu = np.mgrid[0:SIZE[0], 0:SIZE[1]].astype(float)
    x, y = Preprocessor(*fit.center, R, SIZE).to_raw(uu, vv)
    phi_true = np.arctan2(y - cam.c[1], x - cam.c[0]) + cam.rot
    dphi = np.angle(np.exp(1j * (fit.phi - phi_true)))
    far = np.hypot(x - cam.c[0], y - cam.c[1]) > 0.2 * R
    assert np.degrees(np.abs(dphi[far])).max() < 0.5


def test_nominal_tables_would_be_off_by_degrees():
    """The refresh matters: the nominal (unrefreshed) equidistant tables miss θ by > 1.5°."""
    rng = np.random.default_rng(0)
    cam = Fisheye((C_NOMINAL[0] + 6.4, C_NOMINAL[1] - 4.2), -0.03, rot=0.04)
    vv, uu = np.mgrid[0:SIZE[0], 0:SIZE[1]].astype(float)
    x, y = Preprocessor(*C_NOMINAL, R, SIZE).to_raw(uu, vv)
    nominal = np.hypot(x - C_NOMINAL[0], y - C_NOMINAL[1]) / R * np.deg2rad(100)
    truth = cam.theta_at(x, y)
    assert np.degrees(np.abs(nominal - truth)[truth < np.deg2rad(75)]).max() > 1.5
    xy, th, ph = _pokes(rng, cam, 7, 0.3)
    assert _theta_error_deg(refresh_geometry(xy, th, ph, C_NOMINAL, R, SIZE), cam, th.max()) < 0.5


def test_too_few_pokes_and_implausible_centre_are_refused():
    rng = np.random.default_rng(0)
    cam = Fisheye(C_NOMINAL, 0.0, 0.0)
    xy, th, ph = _pokes(rng, cam, 5, 0.3)
    with pytest.raises(CalibrationError, match="at least 6 pokes"):
        refresh_geometry(xy, th, ph, C_NOMINAL, R, SIZE)
    far = Fisheye((C_NOMINAL[0] + 90, C_NOMINAL[1]), 0.0, 0.0)
    xy, th, ph = _pokes(rng, far, 7, 0.3)
    with pytest.raises(CalibrationError, match="gel centre moved"):
        refresh_geometry(xy, th, ph, C_NOMINAL, R, SIZE)


def test_grid_camera_mapping_roundtrip_and_dome_angles():
    uv = np.array([[32.0, 32.0], [0.5, 10.25], [63.5, 40.0]])
    xy = model_to_camera(uv, C_NOMINAL, R, SIZE)
    assert np.allclose(camera_to_model(xy, C_NOMINAL, R, SIZE), uv)
    assert np.allclose(xy[0], C_NOMINAL, atol=2.0)
    th, ph = theta_phi_from_xyz(np.array([[0, 0, 16.0], [16.0, 0, 0], [0, 16 / np.sqrt(2), 16 / np.sqrt(2)]]))
    assert np.allclose(th, [0, np.pi / 2, np.pi / 4]) and np.allclose(ph[1:], [0, np.pi / 2])


@pytest.mark.parametrize("serial", ["TWIN-0001", "TWIN-0005"])
def test_twin_unit_fisheye_theta_within_half_a_degree(serial):
    """The twin's camera (cv2.fisheye model, unit-specific centre offset and focal scale): 7 pokes
    on the true gel, seen through the true camera, refresh the NOMINAL calibration's geometry."""
    twin_unit = pytest.importorskip("tensortouch.tools.twin.unit")
    unit = twin_unit.TwinUnit(serial)
    nominal = twin_unit.TwinUnit(serial, variation=twin_unit.VariationConfig(0, 0, 0, 0))
    gel, size, radius, c0 = unit.gel, (64, 64), nominal.gel_radius_px, nominal.gel_center_px
    rng = np.random.default_rng(0)
    theta = np.array([0.05, .85, .85, .85, .85, .5, .5]) * gel.rim_beta + rng.normal(0, 0.02, 7)
    phi = np.r_[0.0, np.arange(1, 7) * np.pi / 2 + 0.6] + rng.normal(0, 0.1, 7)
    pts = gel.point_at(theta, phi)
    xy = unit.model.project(pts) + 0.3 * rng.standard_normal((7, 2))
    th, ph = gel.theta_phi(pts)
    fit = refresh_geometry(xy, th, ph, c0, radius, size)
    assert np.hypot(*(np.array(fit.center) - unit.gel_center_px)) < 0.5
    vv, uu = np.mgrid[0:size[0], 0:size[1]].astype(float)
    x, y = Preprocessor(*fit.center, radius, size).to_raw(uu, vv)
    dirs, fov = unit.model.rays(np.stack([x, y], -1))
    surf, ok = gel.intersect(unit.model.center, dirs)
    truth, _ = gel.theta_phi(surf)
    sel = ok & fov & (truth <= th.max())
    assert np.degrees(np.abs(fit.theta - truth)[sel]).max() < 0.5
