"""Q-Upsample decoder and the full TensorTouch network (seed §III.J).

Decoding goes coarse → fine over Hiera's stage maps. At each level:
1. an attention block over that level's spatial tokens ("relevant regions are focused on at every
   level"; global at coarse levels, inside mask units at the finest one);
2. Q-Upsample: the inverse of Hiera's Q-pooling — every coarse token is expanded into q_stride²
   queries (a linear map plus a learned sub-position embedding), and those queries attend to the
   level's keys/values, giving a map at twice the resolution;
3. fusion with the encoder feature of the same size (concat → linear → MLP), keeping fine detail.
After the stride-4 level, a ×2 pixel-shuffle convolution reaches half resolution and five small
convolution heads (displacement, normal stress, shear stress, contact normal, contact shear), each
ending in a ×2 pixel shuffle to full resolution, give three channels each: 15 in docs/fields.md order.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import nn

from ....contracts.fields import MODALITIES
from .hiera import Hiera, HieraConfig
from .layers import Block, Mlp, attention, from_units, to_units

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class QUpsampleConfig:
    dims: tuple[int, ...] = (128, 64, 32)    # decoder width at encoder levels 3, 2, 1 (stride 16, 8, 4)
    heads: tuple[int, ...] = (4, 2, 1)
    head_channels: int = 32                  # features at half resolution feeding the heads
    head_hidden: int = 16
    mlp_ratio: float = 2.0
    local_tokens: int = 256                  # levels with more tokens use attention inside mask units


class QUpsample(nn.Module):
    """Queries at 2× resolution from the coarse tokens, attending to the coarse keys/values."""

    def __init__(self, dim_in: int, dim_out: int, heads: int, stride: int = 2):
        super().__init__()
        self.heads, self.stride, self.dim_out = heads, stride, dim_out
        self.norm = nn.LayerNorm(dim_in)
        self.q = nn.Linear(dim_in, dim_out)
        self.kv = nn.Linear(dim_in, 2 * dim_out)
        self.sub_pos = nn.Parameter(torch.zeros(stride * stride, dim_out))
        nn.init.trunc_normal_(self.sub_pos, std=0.02)
        self.proj = nn.Linear(dim_out, dim_out)
        self.res = nn.Linear(dim_in, dim_out)

    def _up(self, x: torch.Tensor, sub_pos: bool = True) -> torch.Tensor:
        """(B, h, w, C) → (B, s·h, s·w, C), nearest; with sub_pos each sub-position gets its embedding."""
        b, h, w, c = x.shape
        s = self.stride
        x = x[:, :, None, :, None, :].expand(b, h, s, w, s, c)
        if sub_pos:
            x = x + self.sub_pos.reshape(1, 1, s, 1, s, c)
        return x.reshape(b, h * s, w * s, c)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, C, h, w) → (B, C', s·h, s·w)."""
        b, _, h, w = x.shape
        xt = self.norm(x.permute(0, 2, 3, 1))                           # (B, h, w, C)
        q = self._up(self.q(xt)).reshape(b, -1, self.dim_out)
        k, v = self.kv(xt).reshape(b, h * w, 2, self.dim_out).unbind(2)
        d = self.dim_out // self.heads
        q, k, v = (z.reshape(b, z.shape[1], self.heads, d).transpose(1, 2) for z in (q, k, v))
        out = attention(q, k, v).transpose(1, 2).reshape(b, -1, self.dim_out)
        res = self._up(self.res(xt), sub_pos=False).reshape(b, -1, self.dim_out)
        y = res + self.proj(out)
        return y.reshape(b, h * self.stride, w * self.stride, self.dim_out).permute(0, 3, 1, 2)


