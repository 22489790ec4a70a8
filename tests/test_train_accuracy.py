"""Force accuracy of the label path (docs/BENCHMARKS.md "Shipped model", error budget):
FE node forces → field image → the runtime's contact clusters must keep the total force."""
import numpy as np
import pytest
from scipy import ndimage
from tensortouch.runtime.stages.contacts import ContactConfig, find_clusters, pixel_forces
from tensortouch.tools.train.dataset import FieldProjector
from tensortouch.tools.train.fields import FieldConfig, contact_force_from_image, fe_to_fields, tributary_area

R = 16.0


def _coarse_dome(step_mm=1.0):
    """FE-like surface nodes about `step_mm` apart on a 16 mm hemisphere cap (θ ≤ 1.2 rad)."""
    rows = []
    for th in np.arange(0.0, 1.2, step_mm / R):
        m = max(1, int(round(2 * np.pi * R * np.sin(th) / step_mm)))
        ph = np.linspace(-np.pi, np.pi, m, endpoint=False) + 0.37 * th
        rows.append(np.stack([R * np.sin(th) * np.cos(ph), R * np.sin(th) * np.sin(ph),
                              R * np.cos(th) * np.ones(m)], 1))
    return np.concatenate(rows)


def _tables(size=64, theta_max=1.25):
    c = (size / 2) / theta_max
    yy, xx = np.mgrid[0:size, 0:size] + 0.5 - size / 2
    theta = np.hypot(xx, yy) / c
    with np.errstate(invalid="ignore", divide="ignore"):
        area = np.where(theta > 0, R ** 2 * np.sin(theta) / (c ** 2 * theta), R ** 2 / c ** 2)
    return {"theta": theta, "phi": np.arctan2(yy, xx), "pixel_area": np.where(theta <= 1.2, area, 0.0)}


def _contact(nodes, theta_c, phi_c, radius=2.0, total=4.0):
    """Per-node normal forces (N) of a small contact patch (few nodes: a coarse FE mesh's view)."""
    c = R * np.array([np.sin(theta_c) * np.cos(phi_c), np.sin(theta_c) * np.sin(phi_c), np.cos(theta_c)])
    d = np.linalg.norm(nodes - c, axis=1)
    w = np.clip(1 - (d / radius) ** 2, 0, None)
    n = nodes / np.linalg.norm(nodes, axis=1, keepdims=True)
    return -n * (total * w / w.sum())[:, None]


@pytest.mark.parametrize("where", [(0.3, 0.2), (0.7, 2.0), (0.9, np.pi)])
def test_force_conserving_projection_keeps_the_node_force_total(where):
    nodes = _coarse_dome()
    area = tributary_area(nodes)
    tables = _tables()
    fn = _contact(nodes, *where)
    z3, z6 = np.zeros_like(nodes), np.zeros((len(nodes), 6))
    expected = fn.sum(0)
    errs = {}
    for conserve in (False, True):
        cfg = FieldConfig(conserve_force=conserve, gaussian_sigma_px=0.0)
        img = FieldProjector(nodes, area, tables, cfg).project(z3, z6, fn, z3)
        ref = fe_to_fields(nodes, z3, z6, fn, z3, tables["theta"], tables["phi"], tables["pixel_area"],
                           node_area=area, cfg=cfg)
        np.testing.assert_allclose(img, ref, atol=1e-5 * np.abs(ref).max())   # projector == fe_to_fields
        f_img, _ = contact_force_from_image(img, tables["pixel_area"])
        errs[conserve] = np.linalg.norm(f_img - expected) / np.linalg.norm(expected)
    assert errs[True] < 1e-3                      # exact up to float32, before smoothing
    assert errs[True] < errs[False]               # the mesh-area quotient does not conserve


def test_runtime_clusters_keep_the_smoothed_tails():
    """A 4 N contact smoothed with σ = 2 px (the label's Gaussian): the cluster's force (core above the
    0.005 N threshold + the grown support) keeps ≥ 99 % of the image total with the runtime defaults."""
    tables = _tables(128)
    pa = tables["pixel_area"]
    mask = pa > 0
    yy, xx = np.mgrid[0:128, 0:128]
    disc = ((xx - 80) ** 2 + (yy - 60) ** 2 <= 4 ** 2).astype(float)
    trac = ndimage.gaussian_filter(disc, 2.0)
    trac *= 4.0 / (trac * pa).sum()               # |F| = 4 N
    fields = np.zeros((15, 128, 128))
    fields[11] = -trac
    fp = pixel_forces(fields, pa)
    xyz = np.zeros((128, 128, 3))
    normals = np.zeros((128, 128, 3))
    normals[..., 2] = 1
    (c,) = find_clusters(fp, xyz, normals, pa, mask)
    assert c.force_mag_n == pytest.approx(4.0, rel=0.01)
    old = ContactConfig(support_floor_n=0.0005, support_radius_px=6.0)
    (c_old,) = find_clusters(fp, xyz, normals, pa, mask, cfg=old)
    assert c_old.force_mag_n < c.force_mag_n


