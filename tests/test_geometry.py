import numpy as np
from tensortouch.runtime.stages.geometry import DomeProfile, equidistant_theta_phi, sample_bilinear, surface_tables


def test_hemisphere_area_and_normals():
    size = 128
    theta, phi = equidistant_theta_phi((size, size), np.pi / 2)
    prof = DomeProfile(radius_mm=10.0)
    t = surface_tables(theta, phi, prof)
    # total visible area of a hemisphere is 2 pi R^2 (pixels at the rim are partial: allow 3 %)
    assert abs(t["pixel_area"].sum() / (2 * np.pi * 100.0) - 1) < 0.03
    n = t["normals"][t["mask"]]
    assert np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-5)
    p = t["surface_xyz"][t["mask"]]
    assert np.allclose(np.linalg.norm(p, axis=1), 10.0, atol=1e-4)
    # apex at the image centre, +x along columns
    c = size // 2
    assert t["surface_xyz"][c, c, 2] > 9.9
    assert t["surface_xyz"][c, size - 10, 0] > 5 and abs(t["surface_xyz"][c, size - 10, 1]) < 0.5


def test_flattened_dome_limit():
    prof = DomeProfile(radius_mm=20.0, center_z_mm=-10.0)
    assert np.isclose(prof.theta_max(), np.arccos(0.5))
    theta, phi = equidistant_theta_phi((64, 64), np.deg2rad(80))
    t = surface_tables(theta, phi, prof)
    assert t["surface_xyz"][..., 2][t["mask"]].min() >= -1e-4


def test_bilinear():
    tab = np.arange(12, dtype=float).reshape(3, 4)
    assert sample_bilinear(tab, 1.5, 1.0) == 5.5
    assert sample_bilinear(tab, 10, 10) == 11
