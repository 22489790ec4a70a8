"""Stage 6 (seed §III.J, §IV-C): baselines, learning-rate schedule, dataset contract, training loop and
resume."""
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tensortouch.contracts.fields import CHANNELS  # noqa: E402
from tensortouch.tools.train.model import build_model  # noqa: E402
from tensortouch.tools.train.model.data import data_hash, load_split, read_index, write_synthetic_dataset  # noqa: E402
from tensortouch.tools.train.model.train import FitConfig, _Progress, fit, load_trained, lr_at  # noqa: E402


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


def test_crop_affine_hand_worked():
    import torch
    from tensortouch.tools.train.model.train import crop_affine

    th = crop_affine(torch.tensor([2.0]), torch.tensor([[0.5, -0.25]]))
    assert torch.equal(th, torch.tensor([[[2.0, 0.0, 0.5], [0.0, 2.0, -0.25]]]))
    with pytest.raises(ValueError, match="expected scale \\(B,\\) and shift \\(B, 2\\)"):
        crop_affine(torch.ones(2), torch.zeros(3, 2))


def test_warp_crop_identity_shift_and_zoom_hand_worked():
    import torch
    from tensortouch.tools.train.model.train import warp_crop

    H = W = 16
    x = torch.zeros(1, 6, H, W)
    x[:, :, 6:10, 6:10] = 1.0                      # a 4 px block at the centre (inside the crop circle)
    zero = torch.full((1, 2, 1, 1), 0.25)
    y = zero.expand(1, 2, H, W).clone()
    y[:, :, 6:10, 6:10] = 0.75
    one, none = torch.ones(1), torch.zeros(1, 2)
    xo, yo = warp_crop(x, y, zero, one, none)      # the calibrated crop: unchanged
    assert torch.allclose(xo, x, atol=1e-6) and torch.allclose(yo, y, atol=1e-6)
    # the crop's centre 2 px to the right (2 px = 2 / 8 radii): the content moves 2 px left, target alike
    xo, yo = warp_crop(x, y, zero, one, torch.tensor([[2.0 / 8, 0.0]]))
    assert torch.allclose(xo[0, 0, 6:10, 4:8], torch.ones(4, 4), atol=1e-5)
    assert float(xo[0, 0, 6:10, 8:10].abs().max()) < 1e-5
    assert torch.allclose(yo[0, 1, 6:10, 4:8], torch.full((4, 4), 0.75), atol=1e-5)
    assert torch.allclose(yo[0, :, 0, 0], zero.view(2))
    # a crop circle of half the radius: the block fills twice the pixels; outside the frame the target is 0 N
    xo, yo = warp_crop(x, y, zero, torch.tensor([0.5]), none)
    assert torch.allclose(xo[0, 0, 5:11, 5:11], torch.ones(6, 6), atol=1e-5)     # 4 px → 8 px (edges bilinear)
    assert float(xo[0, 0, 2, 2]) == 0.0 and abs(float(xo[0, 0, 3, 3]) - 0.0625) < 1e-6   # 0.25 × 0.25 of the corner
    xo, yo = warp_crop(x, y, zero, torch.tensor([2.0]), none)
    assert torch.allclose(yo[0, :, 0, 0], zero.view(2)) and float(xo[0, :, 0, 0].abs().max()) == 0.0
    assert torch.allclose(xo[0, 0, 7:9, 7:9], torch.ones(2, 2), atol=1e-5)      # the block at half its size
    with pytest.raises(ValueError, match="expected inputs \\(B, 6, H, W\\)"):
        warp_crop(torch.zeros(1, 3, H, W), y, zero, one, none)
    with pytest.raises(ValueError, match="y_zero"):
        warp_crop(x, y, torch.zeros(1, 3, 1, 1), one, none)


def test_crop_jitter_draws_within_bounds_and_masks_the_circle():
    import torch
    from tensortouch.tools.train.model.train import crop_jitter

    torch.manual_seed(0)
    x, y = torch.rand(8, 6, 32, 32), torch.rand(8, 15, 32, 32)
    zero = torch.zeros(1, 15, 1, 1)
    xo, yo = crop_jitter(x, y, zero, 0.0, 0.0)
    inside = torch.linspace(-1 + 1 / 32, 1 - 1 / 32, 32)
    disc = (inside.view(-1, 1) ** 2 + inside.view(1, -1) ** 2) <= 1
    assert torch.allclose(xo[..., disc], x[..., disc], atol=1e-5) and torch.allclose(yo, y, atol=1e-5)
    assert float(xo[..., ~disc].abs().max()) == 0.0                 # masked outside the crop as the runtime does
    xo, yo = crop_jitter(x, y, zero, 0.1, 0.05)
    assert xo.shape == x.shape and yo.shape == y.shape and not torch.allclose(yo, y, atol=1e-3)
    with pytest.raises(ValueError, match="must lie in \\[0, 1\\)"):
        crop_jitter(x, y, zero, 1.0, 0.0)


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
