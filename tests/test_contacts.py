import numpy as np
import pytest
from tensortouch.runtime.stages.contacts import ContactConfig, ContactTracker, find_clusters, pixel_forces
from tensortouch.runtime.stages.geometry import DomeProfile, equidistant_theta_phi, surface_tables

SIZE = 64


def tables():
    th, ph = equidistant_theta_phi((SIZE, SIZE), np.deg2rad(90))
    return surface_tables(th, ph, DomeProfile(radius_mm=16.0))


def blob_fields(t, centres, forces_n, sigma_px=3.0):
    """Fields whose contact-normal traction integrates to `forces_n` (N, along -normal) per blob."""
    f = np.zeros((15, SIZE, SIZE), np.float32)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    for (u, v), F in zip(centres, forces_n):
        g = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma_px ** 2)) * t["mask"]
        g = g / (g * t["pixel_area"]).sum()  # traction profile integrating to 1 N
        f[9:12] += (-F * g)[None] * np.moveaxis(t["normals"], -1, 0)
    return f


def test_two_blobs_two_clusters_with_forces():
    t = tables()
    f = blob_fields(t, [(20, 32), (46, 30)], [1.0, 0.5])
    fp = pixel_forces(f, t["pixel_area"])
    cl = find_clusters(fp, t["surface_xyz"], t["normals"], t["pixel_area"], t["mask"], disp=f[0:3])
    assert len(cl) == 2
    cl.sort(key=lambda c: c.uv_px[0])
    # nearly all force lies above the 0.005 N/pixel threshold
    assert 0.9 < cl[0].force_mag_n <= 1.0 + 1e-6 and 0.4 < cl[1].force_mag_n <= 0.5 + 1e-6
    assert abs(cl[0].uv_px[0] - 20.5) < 0.6 and abs(cl[0].uv_px[1] - 32.5) < 0.6
    assert 0.7 < cl[0].circularity <= 1.0 and cl[0].perimeter_px > 0 and cl[0].area_mm2 > 0
    # the 3D centroid lies on the dome, force points into the gel
    assert abs(np.linalg.norm(cl[0].position_mm) - 16.0) < 0.5
    assert np.dot(cl[0].force_n, cl[0].normal) < 0


def test_threshold_and_zero_field():
    t = tables()
    z = np.zeros((3, SIZE, SIZE), np.float32)
    assert find_clusters(z, t["surface_xyz"], t["normals"], t["pixel_area"], t["mask"]) == []
    f = blob_fields(t, [(32, 32)], [0.01])  # spread so thin no pixel passes 0.005 N
    fp = pixel_forces(f, t["pixel_area"])
    assert fp.max() < 0.005
    assert find_clusters(fp, t["surface_xyz"], t["normals"], t["pixel_area"], t["mask"]) == []


def test_eight_connectivity_joins_diagonal_pixels():
    t = tables()
    fp = np.zeros((3, SIZE, SIZE), np.float32)
    for k in range(5):
        fp[2, 28 + k, 28 + k] = -0.1
    cl = find_clusters(fp, t["surface_xyz"], t["normals"], t["pixel_area"], t["mask"], cfg=ContactConfig(min_pixels=1))
    assert len(cl) == 1 and cl[0].pixels == 5


def test_tracker_keeps_ids_and_ranks():
    t = tables()
    tr = ContactTracker()
    ids = None
    for step in range(6):
        f = blob_fields(t, [(20 + step * 0.5, 32), (46, 30)], [0.4, 1.0])
        fp = pixel_forces(f, t["pixel_area"])
        cl = tr.update(find_clusters(fp, t["surface_xyz"], t["normals"], t["pixel_area"], t["mask"]))
        now = {round(c.uv_px[1]): c.id for c in cl}
        if ids is not None:
            assert now == ids  # same ids frame to frame
        ids = now
        assert cl[0].force_mag_n > cl[1].force_mag_n  # strongest first
    assert all(c.age_frames == 5 for c in cl)
    # a new contact far away gets a fresh id
    f = blob_fields(t, [(32, 10)], [1.0])
    cl = tr.update(find_clusters(pixel_forces(f, t["pixel_area"]), t["surface_xyz"], t["normals"], t["pixel_area"], t["mask"]))
    assert cl[0].id not in ids.values() and cl[0].age_frames == 0