def _contact_scale(area_mm2: float):
    """`_force_scale` of bounds [-0.5, 0.5] MPa on every channel (span 1 MPa, zero at 0.5) over an 8×8 image."""
    import torch

    return torch.full((6, 8, 8), float(area_mm2))


def test_total_force_error_is_the_integrated_contact_force_difference():
    import torch
    from tensortouch.tools.train.model.train import total_force_error

    scale = _contact_scale(0.25)                        # 1 MPa per normalized unit × mm² per pixel
    y = torch.full((2, 15, 8, 8), 0.5)
    p = y.clone()
    p[0, 11, :2, :2] += 0.1                                    # fn_z: 4 px × 0.1 MPa × 0.25 mm² = 0.1 N
    p[1, 9, :, :] += 0.01                                      # fn_x: 64 × 0.01 × 0.25 = 0.16 N ...
    p[1, 12, :, :] -= 0.01                                     # ... cancelled by fs_x (the runtime sums fn + fs)
    err = total_force_error(p, y, scale)
    assert err[0].item() == pytest.approx(0.1, rel=1e-5) and err[1].item() == pytest.approx(0.0, abs=1e-6)


def test_pixel_force_excess_counts_single_pixels_beyond_the_tolerance():
    import torch
    from tensortouch.tools.train.model.train import pixel_force_excess

    scale = _contact_scale(0.01)                        # 1 MPa per normalized unit × mm² per pixel
    y = torch.full((3, 15, 8, 8), 0.5)
    p = y.clone()
    p[0, 11, 0, :3] += 0.2                                     # 3 px × 0.2 MPa × 0.01 mm² = 0.002 N each
    p[1, 9, :, :] += 0.04                                      # 64 px of 0.0004 N: all within 0.0005 N
    p[2, 9, 0, 0] += 0.3                                       # fn_x 0.003 N cancelled by fs_x (fn + fs is the force)
    p[2, 12, 0, 0] -= 0.3
    got = pixel_force_excess(p, y, scale, 0.0005)
    assert got[0].item() == pytest.approx(3 * (0.002 - 0.0005), rel=1e-4)
    assert got[1].item() == 0.0 and got[2].item() == pytest.approx(0.0, abs=1e-7)
    with pytest.raises(ValueError, match="scale"):
        pixel_force_excess(p, y, scale[:, :4], 0.0005)
    with pytest.raises(ValueError, match="pred and target"):
        pixel_force_excess(p[:, :9], y[:, :9], scale, 0.0005)


def test_light_sample_weight_emphasises_light_contacts_only():
    import torch
    from tensortouch.tools.train.model.train import FitConfig, light_sample_weight

    scale = _contact_scale(0.25)                        # 1 MPa per normalized unit × mm² per pixel
    y0 = torch.full((1, 15, 1, 1), 0.5)
    y = torch.full((5, 15, 8, 8), 0.5)
    for i, f in enumerate((0.0, 0.01, 0.25, 1.0, 4.0)):       # total normal force per sample (N)
        y[i, 11] -= f / (64 * 0.25)                            # fn_z spread over the 64 pixels
    cfg = FitConfig(light_weight=0.5, light_ref_n=1.0, light_max=3.0, light_min_n=0.05)
    w = light_sample_weight(y, y0, scale, cfg)
    assert w.tolist() == pytest.approx([1.0, 1.0, 2.0, 1.0, 1.0], rel=1e-4)   # rest, noise, (1/0.25)^0.5, firm
    cfg.light_weight = 2.0
    assert light_sample_weight(y, y0, scale, cfg)[2].item() == pytest.approx(3.0)   # clipped at light_max


