"""Stage 6 (seed §III.J, §IV-C): Hiera + Q-Upsample, MAE, baselines, metrics, training loop."""
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tensortouch.contracts.fields import CHANNELS  # noqa: E402
from tensortouch.tools.train.model import build_model  # noqa: E402
from tensortouch.tools.train.model.data import data_hash, load_split, read_index, write_synthetic_dataset  # noqa: E402
from tensortouch.tools.train.model.hiera import Hiera, HieraConfig, HieraMAE  # noqa: E402
from tensortouch.tools.train.model.layers import count_params  # noqa: E402
from tensortouch.tools.train.model.train import FitConfig, _Progress, fit, load_trained, lr_at  # noqa: E402


@pytest.mark.parametrize("size", [128, 96])
def test_shipped_config_shapes_and_parameter_budget(size):
    torch.manual_seed(0)
    m = build_model("hiera_qup", size)
    feats = m.encoder(torch.rand(1, 6, size, size))
    t = size // 4
    assert [tuple(f.shape[1:]) for f in feats] == [(32, t, t), (64, t // 2, t // 2), (128, t // 4, t // 4),
                                                   (256, t // 8, t // 8)]
    assert [len([b for b in range(len(m.encoder.blocks))])] == [7]          # stages 1-2-3-1
    n = count_params(m)
    assert 1_000_000 <= n <= 3_000_000
    assert m(torch.rand(1, 6, size, size)).shape == (1, 15, size, size)
    for arch in ("unet", "vit"):                                          # baselines of a similar size
        assert 0.6 * n <= count_params(build_model(arch, size)) <= 1.4 * n


def test_mask_unit_attention_is_local_in_stage_one():
    """A change deep inside one mask unit moves stage-1 features of that unit only (Hiera's locality)."""
    torch.manual_seed(0)
    enc = Hiera(HieraConfig(image_size=64)).eval()
    x = torch.rand(1, 6, 64, 64)
    x2 = x.clone()
    x2[:, :, 8:24, 8:24] += 1.0           # unit (0, 0) covers pixels 0..31; 8 px margin > conv reach
    with torch.no_grad():
        d = (enc(x)[0] - enc(x2)[0]).abs().sum(1)[0]                      # (16, 16) tokens
    assert d[:8, :8].min() > 0
    outside = d.clone(); outside[:8, :8] = 0
    assert outside.max() == 0
    with torch.no_grad():                 # deeper stages attend globally: everything moves
        assert (enc(x)[3] - enc(x2)[3]).abs().sum(1)[0].min() > 0


def test_mae_masks_75_percent_and_learns():
    torch.manual_seed(0)
    torch.set_num_threads(1)
    mae = HieraMAE(Hiera(HieraConfig(image_size=64)), decoder_dim=32, decoder_depth=1)
    vis = mae.random_mask(3, 16)
    assert vis.shape == (3, 16) and torch.all(vis.sum(1) == 4)
    x = torch.rand(2, 6, 64, 64)
    x[:, :, ::2] *= 0.2                     # structured
    loss, pred, vis = mae(x)
    assert vis.sum(1).tolist() == [1, 1] and pred.shape == (2, 4, 6 * 32 * 32)
    # the loss only looks at masked units: its gradient w.r.t. visible-unit predictions is zero
    pred.retain_grad()
    loss, pred, vis = mae(x, vis)
    pred.retain_grad(); loss.backward()
    assert pred.grad[vis].abs().max() == 0 and pred.grad[~vis].abs().max() > 0
    opt = torch.optim.AdamW(mae.parameters(), lr=1e-3)
    first = None
    for _ in range(10):
        loss = mae(x, vis)[0]
        opt.zero_grad(); loss.backward(); opt.step()
        first = first or loss.item()
    assert loss.item() < 0.8 * first


def test_lr_schedule_warmup_then_cosine():
    total, base = 1000, 1e-3
    lrs = [lr_at(s, total, base, 500, 0.1) for s in range(total)]
    assert lrs[0] == pytest.approx(base / 100) and lrs[99] == pytest.approx(base)   # warmup capped at 10 %
    assert np.all(np.diff(lrs[:100]) > 0) and np.all(np.diff(lrs[100:]) <= 0)
    assert lrs[-1] < 1e-3 * base
    assert lr_at(550, total, base, 500, 1.0) == pytest.approx(0.5 * base * (1 + np.cos(np.pi * 50 / 500)))


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    write_synthetic_dataset(root, 20, size=64, seed=1)
    return root


def test_dataset_contract(tiny_dataset):
    idx = read_index(tiny_dataset)
    assert idx["output_channels"] == list(CHANNELS) and idx["size"] == [64, 64]
    assert {e["split"] for e in idx["samples"]} == {"train", "val"}
    x, y = load_split(tiny_dataset, "train")
    assert x.dtype == np.uint8 and x.shape[1:] == (6, 64, 64) and y.shape[1:] == (15, 64, 64)
    assert y.dtype == np.float32 and y.min() >= 0 and y.max() <= 1
    assert len(data_hash(tiny_dataset)) == 64


def test_fit_resumes_to_the_same_weights(tiny_dataset, tmp_path, monkeypatch):
    cfg = FitConfig(arch="hiera_qup", epochs=2, batch_size=6, checkpoint_every_s=0.0, log_every=1, threads=1)
    ref = fit(tiny_dataset, tmp_path / "ref", cfg)
    assert ref["steps"] == 6 and (tmp_path / "ref" / "best.pt").exists()
    assert set(ref["metrics"]["mean"]) == {"psnr", "ssim", "mse", "auc_rel", "fpr_rel"}

    real_tick = _Progress.tick

    def boom(self, step, *a):
        real_tick(self, step, *a)
        if step == 4:
            raise KeyboardInterrupt

    monkeypatch.setattr(_Progress, "tick", boom)
    with pytest.raises(KeyboardInterrupt):
        fit(tiny_dataset, tmp_path / "cut", cfg)
    monkeypatch.setattr(_Progress, "tick", real_tick)
    resumed = fit(tiny_dataset, tmp_path / "cut", cfg)
    assert resumed["steps"] == 6
    a = torch.load(tmp_path / "ref" / "checkpoint.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=False)["model"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-4, atol=1e-5)
    model, info = load_trained(tmp_path / "cut")
    assert info["arch"] == "hiera_qup" and model(torch.rand(1, 6, 64, 64)).shape == (1, 15, 64, 64)
    hist = [json.loads(l) for l in (tmp_path / "cut" / "history.jsonl").read_text().splitlines()]
    assert [h["epoch"] for h in hist] == [0, 1]


def test_fit_refuses_to_resume_a_different_config(tiny_dataset, tmp_path):
    from tensortouch.tools.train.model.data import DatasetError

    fit(tiny_dataset, tmp_path / "r", FitConfig(arch="unet", epochs=1, batch_size=8, threads=1))
    with pytest.raises(DatasetError, match="config.json"):
        fit(tiny_dataset, tmp_path / "r", FitConfig(arch="unet", epochs=1, batch_size=4, threads=1))


@pytest.mark.parametrize("arch", ["hiera_qup", "unet", "vit"])
def test_heads_start_at_the_mean_target(arch):
    torch.manual_seed(0)
    m = build_model(arch, 64)
    mean = torch.linspace(0.1, 0.9, 15)
    m.heads.set_output_bias(mean)
    with torch.no_grad():
        y = m(torch.rand(2, 6, 64, 64)).mean((0, 2, 3))
    assert (y - mean).abs().max() < 0.1


def test_photometric_jitter_scales_both_frames_alike_within_bounds():
    import torch
    from tensortouch.tools.train.model.train import photometric_jitter

    torch.manual_seed(0)
    x = torch.rand(4, 6, 16, 20) * 0.5
    assert torch.equal(photometric_jitter(x, 0.0), x)
    y = photometric_jitter(x, 0.1)
    g = y / x
    assert torch.allclose(g[:, :3], g[:, 3:])                       # the same LEDs light baseline and current
    assert g.min() >= (0.9 * 0.9) - 1e-6 and g.max() <= (1.1 * 1.1) + 1e-6
    assert (g.amax(dim=(2, 3)) - g.amin(dim=(2, 3))).max() > 0      # a ramp across the image
    assert photometric_jitter(torch.ones(1, 6, 4, 4), 0.1).max() <= 1.0
    with pytest.raises(ValueError, match="expected \\(B, 6, H, W\\)"):
        photometric_jitter(torch.zeros(2, 3, 4, 4), 0.1)