def test_indentation_is_the_deepest_inward_displacement_of_the_cluster():
    t = tables()
    f = blob_fields(t, [(20, 32), (46, 30)], [1.0, 0.5])
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    for (u, v), depth in (((20, 32), 1.2), ((46, 30), 0.4)):    # a Gaussian dent under each blob
        dent = depth * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 4.0 ** 2)) * t["mask"]
        f[0:3] -= dent[None] * np.moveaxis(t["normals"], -1, 0)  # inward = against the outward normal
    fp = pixel_forces(f, t["pixel_area"])
    cl = sorted(find_clusters(fp, t["surface_xyz"], t["normals"], t["pixel_area"], t["mask"], disp=f[0:3]),
                key=lambda c: c.uv_px[0])
    assert [round(c.indentation_mm, 3) for c in cl] == [1.2, 0.4]
    # the force-weighted centroid sits on the flank of the dent, shallower than its deepest point
    assert 16.0 - np.linalg.norm(cl[0].position_mm) < 1.2
    no_disp = find_clusters(fp, t["surface_xyz"], t["normals"], t["pixel_area"], t["mask"])
    assert all(c.indentation_mm == 0.0 for c in no_disp)


def test_light_touch_rule_finds_a_broad_weak_contact_and_leaves_strong_ones_as_they_were():
    t = tables()
    args = (t["surface_xyz"], t["normals"], t["pixel_area"], t["mask"])
    strong = blob_fields(t, [(20, 32)], [1.0])
    light = blob_fields(t, [(46, 30)], [0.3], sigma_px=6.0)       # spread thinner than the strong threshold
    fp = pixel_forces(strong + light, t["pixel_area"])
    peak_light = np.linalg.norm(pixel_forces(light, t["pixel_area"]), axis=0).max()
    cfg0 = ContactConfig(threshold_n=1.5 * peak_light)
    base = find_clusters(fp, *args, cfg=cfg0)
    assert len(base) == 1                                           # the light touch is missed ...
    rule = ContactConfig(threshold_n=cfg0.threshold_n, weak_threshold_n=0.25 * peak_light, min_total_n=0.2)
    cl = sorted(find_clusters(fp, *args, cfg=rule), key=lambda c: c.uv_px[0])
    assert len(cl) == 2                                             # ... and found by its total force
    assert 0.25 < cl[1].force_mag_n <= 0.3 + 1e-6 and abs(cl[1].uv_px[0] - 46.5) < 1.0
    # the strong contact keeps its core; only the light touch's tail no longer joins its support
    assert cl[0].pixels == base[0].pixels and abs(cl[0].force_mag_n - base[0].force_mag_n) < 0.01
    assert abs(cl[0].uv_px[0] - 20.5) < 0.6
    # a weak component whose total stays below min_total_n is not a contact; the rule off = the old result
    assert len(find_clusters(fp, *args, cfg=ContactConfig(threshold_n=cfg0.threshold_n,
                                                          weak_threshold_n=0.25 * peak_light, min_total_n=0.4))) == 1
    assert len(find_clusters(fp, *args, cfg=ContactConfig(threshold_n=cfg0.threshold_n,
                                                          weak_threshold_n=0.25 * peak_light))) == 1


def test_cores_bridged_above_merge_n_are_one_cluster_with_the_summed_force():
    from dataclasses import replace

    from tensortouch.runtime.stages.contacts import ContactConfig, find_clusters

    s = 64
    v, u = np.mgrid[0:s, 0:s].astype(float)
    xyz = np.stack([u * 0.2, v * 0.2, np.zeros_like(u)], -1)
    normals = np.zeros((s, s, 3))
    normals[..., 2] = 1.0
    area, mask = np.full((s, s), 0.04), np.ones((s, s), bool)
    fp = np.zeros((3, s, s))
    fp[2, 31:34, 20:45] = -0.0015                      # the bridge, below the core threshold
    for c in (20, 44):
        fp[2, 31:34, c - 1:c + 2] = -0.004
    base = ContactConfig(support_radius_px=0.0)
    apart = find_clusters(fp, xyz, normals, area, mask, cfg=base)
    merged = find_clusters(fp, xyz, normals, area, mask, cfg=replace(base, merge_n=0.0012))
    assert len(apart) == 2 and len(merged) == 1
    assert merged[0].force_mag_n == pytest.approx(sum(c.force_mag_n for c in apart))
    assert merged[0].pixels == sum(c.pixels for c in apart)
    # a bridge below merge_n does not join them
    assert len(find_clusters(fp, xyz, normals, area, mask, cfg=replace(base, merge_n=0.0016))) == 2
    # splitting leaves what merging joined whole (the dip across the bridge is 60 %, the split asks 50 %)
    assert len(find_clusters(fp, xyz, normals, area, mask, cfg=replace(base, merge_n=0.0012, split_dip=0.5))) == 1


