"""Stage 4 core (seed §III.H): FE surface data → 15-channel field images, on analytic fields."""
import json

import numpy as np
import pytest
from tensortouch.contracts.fields import CHANNELS
from tensortouch.tools.train.fields import (
    FieldConfig,
    FieldDataError,
    attribute_contacts,
    compute_bounds,
    contact_force_from_image,
    denormalize,
    fe_to_fields,
    interpolate_to_grid,
    normalize_global,
    normalize_per_image,
    read_bounds,
    surface_angles,
    transfer_nearest,
    tributary_area,
    write_bounds,
)

R = 16.0          # hemisphere radius, mm


def hemisphere_nodes(n=3000):
    """Fibonacci points on the upper hemisphere (θ ≤ 90°), about 0.7 mm apart."""
    i = np.arange(n) + 0.5
    z = 1.0 - i / n                               # uniform in z ∈ (0, 1] → uniform area
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z ** 2)
    pts = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    return R * np.concatenate([[[0, 0, 1.0]], pts, _rim()], 0)


def _rim(m=144):
    a = np.linspace(-np.pi, np.pi, m, endpoint=False)
    return np.stack([np.cos(a), np.sin(a), 0 * a], 1)


def fisheye_tables(size=96, theta_max=np.pi / 2):
    """Equidistant fisheye looking up +z: r_px = c·θ. Returns θ, φ, pixel_area (mm²)."""
    c = (size / 2) / theta_max
    yy, xx = np.mgrid[0:size, 0:size] + 0.5 - size / 2
    r = np.hypot(xx, yy)
    theta = r / c
    phi = np.arctan2(yy, xx)
    with np.errstate(invalid="ignore", divide="ignore"):
        area = np.where(theta > 0, R ** 2 * np.sin(theta) / (c ** 2 * theta), R ** 2 / c ** 2)
    area = np.where(theta <= theta_max, area, 0.0)
    return theta, phi, area


def hertz(nodes, theta_c, phi_c, a=3.0, p0=0.2):
    """Hertz pressure (MPa) around the surface point at (θc, φc); per-node normal force (N) = −n·p·A."""
    c = R * np.array([np.sin(theta_c) * np.cos(phi_c), np.sin(theta_c) * np.sin(phi_c), np.cos(theta_c)])
    n = nodes / np.linalg.norm(nodes, axis=1, keepdims=True)
    arc = R * np.arccos(np.clip(n @ (c / R), -1, 1))
    p = p0 * np.sqrt(np.clip(1 - (arc / a) ** 2, 0, None))
    return p, n, 2.0 / 3.0 * p0 * np.pi * a ** 2


@pytest.fixture(scope="module")
def dome():
    nodes = hemisphere_nodes()
    area = tributary_area(nodes)
    return nodes, area


def test_tributary_area_sums_to_hemisphere(dome):
    nodes, area = dome
    assert area.sum() == pytest.approx(2 * np.pi * R ** 2, rel=0.01)


@pytest.mark.parametrize("phi_c", [np.pi, 0.4])          # on the φ = ±π seam, and away from it
def test_hertz_contact_integrates_back_to_total_force(dome, phi_c):
    nodes, area = dome
    p, n, f_total = hertz(nodes, 0.7, phi_c)
    fn = -n * (p * area)[:, None]
    zeros3 = np.zeros_like(nodes)
    theta, phi, pix_area = fisheye_tables(96)
    img = fe_to_fields(nodes, zeros3, np.zeros((len(nodes), 6)), fn, zeros3, theta, phi, pix_area,
                       node_area=area)
    assert img.shape == (15, 96, 96) and img.dtype == np.float32
    f_img, s_img = contact_force_from_image(img, pix_area)
    expected = -(n * (p * area)[:, None]).sum(0)
    assert np.linalg.norm(expected) == pytest.approx(f_total, rel=0.02)      # test fixture sanity
    assert np.linalg.norm(f_img) == pytest.approx(f_total, rel=0.04)
    np.testing.assert_allclose(f_img, expected, atol=0.04 * f_total)
    assert np.abs(s_img).max() == 0.0
    # peak traction recovered (σ = 2 px smoothing lowers it a little), in MPa
    peak = np.linalg.norm(img[9:12], axis=0).max()
    assert 0.15 < peak <= 0.2 * 1.01


