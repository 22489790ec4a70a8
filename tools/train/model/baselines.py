"""Baselines of a similar parameter count (seed Table: conv U-Net lineage and a plain ViT encoder).

- `UNet`: four-level convolutional U-Net (two 3×3 conv + GroupNorm + GELU per level, max-pool down,
  transposed-conv up, skip concatenation), same five heads.
- `ViTDense`: the seed's "ViT Encoder" baseline — a plain ViT over 8×8 patches with no hierarchical
  decoder: tokens → linear projection to pixels of each patch (+ a light conv refinement), same heads.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .layers import Block
from .network_input import IN_CHANS, NetworkInput
from .qupsample import Heads

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class UNetConfig:
    """Fully convolutional: any image size divisible by 2 ** len(widths)."""

    in_chans: int = IN_CHANS
    widths: tuple[int, ...] = (18, 36, 72, 144)
    head_channels: int = 16


def _double_conv(cin: int, cout: int) -> nn.Module:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.GroupNorm(math.gcd(8, cout), cout), nn.GELU(),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.GroupNorm(math.gcd(8, cout), cout), nn.GELU())


class UNet(nn.Module):
    def __init__(self, cfg: UNetConfig = UNetConfig()):
        super().__init__()
        w = cfg.widths
        self.down = nn.ModuleList()
        cin = cfg.in_chans
        for c in w:
            self.down.append(_double_conv(cin, c))
            cin = c
        self.bottom = _double_conv(w[-1], 2 * w[-1])
        self.ups, self.dec = nn.ModuleList(), nn.ModuleList()
        cin = 2 * w[-1]
        for c in reversed(w):
            self.ups.append(nn.ConvTranspose2d(cin, c, 2, 2))
            self.dec.append(_double_conv(2 * c, c))
            cin = c
        self.to_heads = nn.Conv2d(w[0], cfg.head_channels, 1)
        self.heads = Heads(cfg.head_channels)

    def forward(self, x):
        skips = []
        for blk in self.down:
            x = blk(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        x = self.bottom(x)
        for up, dec, skip in zip(self.ups, self.dec, reversed(skips)):
            x = dec(torch.cat([up(x), skip], 1))
        return self.heads(F.gelu(self.to_heads(x)))


@dataclass(frozen=True)
class ViTConfig(NetworkInput):
    patch: int = 8
    dim: int = 176
    depth: int = 6
    heads: int = 4
    head_channels: int = 16


class ViTDense(nn.Module):
    def __init__(self, cfg: ViTConfig = ViTConfig()):
        super().__init__()
        self.cfg = cfg
        g = cfg.image_size // cfg.patch
        self.embed = nn.Conv2d(cfg.in_chans, cfg.dim, cfg.patch, cfg.patch)
        self.pos = nn.Parameter(torch.zeros(1, g * g, cfg.dim))
        nn.init.trunc_normal_(self.pos, std=0.02)
        self.blocks = nn.ModuleList(Block(cfg.dim, cfg.heads) for _ in range(cfg.depth))
        self.norm = nn.LayerNorm(cfg.dim)
        self.to_pix = nn.Linear(cfg.dim, cfg.head_channels * cfg.patch ** 2)
        self.refine = nn.Sequential(nn.Conv2d(cfg.head_channels, cfg.head_channels, 3, padding=1), nn.GELU())
        self.heads = Heads(cfg.head_channels)

    def forward(self, x):
        b, _, h, w = x.shape
        p, c = self.cfg.patch, self.cfg.head_channels
        t = self.embed(x).flatten(2).transpose(1, 2) + self.pos
        t = t[:, None]
        for blk in self.blocks:
            t = blk(t)
        t = self.to_pix(self.norm(t[:, 0]))                               # (B, g², c·p²)
        gh, gw = h // p, w // p
        img = t.reshape(b, gh, gw, c, p, p).permute(0, 3, 1, 4, 2, 5).reshape(b, c, h, w)
        return self.heads(self.refine(img))