def _plane(s=64):
    v, u = np.mgrid[0:s, 0:s].astype(float)
    xyz = np.stack([u * 0.2, v * 0.2, np.zeros_like(u)], -1)
    normals = np.zeros((s, s, 3))
    normals[..., 2] = 1.0
    return xyz, normals, np.full((s, s), 0.04), np.ones((s, s), bool)


def test_split_dip_splits_two_joined_presses_and_keeps_a_shallow_dip_whole():
    from dataclasses import replace

    xyz, normals, area, mask = _plane()
    v, u = np.mgrid[0:64, 0:64].astype(float)

    def bumps(peaks, centres=(20, 44), sigma=6.0):
        g = sum(p * np.exp(-((u - c) ** 2 + (v - 32) ** 2) / (2 * sigma ** 2)) for p, c in zip(peaks, centres))
        return np.stack([np.zeros_like(g), np.zeros_like(g), -g])

    base = ContactConfig(threshold_n=0.001, support_radius_px=0.0)
    # two presses 24 px apart whose fields join far above the threshold: one core
    fp = bumps((0.006, 0.005))
    saddle = float(-fp[2, 32, 32])
    assert 0.001 < saddle and saddle / 0.005 < 0.4          # the field dips by > 60 % of the weaker peak
    whole = find_clusters(fp, xyz, normals, area, mask, cfg=base)
    assert len(whole) == 1
    parts = find_clusters(fp, xyz, normals, area, mask, cfg=replace(base, split_dip=0.5))
    assert len(parts) == 2
    parts.sort(key=lambda c: c.uv_px[0])
    assert abs(parts[0].uv_px[0] - 20.5) < 1.5 and abs(parts[1].uv_px[0] - 44.5) < 1.5
    # nothing lost or counted twice, and the bigger press holds more
    assert sum(c.force_mag_n for c in parts) == pytest.approx(whole[0].force_mag_n, rel=1e-9)
    assert sum(c.pixels for c in parts) == whole[0].pixels and parts[0].force_mag_n > parts[1].force_mag_n
    assert all(c.perimeter_px > 0 and 0 < c.circularity <= 1 for c in parts)
    # the dip must be as deep as asked for: at 0.8 (level 0.001 N, below the 0.0015 N saddle) it stays one
    assert len(find_clusters(fp, xyz, normals, area, mask, cfg=replace(base, split_dip=0.8))) == 1
    # one contact with a shallow dip (peaks 12 px apart): one cluster at 0.5
    near = bumps((0.006, 0.005), centres=(26, 38))
    assert len(find_clusters(near, xyz, normals, area, mask, cfg=replace(base, split_dip=0.5))) == 1
    # off (0) leaves the clusters as they were, bit for bit
    same = find_clusters(fp, xyz, normals, area, mask, cfg=replace(base, split_dip=0.0))
    assert [c.to_dict() for c in same] == [c.to_dict() for c in whole]


def test_split_dip_keeps_a_noisy_single_press_whole():

    xyz, normals, area, mask = _plane()
    v, u = np.mgrid[0:64, 0:64].astype(float)
    g = 0.006 * np.exp(-((u - 32) ** 2 + (v - 32) ** 2) / (2 * 6.0 ** 2))
    g = g * (1 + 0.05 * np.random.default_rng(0).standard_normal(g.shape))    # many local maxima
    fp = np.stack([np.zeros_like(g), np.zeros_like(g), -g])
    cl = find_clusters(fp, xyz, normals, area, mask, cfg=ContactConfig(threshold_n=0.001, support_radius_px=0.0,
                                                                       split_dip=0.5))
    assert len(cl) == 1
