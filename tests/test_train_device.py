"""Training device selection (issue 26 item 5): --device auto|cpu|cuda on a CPU-only machine.
Only the CUDA availability query (`tools.train.model.device.cuda_available`) is replaced, and the
tests that do so say "mocked_cuda_query"; every training step here runs for real on the CPU."""
import json

import pytest
import torch
from tensortouch.tools.train.model import device as dev
from tensortouch.tools.train.model.data import DatasetError, data_hash, write_synthetic_dataset
from tensortouch.tools.train.model.train import FitConfig, fit


def test_cpu_and_auto_without_cuda_select_the_cpu(monkeypatch):
    assert dev.resolve_device("cpu") == torch.device("cpu")
    monkeypatch.setattr(dev, "cuda_available", lambda: False)
    assert dev.resolve_device("auto") == torch.device("cpu")
    p = dev.Precision(torch.device("cpu"))
    assert not p.enabled and p.scaler is None and p.state_dict() == {}


def test_cuda_request_without_a_device_is_one_clear_error_mocked_cuda_query(monkeypatch):
    monkeypatch.setattr(dev, "cuda_available", lambda: False)
    with pytest.raises(DatasetError, match="--device cuda: no CUDA device"):
        dev.resolve_device("cuda")
    with pytest.raises(DatasetError, match="expected one of"):
        dev.resolve_device("gpu")


def test_auto_and_cuda_pick_cuda_when_present_mocked_cuda_query(monkeypatch):
    monkeypatch.setattr(dev, "cuda_available", lambda: True)
    assert dev.resolve_device("auto") == torch.device("cuda")
    assert dev.resolve_device("cuda") == torch.device("cuda")
    assert dev.resolve_device("cpu") == torch.device("cpu")   # an explicit CPU request wins


def test_device_is_not_part_of_the_run_or_the_data(tmp_path, monkeypatch):
    """Same data hash and same weights whether the CPU was asked for or chosen by auto; the device is
    not written into config.json, so a run started on one device resumes on another."""
    from tensortouch.tools.train.build import BuildConfig, stage_keys

    write_synthetic_dataset(tmp_path / "a", 12, size=32, seed=3)
    write_synthetic_dataset(tmp_path / "b", 12, size=32, seed=3)
    assert data_hash(tmp_path / "a") == data_hash(tmp_path / "b")
    assert stage_keys(BuildConfig(device="cuda")) == stage_keys(BuildConfig(device="cpu"))
    monkeypatch.setattr(dev, "cuda_available", lambda: False)
    runs = {}
    for name in ("cpu", "auto"):
        cfg = FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, device=name)
        fit(tmp_path / "a", tmp_path / name, cfg)
        assert "device" not in json.loads((tmp_path / name / "config.json").read_text())
        runs[name] = torch.load(tmp_path / name / "best.pt", weights_only=True)
    for k in runs["cpu"]:
        torch.testing.assert_close(runs["cpu"][k], runs["auto"][k])
    assert all(v.device.type == "cpu" for v in runs["cpu"].values())


def test_mae_pretraining_trains_on_the_meta_device():
    """Issue 42: the MAE mask was built on the CPU, so pretraining on any other device failed at
    stage 6. torch's `meta` device (shapes, no data) stands in for a GPU: the whole pretraining step —
    mask, forward, loss, backward, AdamW step through `Precision` — runs there, as `pretrain`'s loop
    does it, and every tensor stays on the model's device."""
    from tensortouch.tools.train.model.hiera import Hiera, HieraConfig, HieraMAE

    torch.manual_seed(0)
    mae = HieraMAE(Hiera(HieraConfig(image_size=64)), decoder_dim=32, decoder_depth=1).to("meta")
    meta = torch.device("meta")
    opt = torch.optim.AdamW(mae.parameters(), lr=1e-3)
    precision = dev.Precision(meta)
    x = torch.rand(2, 6, 64, 64, device=meta)
    for _ in range(3):
        opt.zero_grad(set_to_none=True)
        with precision.autocast():
            loss, pred, visible = mae(x)
        precision.step(loss.float(), opt)
        assert loss.device == meta and pred.shape == (2, 4, 6 * 32 * 32) and visible.device == meta
    assert all(p.device == meta and p.grad is not None for p in mae.parameters() if p.requires_grad)
    vis = mae.random_mask(2, 4)
    assert vis.device == meta and vis.dtype == torch.bool and vis.shape == (2, 4)


def test_the_mae_mask_is_the_same_on_every_device():
    """The mask's draw comes from the CPU generator: the same seed masks the same units wherever the
    model is (shown for the CPU against an explicit device argument) and the visible count is exact."""
    from tensortouch.tools.train.model.hiera import Hiera, HieraConfig, HieraMAE

    mae = HieraMAE(Hiera(HieraConfig(image_size=64)), decoder_dim=32, decoder_depth=1)
    a = mae.random_mask(3, 16, torch.Generator().manual_seed(5))
    b = mae.random_mask(3, 16, torch.Generator().manual_seed(5), device="cpu")
    assert torch.equal(a, b) and a.sum(1).tolist() == [4, 4, 4]
    assert mae.random_mask(1, 16, device="meta").device.type == "meta"


def test_each_run_records_where_it_trained(tmp_path):
    """train_config.json (and every checkpoint) holds the full config with device, precision, torch
    version and threads; a resume elsewhere adds a segment, the same place does not."""
    from tensortouch.tools.train.model.train import PretrainConfig, pretrain, train_config

    write_synthetic_dataset(tmp_path / "d", 8, size=32, seed=1)
    pretrain(tmp_path / "d", tmp_path / "p", PretrainConfig(epochs=1, batch_size=4, threads=1, device="cpu"))
    tc = json.loads((tmp_path / "p" / "train_config.json").read_text())
    assert tc["what"] == "pretrain" and tc["config"]["device"] == "cpu" and tc["config"]["mask_ratio"] == 0.75
    (seg,) = tc["segments"]
    assert seg == {"from_step": 0, "device": "cpu", "device_name": seg["device_name"], "precision": "float32",
                   "param_dtype": "float32", "torch": torch.__version__, "cuda": None, "threads": 1,
                   "deterministic_algorithms": False}
    assert torch.load(tmp_path / "p" / "checkpoint.pt", weights_only=False)["train_config"] == tc
    place = {k: v for k, v in seg.items() if k != "from_step"}
    cfg = PretrainConfig(epochs=1, threads=1)
    assert train_config(cfg, "pretrain", tc, place, 7)["segments"] == tc["segments"]
    moved = train_config(cfg, "pretrain", tc, {**place, "device": "cuda", "precision": "float16 autocast + grad scaling"}, 7)
    assert [s["from_step"] for s in moved["segments"]] == [0, 7] and moved["segments"][1]["device"] == "cuda"
