"""Stages 3, 4 (dataset shell) and 8 cores of `tensortouch train all` (tools/train/*)."""
import numpy as np
from tensortouch.contracts.fields import CHANNELS
from tensortouch.tools.train.correspondence import image_change_centroid, project_to_cap, tables_from_theta_phi
from tensortouch.tools.train.dataset import DatasetConfig, FieldProjector, select_frames, write_dataset
from tensortouch.tools.train.evaluate import frame_errors, has_phantom, summarize
from tensortouch.tools.train.fields import FieldConfig, fe_to_fields, read_bounds, tributary_area
from tensortouch.tools.train.model.data import load_split, read_index

# ---------------------------------------------------------------- stage 4 shell: sample selection

def test_select_frames_strides_pokes_and_keeps_rest_samples():
    fp = np.array([-1] * 10 + [0] * 9 + [-1] * 8 + [1] * 7 + [-1] * 6)
    cfg = DatasetConfig(contact_stride=3, rest_fraction=0.25, master_baseline_share=0.0)
    picks = select_frames(fp, cfg)
    contact = [p for p in picks if p[2] >= 0]
    rest = [p for p in picks if p[2] < 0]
    assert {i for i, _, p in contact if p == 0} == {10, 13, 16, 18}          # stride 3, first and last kept
    assert {i for i, _, p in contact if p == 1} == {27, 30, 33}
    assert all(b == 9 for _, b, p in contact if p == 0)                     # last rest frame before poke 0
    assert all(b == 26 for _, b, p in contact if p == 1)
    assert len(rest) == round(0.25 * len(contact)) and all(fp[i] < 0 for i, _, _ in rest)
    assert all(fp[b] < 0 for _, b, _ in picks)                              # baselines are rest frames
    master = select_frames(fp, DatasetConfig(master_baseline_share=1.0))
    assert {b for _, b, _ in master} == {DatasetConfig().master_frame}


def _dome_nodes(n=400, seed=0):
    rng = np.random.default_rng(seed)
    th = np.arccos(1 - rng.random(n) * (1 - np.cos(0.9)))
    ph = rng.uniform(-np.pi, np.pi, n)
    R, zc = 15.0, -7.0
    return np.stack([R * np.sin(th) * np.cos(ph), R * np.sin(th) * np.sin(ph), zc + R * np.cos(th)], 1)


def test_field_projector_equals_fe_to_fields():
    xyz = _dome_nodes()
    rng = np.random.default_rng(1)
    u, s = rng.normal(size=(len(xyz), 3)), rng.normal(size=(len(xyz), 6))
    cn, cs = rng.normal(size=(len(xyz), 3)), rng.normal(size=(len(xyz), 3))
    S = 24
    yy, xx = (np.mgrid[0:S, 0:S] + 0.5 - S / 2) / (S / 2)
    d = np.hypot(xx, yy)
    tables = {"theta": d * 0.85, "phi": np.arctan2(yy, xx), "pixel_area": np.where(d <= 1, 0.3, 0.0)}
    cfg = FieldConfig(center_mm=(0.0, 0.0, -7.0))
    area = tributary_area(xyz, cfg=cfg)
    ref = fe_to_fields(xyz, u, s, cn, cs, tables["theta"], tables["phi"], tables["pixel_area"], node_area=area, cfg=cfg)
    got = FieldProjector(xyz, area, tables, cfg).project(u, s, cn, cs)
    assert got.shape == (15, S, S)
    np.testing.assert_allclose(got, ref, atol=1e-5 * np.abs(ref).max())


def test_write_dataset_contract(tmp_path):
    rng = np.random.default_rng(2)
    parts = []
    for k in range(2):
        tgt = rng.normal(size=(5, 15, 16, 16)).astype(np.float32)
        tgt[0] = 0.0                                                         # a rest sample
        parts.append({"input": rng.integers(0, 255, (5, 6, 16, 16), dtype=np.uint8), "target": tgt,
                      "val": np.array([False, False, False, True, k == 1])})
    h = write_dataset(tmp_path, parts, 16, "test")
    idx = read_index(tmp_path)
    assert len(idx["samples"]) == 10 and sum(e["split"] == "val" for e in idx["samples"]) == 3
    assert len(h) == 64
    b = read_bounds(tmp_path / "bounds.json")
    x, y = load_split(tmp_path, "train")
    assert x.shape == (7, 6, 16, 16) and y.min() >= 0 and y.max() <= 1
    lo = np.array([b[c][0] for c in CHANNELS])
    hi = np.array([b[c][1] for c in CHANNELS])
    np.testing.assert_allclose(y[0].reshape(15, -1).mean(1), (0 - lo) / (hi - lo), rtol=1e-5)   # zeros → 0 N