class LevelAttention(nn.Module):
    """Transformer block over a level's spatial tokens; inside mask units when the level is large."""

    def __init__(self, dim: int, heads: int, unit: int | None, mlp_ratio: float):
        super().__init__()
        self.block, self.unit = Block(dim, heads, mlp_ratio), unit

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        if self.unit:
            t = to_units(x, (self.unit, self.unit))
            return from_units(self.block(t), (self.unit, self.unit), (h // self.unit, w // self.unit))
        t = x.flatten(2).transpose(1, 2)[:, None]
        return self.block(t)[:, 0].transpose(1, 2).reshape(b, c, h, w)


class Fuse(nn.Module):
    def __init__(self, dim: int, skip_dim: int, mlp_ratio: float):
        super().__init__()
        self.lin = nn.Linear(dim + skip_dim, dim)
        self.norm = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, mlp_ratio)

    def forward(self, x, skip):
        y = self.lin(torch.cat([x, skip], 1).permute(0, 2, 3, 1))
        y = y + self.mlp(self.norm(y))
        return y.permute(0, 3, 1, 2)


class Heads(nn.Module):
    """Five 3-channel convolution heads, concatenated in docs/fields.md order.

    With `shuffle` = 2 each head works at half resolution and emits 3·4 channels that a pixel
    shuffle turns into 3 full-resolution channels (the targets are σ = 2 px smooth, so the sub-pixel
    layout is learned at a quarter of the cost of full-resolution convolutions)."""

    def __init__(self, ch: int, hidden: int = 8, shuffle: int = 1):
        super().__init__()
        self.names = list(MODALITIES)
        self.heads = nn.ModuleList(nn.Sequential(nn.Conv2d(ch, hidden, 3, padding=1), nn.GELU(),
                                                 nn.Conv2d(hidden, 3 * shuffle ** 2, 1), nn.PixelShuffle(shuffle))
                                   for _ in self.names)

    @torch.no_grad()
    def set_output_bias(self, mean: torch.Tensor) -> None:
        """Start every head at the dataset's per-channel mean target (15,), so training begins at the
        constant-mean predictor instead of at 0 (targets are min/max-normalized, mostly ≈ 0.3–0.7)."""
        for i, head in enumerate(self.heads):
            last = head[-2] if isinstance(head[-1], nn.PixelShuffle) else head[-1]
            reps = last.out_channels // 3
            last.bias.copy_(mean[3 * i:3 * i + 3].repeat_interleave(reps))

    @torch.no_grad()
    def remap_output(self, scale: torch.Tensor, offset: torch.Tensor) -> None:
        """Make every output channel k exactly scale[k]·y_k + offset[k] (15,) by rescaling the head's
        last convolution (its output channels c·r² … c·r² + r² − 1 become channel c after the pixel
        shuffle): a fine-tune on data normalized with other bounds starts at the same physical output."""
        for i, head in enumerate(self.heads):
            last = head[-2] if isinstance(head[-1], nn.PixelShuffle) else head[-1]
            reps = last.out_channels // 3
            a = scale[3 * i:3 * i + 3].to(last.weight.dtype).repeat_interleave(reps)
            b = offset[3 * i:3 * i + 3].to(last.weight.dtype).repeat_interleave(reps)
            last.weight.mul_(a.view(-1, *([1] * (last.weight.dim() - 1))))
            last.bias.mul_(a).add_(b)

    def forward(self, x):
        return torch.cat([h(x) for h in self.heads], 1)


def _up_conv(cin: int, cout: int) -> nn.Module:
    return nn.Sequential(nn.Conv2d(cin, 4 * cout, 3, padding=1), nn.PixelShuffle(2), nn.GELU())


class HieraQUpsample(nn.Module):
    """The shipped network: (B, 6, H, W) in [0, 1] → (B, 15, H, W) normalized fields."""

    def __init__(self, enc_cfg: HieraConfig = HieraConfig(), dec_cfg: QUpsampleConfig = QUpsampleConfig()):
        super().__init__()
        self.encoder = Hiera(enc_cfg)
        e = self.encoder.dims                       # e.g. 32, 64, 128, 256
        n_levels = len(e) - 1
        if len(dec_cfg.dims) != n_levels:
            raise ValueError(f"QUpsampleConfig.dims needs {n_levels} entries (one per finer encoder level)")
        self.levels = nn.ModuleList()
        prev = e[-1]
        tokens = enc_cfg.tokens // 2 ** (len(e) - 1)
        for i, (d, hd) in enumerate(zip(dec_cfg.dims, dec_cfg.heads)):
            level_tokens = tokens * tokens
            unit = self.encoder.unit_sides[-1 - i] if level_tokens > dec_cfg.local_tokens else None
            attn = LevelAttention(prev, max(1, hd * 2 if prev > d else hd), unit, dec_cfg.mlp_ratio)
            self.levels.append(nn.ModuleDict({
                "attn": attn, "up": QUpsample(prev, d, hd), "fuse": Fuse(d, e[-2 - i], dec_cfg.mlp_ratio)}))
            prev, tokens = d, tokens * 2
        hc = dec_cfg.head_channels
        self.to_half = _up_conv(prev, hc)               # stride 4 → 2
        self.heads = Heads(hc, dec_cfg.head_hidden, shuffle=2)

    def forward(self, x):
        feats = self.encoder(x)
        y = feats[-1]
        for i, lvl in enumerate(self.levels):
            y = lvl["attn"](y)
            y = lvl["up"](y)
            y = lvl["fuse"](y, feats[-2 - i])
        return self.heads(self.to_half(y))
