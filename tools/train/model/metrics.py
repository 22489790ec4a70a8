"""Evaluation metrics exactly as the seed's Table (§IV-C), averaged over the five modalities.

All inputs are (N, 15, H, W) arrays of *normalized* fields in [0, 1] (model space), so PSNR uses a
data range of 1. Each metric is computed per modality (the three channels of docs/fields.md's
triples, over all samples and pixels) and then averaged over the five modalities, as the seed does.

- MSE   mean squared error.
- PSNR  10·log10(1 / MSE).
- SSIM  Gaussian-window SSIM (σ = 1.5, K1 = 0.01, K2 = 0.03, L = 1) per channel image, averaged.
- FPR_rel  fraction of pixels whose relative error exceeds 100 %: |p − g| > |g| ("off by more than
  the true value"). Relative errors are taken in physical units when `bounds` are given (so zero
  means physical zero), else on the normalized values; the denominator is |g| + ε with
  ε = rel_eps · (hi − lo) of the channel, which makes an exact-zero truth count a false positive only
  when the prediction is off by more than ε.
- AUC_rel  area under the curve "fraction of pixels with relative error ≤ τ" for τ ∈ [0, 1],
  normalized to [0, 1] (1 = every pixel exact).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ....contracts.fields import CHANNELS, MODALITIES

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MetricConfig:
    ssim_sigma: float = 1.5
    ssim_k1: float = 0.01
    ssim_k2: float = 0.03
    data_range: float = 1.0
    rel_eps: float = 1e-2          # ε as a fraction of the channel's range
    auc_tau_max: float = 1.0
    auc_steps: int = 101


def ssim_image(a: np.ndarray, b: np.ndarray, cfg: MetricConfig = MetricConfig()) -> float:
    """Mean SSIM of two 2-D images (Gaussian window)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    c1, c2 = (cfg.ssim_k1 * cfg.data_range) ** 2, (cfg.ssim_k2 * cfg.data_range) ** 2
    f = lambda x: ndimage.gaussian_filter(x, cfg.ssim_sigma, mode="reflect", truncate=3.5)  # noqa: E731
    mu_a, mu_b = f(a), f(b)
    saa, sbb, sab = f(a * a) - mu_a ** 2, f(b * b) - mu_b ** 2, f(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (saa + sbb + c2))
    return float(s.mean())


def _relative_error(pred: np.ndarray, true: np.ndarray, bounds: dict | None, sl: slice,
                    cfg: MetricConfig) -> np.ndarray:
    names = CHANNELS[sl]
    if bounds is not None:
        lo = np.array([bounds[n][0] for n in names], dtype=np.float64)[None, :, None, None]
        span = np.array([bounds[n][1] - bounds[n][0] for n in names], dtype=np.float64)[None, :, None, None]
        p, g = lo + pred * span, lo + true * span
    else:
        span = np.ones((1, len(names), 1, 1))
        p, g = pred.astype(np.float64), true.astype(np.float64)
    return np.abs(p - g) / (np.abs(g) + cfg.rel_eps * span)


def evaluate(pred: np.ndarray, true: np.ndarray, bounds: dict | None = None,
             cfg: MetricConfig = MetricConfig()) -> dict:
    """{'per_modality': {name: {psnr, ssim, mse, auc_rel, fpr_rel}}, 'mean': {...}} for (N, 15, H, W)."""
    pred, true = np.asarray(pred, dtype=np.float64), np.asarray(true, dtype=np.float64)
    if pred.shape != true.shape or pred.ndim != 4 or pred.shape[1] != len(CHANNELS):
        raise ValueError(f"evaluate: pred {pred.shape} and true {true.shape} must both be (N, 15, H, W)")
    taus = np.linspace(0.0, cfg.auc_tau_max, cfg.auc_steps)
    per = {}
    for name, sl in MODALITIES.items():
        p, g = pred[:, sl], true[:, sl]
        mse = float(np.mean((p - g) ** 2))
        psnr = float(10 * np.log10(cfg.data_range ** 2 / max(mse, 1e-20)))
        ssim = float(np.mean([ssim_image(p[i, c], g[i, c], cfg) for i in range(p.shape[0])
                              for c in range(p.shape[1])]))
        rel = _relative_error(p, g, bounds, sl, cfg).ravel()
        rel_sorted = np.sort(rel)
        cdf = np.searchsorted(rel_sorted, taus, side="right") / rel.size
        auc = float(np.trapezoid(cdf, taus) / cfg.auc_tau_max)
        fpr = float(np.mean(rel > 1.0))
        per[name] = {"psnr": psnr, "ssim": ssim, "mse": mse, "auc_rel": auc, "fpr_rel": fpr}
    mean = {k: float(np.mean([v[k] for v in per.values()])) for k in next(iter(per.values()))}
    return {"per_modality": per, "mean": mean}


def psnr_per_modality(pred: np.ndarray, ref: np.ndarray, data_range: float = 1.0) -> dict[str, float]:
    """PSNR (dB) of pred against ref per modality (used for the fp32-vs-int8 parity report)."""
    out = {}
    for name, sl in MODALITIES.items():
        mse = float(np.mean((np.asarray(pred, np.float64)[:, sl] - np.asarray(ref, np.float64)[:, sl]) ** 2))
        out[name] = float(10 * np.log10(data_range ** 2 / max(mse, 1e-20)))
    return out
