"""The int8 convolutional student (tools/train/model/convnet.py) and distillation's pure cores
(tools/train/distill.py): shapes, the heads' bias/remap contract, full static int8 coverage, crop jitter."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from tensortouch.tools.train.distill import DistillConfig, jittered_circles, teacher_targets  # noqa: E402
from tensortouch.tools.train.model import build_model  # noqa: E402
from tensortouch.tools.train.model.convnet import ConvFieldNet, ConvNetConfig  # noqa: E402

SMALL = ConvNetConfig(image_size=32, widths=(4, 8, 8, 8), blocks=(0, 1, 0, 1), decoder=(8, 8, 4, 4))


def test_convnet_maps_6_channels_to_15_at_full_size():
    m = build_model("convnet", 64).eval()
    with torch.no_grad():
        y = m(torch.rand(2, 6, 64, 64))
    assert y.shape == (2, 15, 64, 64)


def test_convnet_rejects_sizes_and_levels_that_do_not_fit():
    with pytest.raises(ValueError, match="divisible"):
        ConvFieldNet(ConvNetConfig(image_size=72))
    with pytest.raises(ValueError, match="one entry per level"):
        ConvFieldNet(ConvNetConfig(widths=(8, 8), blocks=(0, 0, 0), decoder=(8, 8)))


def test_output_bias_starts_at_the_mean_and_remap_is_exact():
    torch.manual_seed(0)
    m = ConvFieldNet(SMALL).eval()
    mean = torch.linspace(0.1, 0.9, 15)
    with torch.no_grad():
        m.heads.conv.weight.zero_()
        m.heads.set_output_bias(mean)
        y = m(torch.rand(1, 6, 32, 32))
    # zero weights: every pixel of channel k is mean[k]
    assert torch.allclose(y[0, :, 5, 7], mean)
    torch.manual_seed(1)
    m = ConvFieldNet(SMALL).eval()
    x = torch.rand(1, 6, 32, 32)
    with torch.no_grad():
        before = m(x)
        scale, offset = torch.full((15,), 2.0), torch.arange(15, dtype=torch.float32) / 10
        m.heads.remap_output(scale, offset)
        after = m(x)
    assert torch.allclose(after, 2.0 * before + offset.view(1, -1, 1, 1), atol=1e-5)
    with pytest.raises(ValueError, match="15"):
        m.heads.set_output_bias(torch.zeros(3))


def test_full_scheme_quantizes_every_convolution_and_stays_close(tmp_path):
    import onnx
    from tensortouch.tools.train.export import ExportConfig, export_onnx, output_head_nodes, quantize_int8, run_model, session

    torch.manual_seed(0)
    m = ConvFieldNet(SMALL).eval()
    fp32 = export_onnx(m, tmp_path / "m.onnx", 32)
    x = np.random.default_rng(0).random((8, 6, 32, 32), dtype=np.float32)
    int8 = quantize_int8(fp32, tmp_path / "q.onnx", x, ExportConfig(scheme="full"))
    g = onnx.load(str(int8)).graph
    produced_by_dq = {o for n in g.node if n.op_type == "DequantizeLinear" for o in n.output}
    head = set(output_head_nodes(g))
    convs = [n for n in g.node if n.op_type == "Conv"]
    assert len([n for n in convs if n.name in head]) == 1          # the head conv: float (quantize_head False)
    body = [n for n in convs if n.name not in head]
    assert body and all(n.input[0] in produced_by_dq and n.input[1] in produced_by_dq for n in body)
    assert not any(n.input[1] in produced_by_dq for n in convs if n.name in head)
    adds = [n for n in g.node if n.op_type == "Add"]
    assert adds and all(all(i in produced_by_dq for i in n.input) for n in adds)
    y32, y8 = run_model(session(fp32), x), run_model(session(int8), x)
    assert y8.shape == y32.shape == (8, 15, 32, 32)
    assert float(np.abs(y8 - y32).max()) < 0.1 * float(np.abs(y32).max() + 1e-6) + 0.05


def test_jittered_circles_keep_the_calibrated_one_first_and_stay_in_bounds():
    cfg = DistillConfig(scale_jitter=0.04, center_jitter_px=1.0)
    c = jittered_circles(160.0, 120.0, 100.0, 50, cfg, np.random.default_rng(0))
    assert c.shape == (51, 3)
    assert tuple(c[0]) == (160.0, 120.0, 100.0)
    assert np.all(np.abs(c[1:, 0] - 160) <= 1.0) and np.all(np.abs(c[1:, 1] - 120) <= 1.0)
    assert np.all((c[1:, 2] >= 96.0) & (c[1:, 2] <= 104.0))
    assert c[1:, 2].std() > 0.5                      # it does jitter
    assert jittered_circles(1.0, 2.0, 3.0, 0, cfg, np.random.default_rng(0)).shape == (1, 3)
    with pytest.raises(ValueError, match="positive radius"):
        jittered_circles(0.0, 0.0, 0.0, 2, cfg, np.random.default_rng(0))
    with pytest.raises(ValueError, match="n = -1"):
        jittered_circles(0.0, 0.0, 5.0, -1, cfg, np.random.default_rng(0))


def test_teacher_targets_feed_the_teacher_inputs_in_0_1_one_frame_at_a_time():
    seen = []

    def teacher(x):                    # a stand-in teacher: channel k = mean of the inputs + k
        seen.append(x.shape)
        return np.broadcast_to(x.mean() + np.arange(15, dtype=np.float32).reshape(1, 15, 1, 1), (1, 15, 4, 4))
    inp = np.full((3, 6, 4, 4), 255, np.uint8)
    inp[1] = 0
    y = teacher_targets(teacher, inp)
    assert seen == [(1, 6, 4, 4)] * 3
    assert y.shape == (3, 15, 4, 4) and y.dtype == np.float32
    assert np.allclose(y[0, :, 0, 0], 1.0 + np.arange(15)) and np.allclose(y[1, :, 0, 0], np.arange(15))
    with pytest.raises(ValueError, match="uint8"):
        teacher_targets(teacher, inp.astype(np.float32))
    with pytest.raises(ValueError, match="teacher gave"):
        teacher_targets(lambda x: np.zeros((1, 14, 4, 4), np.float32), inp)


def test_measured_total_sums_the_indenters_at_the_picked_frames():
    from tensortouch.tools.train.distill import measured_total

    meas = {0: {"force": np.array([[0.0, 0, -1], [0, 0, -2], [0.5, 0, -3]])},
            3: {"force": np.array([[0.0, 0, 0], [0, 1, -1], [0, 0, 0]])}}
    got = measured_total(meas, [2, 1, 1])
    assert got.dtype == np.float32 and got.shape == (3, 3)
    assert got.tolist() == [[0.5, 0, -3], [0, 1, -3], [0, 1, -3]]
    assert measured_total(meas, []).shape == (0, 3)
    with pytest.raises(ValueError, match="outside 0..2"):
        measured_total(meas, [3])
    with pytest.raises(ValueError, match="no indenter"):
        measured_total({}, [0])


def test_measured_force_error_is_the_total_force_against_the_rig():
    import torch
    from tensortouch.tools.train.model.train import measured_force_error

    scale = torch.full((6, 8, 8), 0.25)               # span 1 MPa per normalized unit × 0.25 mm² per pixel
    zero = torch.full((1, 15, 1, 1), 0.5)
    p = torch.full((2, 15, 8, 8), 0.5)
    p[0, 11, :2, :2] -= 0.4                           # fn_z: 4 px × −0.4 MPa × 0.25 mm² = −0.4 N
    p[0, 12, 0, 0] += 0.8                             # fs_x: 0.2 N
    p[1, 9] += 0.01                                   # fn_x 0.16 N over the frame, cancelled by fs_x
    p[1, 12] -= 0.01
    measured = torch.tensor([[0.2, 0.0, -0.1], [0.0, 0.3, -0.4]])
    err = measured_force_error(p, zero, scale, measured)
    assert err[0].item() == pytest.approx(0.3, rel=1e-5)          # (0.2, 0, −0.4) vs (0.2, 0, −0.1)
    assert err[1].item() == pytest.approx(0.5, rel=1e-5)          # (0, 0, 0) vs (0, 0.3, −0.4)
    with pytest.raises(ValueError, match="measured"):
        measured_force_error(p, zero, scale, measured[:1])
    with pytest.raises(ValueError, match="scale"):
        measured_force_error(p, zero, scale[:, :4], measured)


def test_fit_holds_the_total_force_to_the_measured_one(tmp_path):
    """A distilled dataset keeps each sample's measured force (index `force_n`); the fit reads it with the
    term on, and says which file lacks it when a dataset has none."""
    import torch
    from tensortouch.tools.train.dataset import write_dataset
    from tensortouch.tools.train.model.data import DatasetError, load_measured, load_split
    from tensortouch.tools.train.model.train import FitConfig, fit

    rng = np.random.default_rng(0)
    n, S = 12, 32
    bounds = {c: [-1.0, 1.0] for c in __import__("tensortouch.contracts.fields", fromlist=["CHANNELS"]).CHANNELS}
    part = {"input": rng.integers(0, 255, (n, 6, S, S), dtype=np.uint8),
            "target": np.full((n, 15, S, S), 0.5, np.float32), "val": np.arange(n) >= 9,
            "force_n": np.stack([np.zeros(n), np.zeros(n), -np.linspace(0, 2, n)], 1)}
    data = tmp_path / "ds"
    write_dataset(data, [part], S, "test", pixel_area=np.full((S, S), 0.05, np.float32), bounds=bounds,
                  compress=False)
    got = load_measured(data, "train")
    assert got.shape == (9, 3) and got[:, 2].tolist() == pytest.approx((-np.linspace(0, 2, n)[:9]).tolist())
    assert len(load_split(data, "train")[0]) == len(got)
    cfg = FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, fg_weight=5.0, measured_force_weight=0.5)
    fit(data, tmp_path / "run", cfg)
    fit(data, tmp_path / "off", FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, fg_weight=5.0))
    a = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "off" / "checkpoint.pt", weights_only=False)["model"]
    assert any(not torch.equal(a[k], b[k]) for k in a)       # the term moved the weights (same seed and batches)
    del part["force_n"]
    write_dataset(tmp_path / "plain", [part], S, "test", pixel_area=np.full((S, S), 0.05, np.float32),
                  bounds=bounds, compress=False)
    with pytest.raises(DatasetError, match="000000.npz has no measured force"):
        fit(tmp_path / "plain", tmp_path / "run2", cfg)


def test_contact_pixels_keeps_two_pressing_indenters_at_their_nearest_surface_pixel():
    from tensortouch.tools.train.distill import contact_pixels

    # a flat 4×4 "gel" at z = 0, 1 mm per pixel (u = x, v = y); the corner pixel (3, 3) is masked off
    v, u = np.mgrid[0:4, 0:4].astype(float)
    xyz = np.stack([u, v, np.zeros_like(u)], axis=-1)
    mask = np.ones((4, 4), bool)
    mask[3, 3] = False
    tips = np.array([[[0.2, 0.9, 0.5], [3.1, 2.9, 0.3]],      # both press: pixels (0, 1) and the masked (3, 3) → (3, 2)
                     [[0.2, 0.9, 0.5], [3.1, 2.9, 0.3]],      # the second carries 0.1 N (below 0.2 N: not pressing)
                     [[0.2, 0.9, 0.5], [3.1, 2.9, 3.5]]])     # the second's tip is 3.5 mm off the gel: F/T offset
    forces = np.array([[[0.0, 0.1, -1.0], [0.0, 0.0, -0.5]],
                       [[0.0, 0.1, -1.0], [0.0, 0.0, -0.1]],
                       [[0.0, 0.1, -1.0], [0.0, 0.0, -0.5]]])
    got = contact_pixels(tips, forces, xyz, mask)
    assert got.shape == (3, 2, 5) and got.dtype == np.float32
    assert got[0].ravel().tolist() == pytest.approx([0.0, 0.1, -1.0, 0, 1, 0.0, 0.0, -0.5, 3, 2])
    assert np.isnan(got[1:]).all()                             # one contact: the total holds
    assert np.isfinite(contact_pixels(tips, forces, xyz, mask, active_n=0.05, reach_mm=4.0)).all()
    with pytest.raises(ValueError, match="tips and forces"):
        contact_pixels(tips[:, :1], forces, xyz, mask)
    with pytest.raises(ValueError, match="surface_xyz"):
        contact_pixels(tips, forces, xyz[:3], mask)


def test_pixels_in_crop_follows_the_raw_image_between_two_crops():
    from tensortouch.runtime.stages.preprocess import Preprocessor
    from tensortouch.tools.train.distill import pixels_in_crop

    a, b = Preprocessor(160.0, 120.0, 100.0, 128), Preprocessor(162.0, 119.0, 104.0, 128)
    uv = np.array([[64.0, 64.0], [10.0, 100.0], [np.nan, np.nan]])
    got = pixels_in_crop(uv, a, b)
    assert np.isnan(got[2]).all()
    back = pixels_in_crop(got[:2], b, a)
    assert back == pytest.approx(uv[:2])
    raw = np.stack(a.to_raw(uv[:2, 0], uv[:2, 1]), axis=-1)
    assert np.stack(b.to_raw(got[:2, 0], got[:2, 1]), axis=-1) == pytest.approx(raw)
    with pytest.raises(ValueError, match=r"\(\.\.\., 2\)"):
        pixels_in_crop(uv[:, :1], a, b)


def test_measured_force_split_error_holds_each_contact_on_its_side():
    import torch
    from tensortouch.tools.train.model.train import measured_force_error, measured_force_split_error

    scale = torch.full((6, 8, 8), 0.25)
    zero = torch.full((1, 15, 1, 1), 0.5)
    p = torch.full((3, 15, 8, 8), 0.5)
    for i in range(3):
        p[i, 11, 1, 1] -= 4.0          # fn_z −1 N at (u 1, v 1)
        p[i, 11, 6, 6] -= 2.0          # fn_z −0.5 N at (u 6, v 6)
    nan = [float("nan")] * 10
    measured = torch.tensor([
        [0, 0, -1.5, 0, 0, -1.0, 1, 1, 0, 0, -0.5, 6, 6],       # right on both sides: 0
        [0, 0, -1.5, 0, 0, -0.5, 1, 1, 0, 0, -1.0, 6, 6],       # the same total, the split swapped: 0.5 + 0.5
        [0, 0, -1.2] + nan])                                     # one contact: the total's error, 0.3
    err = measured_force_split_error(p, zero, scale, measured)
    assert err.tolist() == pytest.approx([0.0, 1.0, 0.3], abs=1e-5)
    assert measured_force_error(p, zero, scale, measured[:, :3]).tolist() == pytest.approx([0.0, 0.0, 0.3], abs=1e-5)
    assert measured_force_split_error(p[2:], zero, scale, measured[2:]).tolist() == pytest.approx([0.3], abs=1e-5)
    with pytest.raises(ValueError, match=r"\(B, 13\)"):
        measured_force_split_error(p, zero, scale, measured[:, :3])
    with pytest.raises(ValueError, match="scale"):
        measured_force_split_error(p, zero, scale[:, :4], measured)


def test_fit_splits_the_measured_force_at_two_contacts(tmp_path):
    """`contacts_n` goes through the dataset's index into the fit's split term; a split without the
    measured-force weight is refused, and a malformed entry names its sample."""
    import json

    import torch
    from tensortouch.tools.train.dataset import write_dataset
    from tensortouch.tools.train.model.data import DatasetError, load_measured
    from tensortouch.tools.train.model.train import FitConfig, fit

    rng = np.random.default_rng(1)
    n, S = 12, 32
    bounds = {c: [-1.0, 1.0] for c in __import__("tensortouch.contracts.fields", fromlist=["CHANNELS"]).CHANNELS}
    two = np.full((n, 2, 5), np.nan, np.float32)
    two[::2] = [[0, 0, -0.4, 8, 8], [0, 0, -0.6, 24, 20]]
    part = {"input": rng.integers(0, 255, (n, 6, S, S), dtype=np.uint8),
            "target": np.full((n, 15, S, S), 0.5, np.float32), "val": np.arange(n) >= 9,
            "force_n": np.tile([0.0, 0.0, -1.0], (n, 1)), "contacts_n": two}
    data = tmp_path / "ds"
    write_dataset(data, [part], S, "test", pixel_area=np.full((S, S), 0.05, np.float32), bounds=bounds, compress=False)
    got = load_measured(data, "train", contacts=True)
    assert got.shape == (9, 13) and got[0, 3:].tolist() == pytest.approx([0, 0, -0.4, 8, 8, 0, 0, -0.6, 24, 20])
    assert np.isnan(got[1, 3:]).all() and load_measured(data, "train").shape == (9, 3)
    on = FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, fg_weight=5.0, measured_force_weight=0.5)
    fit(data, tmp_path / "split", FitConfig(**{**on.__dict__, "measured_force_split": True}))
    fit(data, tmp_path / "total", on)
    a = torch.load(tmp_path / "split" / "checkpoint.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "total" / "checkpoint.pt", weights_only=False)["model"]
    assert any(not torch.equal(a[k], b[k]) for k in a)       # the split moved the weights (same seed and batches)
    with pytest.raises(DatasetError, match="needs measured_force_weight"):
        fit(data, tmp_path / "x", FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, measured_force_split=True))
    idx = json.loads((data / "index.json").read_text())
    idx["samples"][0]["contacts_n"] = [[0, 0, -0.4, 8]]
    (data / "index.json").write_text(json.dumps(idx))
    with pytest.raises(DatasetError, match="000000.npz: contacts_n must be two"):
        load_measured(data, "train", contacts=True)
