"""Stage 6 — networks (seed §III.J): Hiera + Q-Upsample, MAE pretraining, baselines, metrics, training;
the int8 convolutional student (convnet.py, issue #44).

`build_model(arch, image_size)` is the single place that maps an architecture name to a module, so
checkpoints store only (arch, image_size) plus weights.
"""
from __future__ import annotations

ARCHS = ("hiera_qup", "unet", "vit", "convnet")


def build_model(arch: str, image_size: int):
    """A fresh network for `arch` ∈ ARCHS at a square input size (6 ch in, 15 ch out)."""
    if arch == "hiera_qup":
        from .hiera import HieraConfig
        from .qupsample import HieraQUpsample

        return HieraQUpsample(HieraConfig(image_size=image_size))
    if arch == "unet":
        from .baselines import UNet

        return UNet()
    if arch == "vit":
        from .baselines import ViTConfig, ViTDense

        return ViTDense(ViTConfig(image_size=image_size))
    if arch == "convnet":
        from .convnet import ConvFieldNet, ConvNetConfig

        return ConvFieldNet(ConvNetConfig(image_size=image_size))
    raise ValueError(f"unknown architecture {arch!r}; choose one of {ARCHS}")
