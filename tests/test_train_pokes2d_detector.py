"""Stage 3: the 2D poke detector (tools/train/pokes2d.py) on synthetic dots and lenses (fast), and the
whole GPR calibration of twin units against their true lens (slow: records twin calibration sessions)."""
import numpy as np
import pytest
from tensortouch.tools.train.pokes2d import FlowPredictor, dot_centers, fit_offset, track_dots
from tensortouch.tools.twin.camera import CameraConfig, FisheyeModel
from tensortouch.tools.twin.geometry import GelSurface

GEL = GelSurface(12.0, 6.0, 2.0)


def _dots_image(xy, shape=(120, 160), radius=1.8, level=110.0):
    """Anti-aliased dark discs (the twin's skin dots are ~2 px discs ~5–7 px apart)."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    img = np.full(shape, 180.0)
    for x, y in xy:
        img -= level * np.clip(radius + 0.5 - np.hypot(xx - x, yy - y), 0.0, 1.0)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_dots_are_located_and_tracked_to_sub_pixel():
    rng = np.random.default_rng(1)
    g = np.stack(np.meshgrid(np.arange(12, 150, 7.0), np.arange(12, 110, 7.0)), -1).reshape(-1, 2)
    g = g + rng.uniform(-1.0, 1.0, g.shape)
    motion = np.column_stack([0.8 * np.sin(g[:, 1] / 20), -0.6 * np.cos(g[:, 0] / 25)])
    c = dot_centers(_dots_image(g))
    assert len(c) == len(g)
    x, v = track_dots(_dots_image(g), _dots_image(g + motion))
    assert len(x) == len(g)
    j = np.argmin(np.linalg.norm(g[None] - x[:, None], axis=2), axis=1)
    assert np.abs(x - g[j]).max() < 0.1 and np.abs(v - motion[j]).max() < 0.2
    assert np.sqrt(np.mean((v - motion[j]) ** 2)) < 0.06


def _poke_field(p3, depth=1.0, width=1.6, slide=0.15):
    """Smooth indentation: inward normal displacement + a small inward tangential pull (mm)."""
    def u(X):
        n = GEL.normals(X)
        d = X - p3
        w = np.exp(-np.sum(d * d, 1) / (2 * width ** 2))
        tang = d - np.sum(d * n, 1, keepdims=True) * n
        return -depth * w[:, None] * n - slide * w[:, None] * tang
    return u


@pytest.mark.parametrize("theta,phi", [(0.05, 0.3), (0.35, -2.0), (0.55, 1.1)])
def test_fit_offset_recovers_the_true_image_of_the_poke_through_an_unknown_lens(theta, phi):
    """Dots seen through a 'true' lens (centre off by (3.1, −2.4) px, focal +3 %), motion predicted with
    the nominal lens: the fitted point is the true lens's image of the 3D poke point."""
    true = FisheyeModel(CameraConfig(cx=159.5 + 3.1, cy=119.5 - 2.4, focal_px=74.0 * 1.03))
    nominal = FisheyeModel(CameraConfig())
    p3 = GEL.point_at(np.array([theta]), np.array([phi]))[0]
    field = _poke_field(p3)
    X = GEL.samples(1.1)
    X = X[np.linalg.norm(X - p3, axis=1) < 6]
    x = true.project(X)
    v = true.project(X + field(X)) - x
    nodes = GEL.samples(0.3)
    pred = FlowPredictor(nominal, GEL, nodes, field(nodes), nominal.project(p3))
    r = fit_offset(x, v, pred)
    q_true = true.project(p3)
    assert r["ok"] and np.hypot(*(np.array(r["xy"]) - q_true)) < 0.25
    assert np.hypot(*(nominal.project(p3) - q_true)) > 2.0           # the nominal lens alone is far off
    # without the poke's motion there is nothing to fit
    assert not fit_offset(x[:3], v[:3], pred)["ok"]


def test_image_change_centroid_is_biased_where_the_model_fit_is_not():
    """Why the detector changed: the magnitude-weighted centre of the dot motion is shifted off the
    poke point (the skin moves towards the camera, so the pattern is asymmetric) by > 1 px off-axis."""
    lens = FisheyeModel(CameraConfig())
    p3 = GEL.point_at(np.array([0.5]), np.array([0.4]))[0]
    field = _poke_field(p3)
    X = GEL.samples(1.1)
    X = X[np.linalg.norm(X - p3, axis=1) < 6]
    x = lens.project(X)
    v = lens.project(X + field(X)) - x
    w = np.sum(v * v, 1)
    centroid = (w[:, None] * x).sum(0) / w.sum()
    q = lens.project(p3)
    assert np.hypot(*(centroid - q)) > 1.0
    nodes = GEL.samples(0.3)
    r = fit_offset(x, v, FlowPredictor(lens, GEL, nodes, field(nodes), q))
    assert np.hypot(*(np.array(r["xy"]) - q)) < 0.1


@pytest.mark.slow
@pytest.mark.parametrize("serial", ["TWIN-T01", "TWIN-H01"])
def test_gpr_from_detected_pokes_recovers_the_twin_lens_within_half_a_degree(tmp_path, serial):
    """Stage 3 for real on twin data: FE-physics calibration session of the unit (9 light pokes; twin FE
    solves shared through the cache), stage-1 contacts, FE re-solved from the measured poses, the 2D
    detector, GPR → θ within 0.5° of the unit's true lens (p95 over the poked region θ ≤ 0.6 rad)."""
    from tensortouch.tools.train.build import Build, BuildConfig, SessionSpec
    from tensortouch.tools.train.correspondence import fit_unit

    b = Build(BuildConfig(train=[SessionSpec(serial, 1, 1)], heldout=[], tables="gpr"), tmp_path)
    g = fit_unit(b, serial)
    assert g["pokes"] >= 8
    err = np.hypot(*np.asarray(g["poke_px_err_vs_truth"]).T)
    assert np.sqrt(np.mean(err ** 2)) < 1.0                                   # px, detector vs exact projection
    assert g["theta_err_deg"]["p95"] < 0.5 and g["theta_err_deg"]["mean"] < 0.3
    assert g["phi_err_deg"]["p95"] < 1.0
