"""Hiera encoder, written from the paper's description (Ryali et al. 2023), small CPU configuration.

Tokens are kept in mask-unit layout (B, U, h·w, C): U mask units of h×w tokens. That makes the three
Hiera ingredients plain tensor ops: mask-unit attention = attention within each unit, Q-pooling =
max-pool inside each unit, MAE = dropping whole units (the encoder never sees masked units).
Stages double the width and heads and halve the resolution (q_stride 2); the first block of a new
stage pools its queries and projects its residual; stages with `mask_unit_attn` attend inside units
(lagged by one block, as in Hiera: the pooling block still uses the previous stage's setting).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import nn

from .layers import Mlp, attention, from_units, to_units, unit_pool
from .network_input import NetworkInput

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HieraConfig(NetworkInput):
    """DESIGN §10 small CPU configuration as defaults."""

    embed_dim: int = 32
    heads: int = 1
    stages: tuple[int, ...] = (1, 2, 3, 1)
    mask_unit: int = 8                    # tokens per side of a mask unit at stage 1
    patch_stride: int = 4                 # patch-embed conv: kernel 7, stride 4, padding 3
    patch_kernel: int = 7
    q_stride: int = 2
    mask_unit_attn: tuple[bool, ...] = (True, True, False, False)
    mlp_ratio: float = 4.0

    @property
    def tokens(self) -> int:
        return self.image_size // self.patch_stride

    @property
    def grid(self) -> tuple[int, int]:
        g = self.tokens // self.mask_unit
        return g, g

    def dims(self) -> list[int]:
        return [self.embed_dim * 2 ** i for i in range(len(self.stages))]

    def validate(self) -> None:
        pooled = self.mask_unit // self.q_stride ** (len(self.stages) - 1)
        if self.tokens % self.mask_unit or pooled < 1:
            raise ValueError(f"HieraConfig: image {self.image_size} / stride {self.patch_stride} must be a "
                             f"multiple of mask_unit {self.mask_unit} and the unit must survive "
                             f"{len(self.stages) - 1} poolings")


class HieraBlock(nn.Module):
    def __init__(self, dim: int, dim_out: int, heads: int, unit_side: int, pool: bool, unit_attn: bool,
                 mlp_ratio: float, q_stride: int):
        super().__init__()
        self.dim, self.dim_out, self.heads = dim, dim_out, heads
        self.unit_side, self.pool, self.unit_attn, self.q_stride = unit_side, pool, unit_attn, q_stride
        self.norm1 = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim_out)
        self.proj = nn.Linear(dim_out, dim_out)
        self.res_proj = nn.Linear(dim, dim_out) if dim != dim_out else None
        self.norm2 = nn.LayerNorm(dim_out)
        self.mlp = Mlp(dim_out, mlp_ratio)

    def _attn(self, x: torch.Tensor) -> torch.Tensor:
        b, u, t, _ = x.shape
        unit = (self.unit_side, self.unit_side)
        qkv = self.qkv(x)                                               # (B, U, T, 3C')
        q, k, v = qkv.chunk(3, dim=-1)
        if self.pool:
            q = unit_pool(q, unit, self.q_stride)
        tq = q.shape[2]
        if not self.unit_attn:                                          # global: one group of all tokens
            q, k, v = (z.reshape(b, 1, -1, self.dim_out) for z in (q, k, v))
        g = q.shape[1]
        d = self.dim_out // self.heads
        q, k, v = (z.reshape(b, g, z.shape[2], self.heads, d).transpose(2, 3) for z in (q, k, v))
        out = attention(q, k, v).transpose(2, 3).reshape(b, u, tq, self.dim_out)
        return self.proj(out)

    def forward(self, x):
        xn = self.norm1(x)
        res = x
        if self.res_proj is not None:
            res = self.res_proj(xn)
        if self.pool:
            res = unit_pool(res, (self.unit_side, self.unit_side), self.q_stride)
        x = res + self._attn(xn)
        return x + self.mlp(self.norm2(x))


class Hiera(nn.Module):
    """Encoder: (B, 6, H, W) → list of stage feature maps [(B, C_i, H/4/2^i, W/4/2^i)]."""

    def __init__(self, cfg: HieraConfig = HieraConfig()):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        dims = cfg.dims()
        self.patch_embed = nn.Conv2d(cfg.in_chans, cfg.embed_dim, cfg.patch_kernel, cfg.patch_stride,
                                     cfg.patch_kernel // 2)
        self.pos_embed = nn.Parameter(torch.zeros(1, cfg.embed_dim, cfg.tokens, cfg.tokens))
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        self.blocks = nn.ModuleList()
        self.stage_ends: list[int] = []
        self.unit_sides: list[int] = []           # unit side (tokens) at the output of each stage
        side, dim, lag_attn = cfg.mask_unit, cfg.embed_dim, cfg.mask_unit_attn[0]
        for s, depth in enumerate(cfg.stages):
            for i in range(depth):
                pool = s > 0 and i == 0
                dim_out = dims[s]
                heads_s = cfg.heads * 2 ** s
                unit_attn = lag_attn if pool else cfg.mask_unit_attn[s]
                self.blocks.append(HieraBlock(dim, dim_out, heads_s, side, pool, unit_attn,
                                              cfg.mlp_ratio, cfg.q_stride))
                if pool:
                    side //= cfg.q_stride
                dim = dim_out
            lag_attn = cfg.mask_unit_attn[s]
            self.stage_ends.append(len(self.blocks) - 1)
            self.unit_sides.append(side)
        self.norms = nn.ModuleList(nn.LayerNorm(d) for d in dims)
        self.dims = dims

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """Patch embedding + absolute position → mask-unit layout (B, U, h·w, C)."""
        x = self.patch_embed(x) + self.pos_embed
        return to_units(x, (self.cfg.mask_unit, self.cfg.mask_unit))

    def forward_units(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Run the blocks on unit-layout tokens (possibly a subset of units); stage outputs in unit layout."""
        outs = []
        stage = 0
        for i, blk in enumerate(self.blocks):
            x = blk(x)
            if i == self.stage_ends[stage]:
                outs.append(self.norms[stage](x))
                stage += 1
        return outs

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        outs = self.forward_units(self.embed(x))
        return [from_units(o, (s, s), self.cfg.grid) for o, s in zip(outs, self.unit_sides)]


