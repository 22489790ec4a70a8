"""Exact export-time rewrites of a trained network (no retraining, same function, faster ONNX graph).

Applied by `tools/train/export.py` before `torch.onnx.export`; each rewrite is checked numerically
against the original module (`reparametrize` raises if the outputs differ beyond float rounding).

- `FusedHeads`   the five 3-channel heads of `qupsample.Heads` (conv k×k → GELU → 1×1 conv → pixel
                 shuffle, one per modality) as ONE k×k conv (all hidden channels), one GELU, and one
                 grouped 1×1 conv + pixel shuffle. Per-head shuffle-then-concat equals concat-then-
                 shuffle because each head's 3·s² channels are contiguous.
- `ConvShuffle`  PixelShuffle(s) ∘ Conv2d(k×k odd, stride 1, "same" padding, groups g) as one
                 ConvTranspose2d (kernel s·k, stride s, padding s·(k//2)) plus the conv bias laid out
                 as an s×s tile: out[c, s·i+a, s·j+b] takes tap (di, dj) at kernel position
                 (a + s·(k-1-di), b + s·(k-1-dj)). Used for the heads' 1×1 conv + shuffle, where it
                 removes a DepthToSpace over the full-resolution output (measured faster); the
                 stride-4 → 2 `to_half` conv keeps Conv + DepthToSpace (its ConvTranspose form,
                 kernel 6, measured slower in onnxruntime).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import nn

from .model.network_input import IN_CHANS

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RewriteConfig:
    fuse_heads: bool = True
    heads_shuffle_as_deconv: bool = True
    check_batch: int = 2              # random inputs used to check the rewrite (0: no check, for templates)
    check_atol: float = 1e-4          # max |difference| allowed on the [0, 1]-normalized outputs


class ConvShuffle(nn.Module):
    """PixelShuffle(s)(conv(x)) as one ConvTranspose2d plus a sub-position bias tile (exact)."""

    def __init__(self, conv: nn.Conv2d, s: int):
        super().__init__()
        k, g = conv.kernel_size[0], conv.groups
        r = k // 2
        if conv.kernel_size != (k, k) or k % 2 != 1 or conv.stride != (1, 1) or conv.padding != (r, r) \
                or conv.dilation != (1, 1) or conv.out_channels % (s * s * g):
            raise ValueError(f"ConvShuffle: needs an odd square 'same' conv with stride 1, got {conv}")
        cin, cout = conv.in_channels, conv.out_channels // (s * s)
        w = conv.weight.detach().reshape(cout, s, s, cin // g, k, k)          # [c, a, b, cin/g, di, dj]
        wt = torch.zeros(cin, cout // g, s * k, s * k, dtype=w.dtype)
        ci, co = cin // g, cout // g
        for a in range(s):
            for b in range(s):
                for di in range(k):
                    for dj in range(k):
                        u, v = a + s * (k - 1 - di), b + s * (k - 1 - dj)
                        tap = w[:, a, b, :, di, dj]                             # (cout, cin/g)
                        for j in range(g):
                            wt[j * ci:(j + 1) * ci, :, u, v] = tap[j * co:(j + 1) * co].T
        self.deconv = nn.ConvTranspose2d(cin, cout, s * k, stride=s, padding=s * r, groups=g, bias=False)
        self.deconv.weight.data.copy_(wt)
        self.s = s
        bias = conv.bias.detach() if conv.bias is not None else torch.zeros(conv.out_channels)
        self.register_buffer("bias_tile", bias.reshape(1, cout, s, s).clone())

    def forward(self, x):
        y = self.deconv(x)
        b, c, h, w = y.shape
        # bias[c, a, w % s] for output row s·i + a: rows taken in pairs (a = 0..s-1) so the addend is a
        # small (1, c, 1, s·w) constant broadcast over i (a full (c, h, w) constant would add ~1 MB to
        # the graph; a 6-D broadcast measured 20x slower in onnxruntime)
        tile = self.bias_tile.repeat(1, 1, 1, w // self.s).reshape(1, c, 1, self.s * w)
        return (y.reshape(b, c, h // self.s, self.s * w) + tile).reshape(b, c, h, w)


class FusedHeads(nn.Module):
    """`qupsample.Heads` (n × [Conv, GELU, Conv 1×1, PixelShuffle]) as one conv stack (exact)."""

    def __init__(self, heads: nn.Module, shuffle_as_deconv: bool = True):
        super().__init__()
        first = [h[0] for h in heads.heads]
        second = [h[2] for h in heads.heads]
        s = heads.heads[0][3].upscale_factor
        c1 = nn.Conv2d(first[0].in_channels, sum(c.out_channels for c in first), first[0].kernel_size,
                       padding=first[0].padding)
        c1.weight.data.copy_(torch.cat([c.weight.detach() for c in first]))
        c1.bias.data.copy_(torch.cat([c.bias.detach() for c in first]))
        c2 = nn.Conv2d(c1.out_channels, sum(c.out_channels for c in second), 1, groups=len(second))
        c2.weight.data.copy_(torch.cat([c.weight.detach() for c in second]))
        c2.bias.data.copy_(torch.cat([c.bias.detach() for c in second]))
        self.conv, self.act = c1, heads.heads[0][1]
        self.up = ConvShuffle(c2, s) if shuffle_as_deconv else nn.Sequential(c2, nn.PixelShuffle(s))

    def forward(self, x):
        return self.up(self.act(self.conv(x)))


def _fusable_heads(m: nn.Module) -> bool:
    hs = getattr(m, "heads", None)
    if not isinstance(hs, nn.ModuleList) or not hs:
        return False
    shapes = set()
    for h in hs:
        if not (isinstance(h, nn.Sequential) and len(h) == 4 and isinstance(h[0], nn.Conv2d)
                and isinstance(h[2], nn.Conv2d) and isinstance(h[3], nn.PixelShuffle)
                and h[2].kernel_size == (1, 1) and h[0].groups == 1 and h[2].groups == 1):
            return False
        shapes.add((h[0].in_channels, h[0].out_channels, h[0].kernel_size, h[0].padding, h[0].stride,
                    h[2].out_channels, h[3].upscale_factor, type(h[1]), getattr(h[1], "approximate", None)))
    return len(shapes) == 1


@torch.no_grad()
def reparametrize(model: nn.Module, image_size: int, in_channels: int = IN_CHANS,
                  cfg: RewriteConfig = RewriteConfig()) -> tuple[nn.Module, list[str]]:
    """Apply the rewrites in place where the structure matches; returns (model, names rewritten).

    Raises ValueError when a rewritten model's output differs from the original's by more than
    `cfg.check_atol` (the rewrite would then be wrong, not merely rounded)."""
    from .model.qupsample import Heads

    model = model.eval()
    done: list[str] = []
    if not cfg.fuse_heads:
        return model, done
    check = cfg.check_batch > 0
    if check:
        x = torch.rand(cfg.check_batch, in_channels, image_size, image_size, generator=torch.Generator().manual_seed(0))
        ref = model(x)
    for name, mod in list(model.named_modules()):
        if isinstance(mod, Heads) and _fusable_heads(mod):
            parent = model.get_submodule(name.rpartition(".")[0]) if "." in name else model
            setattr(parent, name.rpartition(".")[2], FusedHeads(mod, cfg.heads_shuffle_as_deconv))
            done.append(name)
    if done and check:
        err = float((model(x) - ref).abs().max())
        if err > cfg.check_atol:
            raise ValueError(f"export rewrite of {done} changed the output by {err:.3g} (> {cfg.check_atol})")
        log.info("export rewrites %s: max |Δ| %.2g on %d random inputs", done, err, cfg.check_batch)
    return model, done
