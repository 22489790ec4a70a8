"""Which covariate best explains what remains? Held-out partial R² of smooth 1-D fits (pure core).

For every scalar covariate c the residual r (N,3) is explained in two ways by a piecewise-linear
function of c (hat basis on quantile knots, light ridge):
    additive:        r_j ≈ s_j(c)               (an offset that depends on c)
    multiplicative:  r ≈ F_pred * s(c)           (a gain error that depends on c)
and, for a vector covariate v (the indenter's velocity or acceleration from mocap):
    along:           r ≈ s(|v|) v/|v|             (a force along v that depends on its size: a drag)
each fitted on training blocks and scored on the held-out block (blocked CV). The score is the
held-out partial R² = 1 - SSE(c) / SSE(constant), where SSE(constant) is the better of "nothing"
and the same two forms with a constant instead of a function of c: what c explains beyond a
plain offset or gain error (0 = nothing more). Per held-out block the SSE gain over that
reference is kept (`block_gain`), so the diagnosis can test the top covariate's significance.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ScanConfig:
    knots: int = 8
    ridge: float = 1e-3           # relative to the mean diagonal of the normal equations
    min_unique: int = 4           # covariates with fewer distinct values are skipped


def hat_basis(c: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """(N, K) piecewise-linear interpolation weights of c on sorted knots (constant outside)."""
    c = np.clip(c, knots[0], knots[-1])
    j = np.clip(np.searchsorted(knots, c, side="right") - 1, 0, len(knots) - 2)
    w = (c - knots[j]) / np.maximum(knots[j + 1] - knots[j], 1e-12)
    B = np.zeros((len(c), len(knots)))
    rows = np.arange(len(c))
    B[rows, j] = 1.0 - w
    B[rows, j + 1] += w
    return B


def _designs(B: np.ndarray, pred: np.ndarray, direction: np.ndarray | None = None) -> dict[str, np.ndarray]:
    n, k = B.shape
    if direction is not None:
        return {"along": (direction[:, :, None] * B[:, None, :]).reshape(3 * n, k)}
    add = np.zeros((3 * n, 3 * k))
    for j in range(3):
        add[j::3, j * k:(j + 1) * k] = B
    mul = (pred[:, :, None] * B[:, None, :]).reshape(3 * n, k)
    return {"additive": add, "multiplicative": mul}


def _cv_sse(B: np.ndarray, resid: np.ndarray, pred: np.ndarray, blocks: np.ndarray,
            cfg: ScanConfig, direction: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Held-out SSE per block of each form with basis B (blocked CV from per-block sufficient statistics)."""
    y = resid.reshape(-1)
    rowblock = np.repeat(blocks, 3)
    out = {}
    for form, X in _designs(B, pred, direction).items():
        stats = []
        for b in np.unique(blocks):
            m = rowblock == b
            Xb, yb = X[m], y[m]
            stats.append((Xb.T @ Xb, Xb.T @ yb, float(yb @ yb)))
        XtX = sum(s[0] for s in stats)
        Xty = sum(s[1] for s in stats)
        sse = []
        for A_b, c_b, yy_b in stats:
            A = XtX - A_b
            A[np.diag_indices_from(A)] += cfg.ridge * max(float(np.mean(np.diag(A))), 1e-12)
            w = np.linalg.solve(A, Xty - c_b)
            sse.append(max(yy_b - 2.0 * float(w @ c_b) + float(w @ A_b @ w), 0.0))
        out[form] = np.asarray(sse)
    return out


def covariate_score(c: np.ndarray, resid: np.ndarray, pred: np.ndarray, blocks: np.ndarray,
                    cfg: ScanConfig | None = None, direction: np.ndarray | None = None) -> dict | None:
    """Held-out R² of the better of the smooth forms (with `direction`: the along form only);
    None when c cannot be scanned."""
    cfg = cfg or ScanConfig()
    ok = np.isfinite(c)
    if ok.sum() < 10 or len(np.unique(c[ok])) < cfg.min_unique:
        return None
    c = np.where(ok, c, np.nanmedian(c))
    knots = np.unique(np.quantile(c, np.linspace(0, 1, cfg.knots)))
    if len(knots) < 2:
        return None
    B = hat_basis(c, knots)
    ids = np.unique(blocks)
    e2 = np.sum(resid ** 2, axis=1)
    refs = {"nothing": np.array([float(e2[blocks == b].sum()) for b in ids])}
    refs.update(_cv_sse(np.ones((len(c), 1)), resid, pred, blocks, cfg))
    ref = min(refs.values(), key=lambda a: float(a.sum()))
    best = None
    for form, sse in _cv_sse(B, resid, pred, blocks, cfg, direction).items():
        score = 1.0 - float(sse.sum()) / max(float(ref.sum()), 1e-300)
        if best is None or score > best["score"]:
            best = {"score": score, "form": form, "block_gain": (ref - sse).tolist(), "block_ids": ids.tolist()}
    return best


def scan(cov: dict, names: dict[str, str], resid: np.ndarray, pred: np.ndarray, blocks: np.ndarray,
         cfg: ScanConfig | None = None, vectors: dict | None = None) -> list[dict]:
    """Scores of every scannable covariate, best first: [{covariate, unit, score, form, block_gain}].
    `vectors`: {name: ((x, y, z columns), unit)} scanned with the along form on their magnitude."""
    out = []
    for name, unit in names.items():
        if name not in cov or np.ndim(cov[name]) != 1:
            continue
        s = covariate_score(np.asarray(cov[name], dtype=np.float64), resid, pred, blocks, cfg)
        if s is not None:
            out.append({"covariate": name, "unit": unit, **s})
    for name, (cols, unit) in (vectors or {}).items():
        if not all(k in cov for k in cols):
            continue
        v = np.column_stack([np.asarray(cov[k], dtype=np.float64) for k in cols])
        mag = np.linalg.norm(v, axis=1)
        s = covariate_score(mag, resid, pred, blocks, cfg, v / np.maximum(mag, 1e-12)[:, None])
        if s is not None:
            out.append({"covariate": name, "unit": unit, **s})
    out.sort(key=lambda d: -d["score"])
    return out