def test_given_bounds_write_normalized_targets_as_they_are(tmp_path):
    """A distilled set (`distill.write_distilled`): the teacher's bounds are stored, its already normalized
    targets are not normalized again; a set with no frames is refused."""
    import pytest
    from tensortouch.contracts.errors import TensorTouchError
    from tensortouch.tools.train.distill import write_distilled

    rng = np.random.default_rng(3)
    bounds = {c: [-2.0, 3.0] for c in CHANNELS}
    tgt = rng.uniform(0, 1, (3, 15, 16, 16)).astype(np.float32)
    parts = [{"input": rng.integers(0, 255, (3, 6, 16, 16), dtype=np.uint8), "target": tgt,
              "val": np.array([False, True, False])}]
    write_distilled(tmp_path / "d", parts, bounds, 16, "test")
    assert read_bounds(tmp_path / "d" / "bounds.json") == bounds
    _, y = load_split(tmp_path / "d", "train")
    np.testing.assert_array_equal(y, tgt[[0, 2]])
    empty = [{"input": np.zeros((0, 6, 16, 16), np.uint8), "target": np.zeros((0, 15, 16, 16), np.float32),
              "val": np.zeros(0, bool)}]
    with pytest.raises(TensorTouchError, match="no frames"):
        write_distilled(tmp_path / "e", empty, bounds, 16, "test")


def test_stacked_split_is_load_split_memory_mapped_and_follows_the_dataset(tmp_path):
    """A fit reads its training split from memory maps written once per dataset version: the same values in
    the same order as load_split, read-only, reused while the index stands, rewritten when it changes."""
    import pytest
    from tensortouch.tools.train.model.data import DatasetError, stacked_split

    rng = np.random.default_rng(5)
    parts = [{"input": rng.integers(0, 255, (4, 6, 16, 16), dtype=np.uint8),
              "target": rng.normal(size=(4, 15, 16, 16)).astype(np.float32), "val": np.array([0, 1, 0, 0], bool)}]
    write_dataset(tmp_path / "d", parts, 16, "test")
    x, y = stacked_split(tmp_path / "d", "train")
    xr, yr = load_split(tmp_path / "d", "train")
    assert isinstance(x, np.memmap) and not x.flags.writeable
    np.testing.assert_array_equal(x, xr)
    np.testing.assert_array_equal(y, yr)
    files = sorted(p.name for p in (tmp_path / "d" / "stack").glob("*.npy"))
    assert len(files) == 2 and not list((tmp_path / "d" / "stack").glob("*.partial"))
    mtimes = [p.stat().st_mtime_ns for p in sorted((tmp_path / "d" / "stack").glob("*.npy"))]
    stacked_split(tmp_path / "d", "train")                                    # reused, not rewritten
    assert [p.stat().st_mtime_ns for p in sorted((tmp_path / "d" / "stack").glob("*.npy"))] == mtimes
    parts[0]["val"][:] = [1, 1, 0, 0]                                         # a new version of the dataset
    write_dataset(tmp_path / "d", parts, 16, "test")
    x2, _ = stacked_split(tmp_path / "d", "train")
    assert x2.shape[0] == 2 and len(list((tmp_path / "d" / "stack").glob("train-*.npy"))) == 2
    np.testing.assert_array_equal(x2, load_split(tmp_path / "d", "train")[0])
    with pytest.raises(DatasetError, match="no samples in split 'test'"):
        stacked_split(tmp_path / "d", "test")


# ---------------------------------------------------------------- stage 3: correspondence cores

def test_image_change_centroid_finds_a_blob():
    base = np.full((120, 160, 3), 100, np.uint8)
    cur = base.copy()
    yy, xx = np.mgrid[0:120, 0:160]
    blob = 60 * np.exp(-((xx - 101.3) ** 2 + (yy - 47.6) ** 2) / (2 * 4.0 ** 2))
    cur = np.clip(cur + blob[..., None], 0, 255).astype(np.uint8)
    x, y = image_change_centroid(base, cur)
    assert abs(x - 101.3) < 0.5 and abs(y - 47.6) < 0.5
    assert np.isnan(image_change_centroid(base, base)[0])