def test_phi_wraparound_has_no_seam(dome):
    nodes, _ = dome
    th, ph = surface_angles(nodes)
    # smooth field across the seam: depends on φ through cos/sin only
    vals = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(2 * ph) * th], 1)
    theta, phi, pix_area = fisheye_tables(96)
    mask = pix_area > 0
    out = interpolate_to_grid(th, ph, vals, theta, phi, mask)
    truth = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(2 * phi) * theta])
    err = np.abs(out - truth)[:, mask]
    assert err.max() < 0.03
    near_seam = (np.abs(np.abs(phi) - np.pi) < 0.15)[mask]
    assert err[:, near_seam].max() < 0.03
    # without padding the seam rows are extrapolated (nearest) and visibly wrong
    bare = interpolate_to_grid(th, ph, vals, theta, phi, mask, FieldConfig(phi_pad_rad=0.0))
    assert np.abs(bare - truth)[:, mask][:, near_seam].max() > 2 * err[:, near_seam].max()


def test_displacement_and_stress_channels_map_in_order(dome):
    nodes, area = dome
    u = np.tile([0.1, -0.2, 0.3], (len(nodes), 1))
    s = np.tile([1, 2, 3, 4, 5, 6], (len(nodes), 1)) * 0.01
    theta, phi, pix_area = fisheye_tables(64)
    z3 = np.zeros_like(nodes)
    img = fe_to_fields(nodes, u, s, z3, z3, theta, phi, pix_area, node_area=area)
    m = pix_area > 0
    expect = [0.1, -0.2, 0.3, .01, .02, .03, .04, .05, .06] + [0] * 6
    for c, v in enumerate(expect):
        np.testing.assert_allclose(img[c][m], v, atol=1e-6, err_msg=CHANNELS[c])
        assert np.all(img[c][~m] == 0)


def test_kdtree_transfer_to_denser_surface(dome):
    nodes, _ = dome
    vals = nodes[:, 2:3] * 2
    dense = nodes[:200] * 1.0001
    out, dist = transfer_nearest(nodes, vals, dense)
    np.testing.assert_allclose(out[:, 0], vals[:200, 0])
    assert dist.max() < 0.01


def test_shape_errors_name_the_field(dome):
    nodes, area = dome
    theta, phi, pix_area = fisheye_tables(32)
    with pytest.raises(FieldDataError, match="contact_shear"):
        fe_to_fields(nodes, nodes * 0, np.zeros((len(nodes), 6)), nodes * 0, np.zeros((3, 3)),
                     theta, phi, pix_area, node_area=area)


def test_bounds_json_roundtrip_and_normalization(tmp_path):
    rng = np.random.default_rng(0)
    imgs = [rng.normal(size=(15, 8, 8)) * (np.arange(15)[:, None, None] + 1) for _ in range(4)]
    b = compute_bounds(imgs)
    assert list(b) == list(CHANNELS)
    write_bounds(tmp_path / "bounds.json", b)
    doc = json.loads((tmp_path / "bounds.json").read_text())
    assert doc["channels"] == list(CHANNELS) and doc["units"][0] == "mm" and doc["units"][-1] == "MPa"
    b2 = read_bounds(tmp_path / "bounds.json")
    y = normalize_global(imgs[0], b2)
    assert y.min() >= 0 and y.max() <= 1
    np.testing.assert_allclose(denormalize(y, b2), imgs[0], atol=1e-5 * 15)
    yl, lo, hi = normalize_per_image(imgs[1])
    assert np.allclose(yl.reshape(15, -1).min(1), 0) and np.allclose(yl.reshape(15, -1).max(1), 1)
    doc["channels"] = doc["channels"][::-1]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(FieldDataError, match="bad.json"):
        read_bounds(tmp_path / "bad.json")


def test_kmeans_attribution_to_nearest_indenters():
    rng = np.random.default_rng(1)
    ind = np.array([[5.0, 0, 14], [-5.0, 2, 14], [0, -6, 13]])
    pts, truth = [], []
    for k, c in enumerate(ind):
        pts.append(c + rng.normal(scale=0.8, size=(40, 3)) - [0, 0, 0.5]); truth += [k] * 40
    pts = np.concatenate(pts)
    perm = rng.permutation(len(pts))
    labels = attribute_contacts(pts[perm], ind[[2, 0, 1]])   # indenter order does not matter
    np.testing.assert_array_equal(labels, np.argsort([2, 0, 1])[np.array(truth)[perm]])
    assert np.all(attribute_contacts(pts, ind[:1]) == 0)
