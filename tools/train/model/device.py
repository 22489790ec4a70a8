"""Where training runs: `--device auto|cpu|cuda` and mixed precision on CUDA.

`resolve_device("auto")` is CUDA when `torch.cuda.is_available()` says so, else the CPU; "cuda"
without a CUDA device is an error naming the option. On CUDA the forward pass and loss run under
float16 autocast with a gradient scaler (`Precision`); on the CPU everything stays float32, as
before. The device is where a run executes, not what it learns from: it is not part of a run's
config.json, the recipe or the data hash, so the same recipe gives the same dataset anywhere and
a run may resume on another device. Since device and precision still change the weights, each run
records where it trained (train_config.json, `train.run_place`) and the package manifest copies it
(`training.run_place`).
"""
from __future__ import annotations

import contextlib

import torch

from .data import DatasetError

DEVICES = ("auto", "cpu", "cuda")


def cuda_available() -> bool:
    """The CUDA availability query (the one thing tests replace on machines without a GPU)."""
    return torch.cuda.is_available()


def resolve_device(request: str = "auto") -> torch.device:
    if request not in DEVICES:
        raise DatasetError(f"--device: expected one of {DEVICES}, got {request!r}")
    if request == "cpu":
        return torch.device("cpu")
    if cuda_available():
        return torch.device("cuda")
    if request == "cuda":
        raise DatasetError("--device cuda: no CUDA device is available (torch.cuda.is_available() is False; "
                           "install a CUDA build of torch, or use --device auto|cpu)")
    return torch.device("cpu")


class Precision:
    """Mixed precision on CUDA (float16 autocast + GradScaler), plain float32 elsewhere."""

    def __init__(self, device: torch.device, amp: bool = True):
        self.device = device
        self.enabled = bool(amp) and device.type == "cuda"
        self.scaler = torch.amp.GradScaler("cuda") if self.enabled else None

    def autocast(self):
        if not self.enabled:
            return contextlib.nullcontext()
        return torch.autocast(device_type="cuda", dtype=torch.float16)

    def step(self, loss: torch.Tensor, opt: torch.optim.Optimizer) -> None:
        """Backward + optimizer step (scaled on CUDA)."""
        if self.scaler is None:
            loss.backward()
            opt.step()
            return
        self.scaler.scale(loss).backward()
        self.scaler.step(opt)
        self.scaler.update()

    def state_dict(self) -> dict:
        return self.scaler.state_dict() if self.scaler is not None else {}

    def load_state_dict(self, state: dict) -> None:
        if self.scaler is not None and state:
            self.scaler.load_state_dict(state)


def cpu_state(module: torch.nn.Module) -> dict:
    """A module's state dict on the CPU (files written on a GPU load anywhere)."""
    return {k: v.detach().cpu() for k, v in module.state_dict().items()}