def test_project_to_cap_and_tables_match_the_twin_truth():
    from tensortouch.tools.twin.unit import TwinUnit, true_tables

    p = project_to_cap(np.array([[0.0, 0.0, 2.0], [3.0, 0.0, 5.0]]), -7.0, 15.0)
    np.testing.assert_allclose(np.linalg.norm(p - [0, 0, -7.0], axis=1), 15.0)
    np.testing.assert_allclose(p[0], [0, 0, 8.0])
    unit = TwinUnit("TWIN-TEST-TABLES")
    truth = true_tables(unit, 48)
    got = tables_from_theta_phi(truth["theta"], truth["phi"], unit.gel, truth["mask"])
    m = truth["mask"] & (truth["theta"] < 0.7)
    np.testing.assert_allclose(got["surface_xyz"][m], truth["surface_xyz"][m], atol=1e-6)
    np.testing.assert_allclose(got["normals"][m], truth["normals"][m], atol=1e-6)
    rel = np.abs(got["pixel_area"][m] - truth["pixel_area"][m]) / truth["pixel_area"][m]
    assert np.median(rel) < 0.02                                                   # central vs ±0.5 px differences


# ---------------------------------------------------------------- stage 8: matching and summary

class _C:
    force_mag_n = property(lambda self: float(np.linalg.norm(self.force_n)))

    def __init__(self, pos, force):
        self.position_mm, self.force_n = pos, force


def test_frame_errors_match_nearest_cluster_and_count_misses():
    tips = np.array([[0.0, 0.0, 8.0], [5.0, 0.0, 6.0]])
    forces = np.array([[0.0, 0.0, -3.0], [0.5, 0.0, -2.0]])
    cl = [_C((5.2, 0.1, 6.0), (0.4, 0.0, -1.8)), _C((0.1, -0.1, 7.9), (0.0, 0.1, -2.5))]
    rows = frame_errors(cl, tips, forces)
    assert [r["indenter"] for r in rows] == [0, 1]
    assert rows[0]["pred_force"] == [0.0, 0.1, -2.5] and rows[1]["pred_pos"] == [5.2, 0.1, 6.0]
    miss = frame_errors([], tips, forces)
    assert all(r["miss"] for r in miss)
    s = summarize(rows + miss, [0.0, 0.3])
    assert s["contact_samples"] == 4 and s["detected_fraction"] == 0.5
    assert abs(s["position_mae_mm"]["x"] - 0.15) < 1e-9
    assert abs(s["force_mag_mae_n"] - np.mean([0.5, np.linalg.norm([.5, 0, -2]) - np.linalg.norm([.4, 0, -1.8]),
                                               3.0, np.linalg.norm([.5, 0, -2])])) < 1e-3
    assert s["rest_force_mean_n"] == 0.15 and s["rest_false_contact_fraction"] == 0.5
    assert frame_errors(cl, tips, forces * 0.1) == []                            # below the contact threshold


def test_a_second_cluster_beside_a_single_contact_is_a_phantom():
    tip, force = np.array([[0.0, 0.0, 8.0]]), np.array([[0.0, 0.0, -2.0]])
    main, split = _C((0.1, 0.0, 7.9), (0.0, 0.0, -1.2)), _C((3.0, 0.0, 7.5), (0.3, 0.0, -0.6))
    assert has_phantom([main, split], frame_errors([main, split], tip, force))
    assert not has_phantom([main], frame_errors([main], tip, force))
    speck = _C((3.0, 0.0, 7.5), (0.0, 0.0, -0.01))                              # below phantom_n
    assert not has_phantom([main, speck], frame_errors([main, speck], tip, force))
    s = summarize(frame_errors([main], tip, force), [], [True, False, False, False])
    assert s["single_contact_frames"] == 4 and s["phantom_fraction"] == 0.25


def test_gpr_tables_recover_the_twin_lens_from_exact_pokes():
    """Stage 3 without the image detector: 12 pokes whose 2D positions are the twin lens's exact
    projections → GPR θ within 0.5° of the unit's truth on the poked region (θ ≤ 0.6 rad)."""
    from tensortouch.tools.train.correspondence import gpr_tables, truth_errors
    from tensortouch.tools.twin.unit import TwinUnit, VariationConfig

    unit = TwinUnit("TWIN-TEST-GPR")
    nominal = TwinUnit("TWIN-TEST-GPR", variation=VariationConfig(0.0, 0.0, 0.0, 0.0))
    rng = np.random.default_rng(4)
    th = np.arccos(1 - rng.random(12) * (1 - np.cos(0.6)))
    ph = rng.uniform(-np.pi, np.pi, 12)
    pts = unit.gel.point_at(th, ph)
    xy = unit.model.project(pts)
    fit, tables, x, y = gpr_tables(xy, th, ph, unit.gel, nominal.gel_center_px, nominal.gel_radius_px, (48, 48))
    assert np.hypot(*(np.array(fit.center) - unit.gel_center_px)) < 0.5          # the unit's offset centre
    err = truth_errors(unit, tables, x, y)
    assert err["theta_err_deg"]["p95"] < 0.5 and err["phi_err_deg"]["p95"] < 0.5
    assert tables["mask"].sum() > 0.6 * 48 * 48 and np.all(tables["pixel_area"][tables["mask"]] > 0)