def test_fit_fine_tunes_from_a_state_dict_with_the_force_term(tmp_path):
    import torch
    from tensortouch.tools.train.model.data import write_synthetic_dataset
    from tensortouch.tools.train.model.train import FitConfig, fit

    data = tmp_path / "ds"
    write_synthetic_dataset(data, 12, size=64, seed=3)
    cfg = FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, fg_weight=5.0)
    fit(data, tmp_path / "base", cfg)
    with pytest.raises(Exception, match="pixel_area.npy"):
        fit(data, tmp_path / "nf", FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, force_weight=0.1))
    np.save(data / "pixel_area.npy", np.full((64, 64), 0.05, np.float32))
    tuned = FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, fg_weight=5.0, force_weight=0.1,
                      light_weight=0.5, lr=0.0, init_from=str(tmp_path / "base" / "best.pt"))
    fit(data, tmp_path / "ft", tuned)                           # lr 0: the weights stay those loaded
    a = torch.load(tmp_path / "base" / "best.pt", weights_only=True)
    b = torch.load(tmp_path / "ft" / "best.pt", weights_only=True)
    for k in a:
        torch.testing.assert_close(a[k], b[k])


def test_budget_table_bins_label_errors_by_force_and_indenter_count():
    from types import SimpleNamespace

    from tensortouch.tools.train.evaluate import budget_table, sample_forces

    S = 64
    pa = np.full((S, S), 0.1)
    xyz = np.zeros((S, S, 3))
    xyz[..., 0], xyz[..., 1] = np.mgrid[0:S, 0:S][1] * 0.3, np.mgrid[0:S, 0:S][0] * 0.3
    normals = np.zeros((S, S, 3))
    normals[..., 2] = 1
    cal = SimpleNamespace(pixel_area=pa, surface_xyz=xyz, normals=normals, mask=pa > 0)
    yy, xx = np.mgrid[0:S, 0:S]

    def field(centres, forces):
        f = np.zeros((15, S, S))
        for (u, v), fz in zip(centres, forces):
            disc = ((xx - u) ** 2 + (yy - v) ** 2 <= 9).astype(float)
            f[11] += -fz * disc / (disc * pa).sum()
        return f

    items = []
    for fz, k in ((2.0, 1), (6.0, 1), (4.0, 2)):
        centres = [(20, 20), (44, 44)][:k]
        tips = np.array([[u * 0.3, v * 0.3, 0.0] for u, v in centres] + [[0, 0, 0]] * (2 - k))
        meas = np.array([[0, 0, -fz]] * k + [[0, 0, 0]] * (2 - k), float)
        lab = field(centres, [fz * 0.9] * k)                  # the label carries 90 % of the force
        items.append({"meas": meas.sum(0), "n_contact": k, "label": sample_forces(lab, cal, tips, meas, ContactConfig())})
    t = budget_table(items)
    assert t["all"]["n"] == 3 and t["all"]["detected_fraction"] == 1.0
    assert t["F 1.5-3 N"]["force_mag_bias_n"] == pytest.approx(-0.2, abs=1e-6)
    assert t["F 5-7 N"]["integral_bias_n"] == pytest.approx(-0.6, abs=1e-6)
    assert t["2 indenter(s)"]["contact_samples"] == 2
    assert t["2 indenter(s)"]["force_mag_mae_n"] == pytest.approx(0.4, abs=1e-6)
    assert t["2 indenter(s)"]["position_mae_mm"]["x"] < 0.05
    assert "at an FE frame" not in t                   # twin-solve labels carry no label kind

    for it, at in zip(items, (True, False, False)):
        it["at_fe_frame"] = at
    t = budget_table(items)
    assert t["at an FE frame"]["n"] == 1 and t["at an FE frame"]["integral_bias_n"] == pytest.approx(-0.2, abs=1e-6)
    assert t["between FE frames"]["n"] == 2
    assert t["between FE frames"]["integral_bias_n"] == pytest.approx(-0.7, abs=1e-6)   # (-0.6 - 0.8) / 2: 6 N, and 2 × 4 N


def test_at_fe_frames_is_within_half_a_camera_period_of_any_source():
    from types import SimpleNamespace

    from tensortouch.tools.train.evaluate import at_fe_frames

    frame_t = np.arange(10) * 0.1                           # 10 Hz camera: half a period is 0.05 s
    sources = [SimpleNamespace(times=[0.21, 0.5]), SimpleNamespace(times=[0.84])]
    got = at_fe_frames(frame_t, np.array([1, 2, 3, 5, 8, 9]), sources)
    assert got.tolist() == [False, True, False, True, True, False]
    assert at_fe_frames(frame_t, np.array([0, 1]), []).tolist() == [False, False]
    assert at_fe_frames(frame_t, np.array([4, 6]), [SimpleNamespace(times=[0.43])]).tolist() == [True, False]
