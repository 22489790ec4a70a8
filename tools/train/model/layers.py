"""Shared transformer pieces: attention (SDPA when training, explicit MatMul/Softmax when exporting
to ONNX so the graph quantizes cleanly), MLP, pre-norm block, mask-unit layout helpers."""
from __future__ import annotations

import logging

import torch
import torch.nn.functional as F
from torch import nn

log = logging.getLogger(__name__)


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """softmax(q·kᵀ/√d)·v over the last two dims of (..., L, d)."""
    if torch.onnx.is_in_onnx_export():
        scale = q.shape[-1] ** -0.5
        return torch.softmax((q * scale) @ k.transpose(-2, -1), dim=-1) @ v
    return F.scaled_dot_product_attention(q, k, v)


class Mlp(nn.Module):
    def __init__(self, dim: int, ratio: float = 4.0, dim_out: int | None = None):
        super().__init__()
        hidden = int(dim * ratio)
        self.fc1, self.fc2 = nn.Linear(dim, hidden), nn.Linear(hidden, dim_out or dim)

    def forward(self, x):
        return self.fc2(F.gelu(self.fc1(x)))


class Attention(nn.Module):
    """Multi-head self-attention on (B, N, L, C) token groups: attention within each group N
    (N = mask units for local attention, N = 1 for global attention)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv, self.proj = nn.Linear(dim, 3 * dim), nn.Linear(dim, dim)

    def forward(self, x):
        b, n, l, c = x.shape
        qkv = self.qkv(x).reshape(b, n, l, 3, self.heads, c // self.heads).permute(3, 0, 1, 4, 2, 5)
        out = attention(qkv[0], qkv[1], qkv[2])                      # (B, N, h, L, d)
        return self.proj(out.permute(0, 1, 3, 2, 4).reshape(b, n, l, c))


class Block(nn.Module):
    """Pre-norm transformer block on (B, N, L, C)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float = 4.0):
        super().__init__()
        self.norm1, self.norm2 = nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.attn, self.mlp = Attention(dim, heads), Mlp(dim, mlp_ratio)

    def forward(self, x):
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


def to_units(x: torch.Tensor, unit: tuple[int, int]) -> torch.Tensor:
    """(B, C, H, W) → (B, U, h·w, C): mask-unit windows of size unit=(h, w), row-major units."""
    b, c, hh, ww = x.shape
    h, w = unit
    x = x.reshape(b, c, hh // h, h, ww // w, w).permute(0, 2, 4, 3, 5, 1)
    return x.reshape(b, (hh // h) * (ww // w), h * w, c)


def from_units(x: torch.Tensor, unit: tuple[int, int], grid: tuple[int, int]) -> torch.Tensor:
    """Inverse of to_units: (B, U, h·w, C) → (B, C, gh·h, gw·w)."""
    b, _, _, c = x.shape
    h, w = unit
    gh, gw = grid
    return x.reshape(b, gh, gw, h, w, c).permute(0, 5, 1, 3, 2, 4).reshape(b, c, gh * h, gw * w)


def unit_pool(x: torch.Tensor, unit: tuple[int, int], stride: int = 2) -> torch.Tensor:
    """Max-pool (stride × stride) inside each mask unit: (B, U, h·w, C) → (B, U, h·w/stride², C)."""
    b, u, _, c = x.shape
    h, w = unit
    x = x.reshape(b, u, h // stride, stride, w // stride, stride, c)
    return x.amax(dim=(3, 5)).reshape(b, u, (h // stride) * (w // stride), c)


def count_params(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
