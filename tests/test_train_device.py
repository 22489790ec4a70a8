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