class HieraMAE(nn.Module):
    """MAE pretraining: drop `mask_ratio` of the mask units, encode the visible ones, fuse the
    stage outputs at the last stage's resolution, and reconstruct every unit's pixels with a light
    ViT-style decoder; the loss is on masked units only (per-unit normalized pixel targets)."""

    def __init__(self, encoder: Hiera, decoder_dim: int = 64, decoder_depth: int = 2,
                 decoder_heads: int = 2, mask_ratio: float = 0.75):
        super().__init__()
        from .layers import Block

        cfg = encoder.cfg
        self.encoder, self.mask_ratio = encoder, mask_ratio
        last_side = encoder.unit_sides[-1]
        # multi-scale fusion: each stage → last-stage resolution by a strided conv (kernel = stride)
        self.fuse = nn.ModuleList()
        for d, side in zip(encoder.dims, encoder.unit_sides):
            k = side // last_side
            self.fuse.append(nn.Conv2d(d, encoder.dims[-1], k, k))
        t_last = last_side ** 2
        self.embed = nn.Linear(encoder.dims[-1] * t_last, decoder_dim)
        self.mask_token = nn.Parameter(torch.zeros(1, 1, decoder_dim))
        n_units = cfg.grid[0] * cfg.grid[1]
        self.dec_pos = nn.Parameter(torch.zeros(1, n_units, decoder_dim))
        nn.init.trunc_normal_(self.dec_pos, std=0.02)
        nn.init.trunc_normal_(self.mask_token, std=0.02)
        self.blocks = nn.ModuleList(Block(decoder_dim, decoder_heads) for _ in range(decoder_depth))
        self.norm = nn.LayerNorm(decoder_dim)
        self.unit_px = cfg.mask_unit * cfg.patch_stride
        self.pred = nn.Linear(decoder_dim, cfg.in_chans * self.unit_px ** 2)

    def n_visible(self, n_units: int) -> int:
        """Visible units per sample: round((1 − ratio)·U), at least 1."""
        return max(1, int(round(n_units * (1 - self.mask_ratio))))

    def random_mask(self, b: int, n_units: int, generator: torch.Generator | None = None,
                    device: torch.device | str | None = None) -> torch.Tensor:
        """(B, U) bool on `device` (default: the model's), True = visible; exactly `n_visible(U)` visible
        units per sample. The uniform draw comes from the CPU generator (torch's global one unless
        `generator`), whose state a checkpoint keeps, so the same seed masks the same units on every
        device and a resumed run draws the same masks; only the (B, U) draw crosses to the device."""
        device = torch.device(device) if device is not None else self.mask_token.device
        n_vis = self.n_visible(n_units)
        noise = torch.rand(b, n_units, generator=generator).to(device)
        ids = noise.argsort(dim=1)[:, :n_vis]
        vis = torch.zeros(b, n_units, dtype=torch.bool, device=device)
        vis.scatter_(1, ids, True)
        return vis

    def unit_pixels(self, img: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) → (B, U, C·P²) pixels per mask unit (P = unit size in pixels)."""
        u = to_units(img, (self.unit_px, self.unit_px))                 # (B, U, P², C)
        return u.permute(0, 1, 3, 2).reshape(u.shape[0], u.shape[1], -1)

    def forward(self, img: torch.Tensor, visible: torch.Tensor | None = None):
        enc = self.encoder
        b = img.shape[0]
        tokens = enc.embed(img)                                         # (B, U, T, C)
        n_units = tokens.shape[1]
        if visible is None:
            visible = self.random_mask(b, n_units, device=img.device)
            n_vis = self.n_visible(n_units)            # known without reading the mask back from the device
        else:
            visible = visible.to(img.device)
            n_vis = int(visible[0].sum())
        idx = visible.float().argsort(dim=1, descending=True, stable=True)[:, :n_vis]   # visible unit ids
        gathered = torch.gather(tokens, 1, idx[:, :, None, None].expand(-1, -1, tokens.shape[2], tokens.shape[3]))
        outs = enc.forward_units(gathered)
        fused = 0
        for o, side, conv in zip(outs, enc.unit_sides, self.fuse):
            bu = o.shape[0] * o.shape[1]
            o = o.reshape(bu, side, side, o.shape[-1]).permute(0, 3, 1, 2)
            fused = fused + conv(o)                                     # (B·Uv, C4, s, s)
        fused = fused.flatten(1).reshape(b, n_vis, -1)
        z = self.embed(fused)
        full = self.mask_token.expand(b, n_units, -1).clone()
        full = full.scatter(1, idx[:, :, None].expand(-1, -1, z.shape[-1]), z)
        x = (full + self.dec_pos)[:, None]                               # (B, 1, U, D): global attention
        for blk in self.blocks:
            x = blk(x)
        pred = self.pred(self.norm(x[:, 0]))                              # (B, U, C·P²)
        target = self.unit_pixels(img)
        mean, var = target.mean(-1, keepdim=True), target.var(-1, keepdim=True)
        target = (target - mean) / (var + 1e-6).sqrt()
        per_unit = ((pred - target) ** 2).mean(-1)
        masked = (~visible).float()
        loss = (per_unit * masked).sum() / masked.sum().clamp(min=1)
        return loss, pred, visible
