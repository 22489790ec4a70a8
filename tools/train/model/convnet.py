"""A convolutional encoder-decoder made for int8 on one CPU core (issue #44).

Every weighted layer is a convolution followed by BatchNorm (folded into the convolution when exported)
and ReLU, so onnxruntime's static QDQ quantization covers the whole graph: no LayerNorm, GELU, Softmax
or attention matmul stays in float. Shape: a stride-2 pyramid (128² → 64² → 32² → 16² → 8²; most blocks
at the coarse levels, where they are cheap), an FPN-style decoder that adds each level's 1×1 lateral to the nearest-neighbour upsampled coarser level, and a 1×1 head
at 64² whose 15·4 channels a pixel shuffle turns into the 15 full-resolution fields (the targets are smooth
at the pixel scale; the Hiera network's heads use the same shuffle).

(B, 6, H, W) inputs in [0, 1] → (B, 15, H, W) normalized fields, the contract of every network here.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from ....contracts.fields import N_CHANNELS
from .network_input import NetworkInput


@dataclass(frozen=True)
class ConvNetConfig(NetworkInput):
    # encoder widths at strides 2, 4, 8, 16 and the residual 3×3 blocks after each downsampling
    widths: tuple[int, ...] = (16, 32, 64, 128)
    blocks: tuple[int, ...] = (0, 1, 3, 3)
    # decoder widths at strides 16, 8, 4, 2 (coarse to fine)
    decoder: tuple[int, ...] = (96, 64, 32, 24)
    shuffle: int = 2                     # the head works at stride `shuffle`, a pixel shuffle restores full size


def conv_bn_relu(cin: int, cout: int, k: int = 3, stride: int = 1, relu: bool = True) -> nn.Sequential:
    layers = [nn.Conv2d(cin, cout, k, stride, k // 2, bias=False), nn.BatchNorm2d(cout)]
    if relu:
        layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class Residual(nn.Module):
    """x + BN(conv(ReLU(BN(conv(x))))), then ReLU: the int8-friendly basic block."""

    def __init__(self, ch: int):
        super().__init__()
        self.body = nn.Sequential(conv_bn_relu(ch, ch), conv_bn_relu(ch, ch, relu=False))
        self.act = nn.ReLU(inplace=True)

    def forward(self, x):
        return self.act(x + self.body(x))


class ShuffleHead(nn.Module):
    """1×1 convolution to 15·r² channels + pixel shuffle → 15 channels at r× the resolution; the same
    `set_output_bias` / `remap_output` interface as the Hiera network's heads (tools/train/model/train.py)."""

    def __init__(self, ch: int, shuffle: int):
        super().__init__()
        self.r2 = shuffle ** 2
        self.conv = nn.Conv2d(ch, N_CHANNELS * self.r2, 1)
        self.shuffle = nn.PixelShuffle(shuffle)

    @torch.no_grad()
    def set_output_bias(self, mean: torch.Tensor) -> None:
        """Start every output channel at the dataset's mean target (15,)."""
        if mean.shape != (N_CHANNELS,):
            raise ValueError(f"set_output_bias: expected ({N_CHANNELS},) means, got {tuple(mean.shape)}")
        self.conv.bias.copy_(mean.to(self.conv.bias.dtype).repeat_interleave(self.r2))

    @torch.no_grad()
    def remap_output(self, scale: torch.Tensor, offset: torch.Tensor) -> None:
        """Make output channel k exactly scale[k]·y_k + offset[k] (15,) by rescaling the 1×1 convolution."""
        a = scale.to(self.conv.weight.dtype).repeat_interleave(self.r2)
        b = offset.to(self.conv.weight.dtype).repeat_interleave(self.r2)
        self.conv.weight.mul_(a.view(-1, 1, 1, 1))
        self.conv.bias.mul_(a).add_(b)

    def forward(self, x):
        return self.shuffle(self.conv(x))


class ConvFieldNet(nn.Module):
    """(B, 6, H, W) in [0, 1] → (B, 15, H, W) normalized fields; H = W divisible by 2^len(widths)."""

    channels_last = True      # the training loop runs it in channels-last memory (faster convolutions on the CPU)

    def __init__(self, cfg: ConvNetConfig = ConvNetConfig()):
        super().__init__()
        n = len(cfg.widths)
        if len(cfg.blocks) != n or len(cfg.decoder) != n:
            raise ValueError(f"ConvNetConfig: widths {cfg.widths}, blocks {cfg.blocks} and decoder {cfg.decoder} "
                             "need one entry per level")
        if cfg.image_size % 2 ** n:
            raise ValueError(f"ConvNetConfig: image_size {cfg.image_size} is not divisible by 2^{n}")
        if cfg.shuffle != 2:
            raise ValueError(f"ConvNetConfig: shuffle {cfg.shuffle}; the decoder ends at stride 2, so it must be 2")
        self.cfg = cfg
        self.stages = nn.ModuleList()
        cin = cfg.in_chans
        for w, b in zip(cfg.widths, cfg.blocks):
            self.stages.append(nn.Sequential(conv_bn_relu(cin, w, stride=2), *(Residual(w) for _ in range(b))))
            cin = w
        fine_first = list(reversed(cfg.widths))            # encoder widths, coarse to fine
        self.laterals = nn.ModuleList(conv_bn_relu(c, d, k=1, relu=False) for c, d in zip(fine_first, cfg.decoder))
        self.smooth = nn.ModuleList(conv_bn_relu(d, d) for d in cfg.decoder)
        # the upsampled coarser level is brought to the finer level's decoder width by a 1×1 before the add
        self.bridges = nn.ModuleList(conv_bn_relu(a, b, k=1, relu=False)
                                     for a, b in zip(cfg.decoder[:-1], cfg.decoder[1:]))
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.act = nn.ReLU(inplace=True)
        self.heads = ShuffleHead(cfg.decoder[-1], cfg.shuffle)

    def forward(self, x):
        feats = []
        for s in self.stages:
            x = s(x)
            feats.append(x)
        y = self.smooth[0](self.act(self.laterals[0](feats[-1])))
        for i in range(1, len(feats)):
            y = self.act(self.laterals[i](feats[-1 - i]) + self.up(self.bridges[i - 1](y)))
            y = self.smooth[i](y)
        return self.heads(y)
