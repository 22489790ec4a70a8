"""Fingertip pose selection (seed §III.N): sweep the thumb distal joint over a grid of z-offset ×
pitch, evaluate each variant's thumb–index contact workspace, score it, pick one.

Per variant: mean thumb manipulability over its contact configurations, the contact points,
their PCA axis and the best inlier axis (RANSAC-like, 1 cm radius). The choice balances the two
metrics: score = w̄ / max w̄ + inliers / max inliers (equal weights by default). Every variant sees
the same joint samples, so differences come from the mount, not from sampling noise.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from . import hand_model
from .axis import Axis, best_inlier_axis, pca_axis
from .hand_model import HandSpec
from .workspace import Workspace, WorkspaceConfig, evaluate, sample_q


@dataclass(frozen=True)
class MountConfig:
    z_cm: tuple[float, ...] = (3.5, 3.9, 4.3, 4.7, 5.1, 5.5)     # thumb distal joint z-offset
    pitch_deg: tuple[float, ...] = (-30.0, -20.0, -10.0, 0.0, 10.0, 20.0, 30.0)
    inlier_radius_m: float = 0.01                                 # seed: 1 cm
    ransac_trials: int = 400
    weight_manipulability: float = 0.5
    weight_inliers: float = 0.5
    workspace: WorkspaceConfig = field(default_factory=WorkspaceConfig)


@dataclass
class VariantResult:
    z_cm: float
    pitch_deg: float
    mean_w: float               # mean thumb manipulability over the contacts (nan: no contact)
    n_contacts: int
    pca: Axis | None
    best: Axis | None
    workspace: Workspace

    @property
    def inliers(self) -> int:
        return int(self.best.inliers.sum()) if self.best is not None else 0


@dataclass
class MountResult:
    config: MountConfig
    variants: list[VariantResult]
    chosen: VariantResult
    seconds: float

    def grid(self, what: str) -> np.ndarray:
        """(len(z), len(pitch)) array of `mean_w`, `inliers` or `n_contacts`."""
        nz, npitch = len(self.config.z_cm), len(self.config.pitch_deg)
        return np.array([float(getattr(v, what)) for v in self.variants]).reshape(nz, npitch)


def evaluate_variant(model, spec: HandSpec, nominal, z_cm: float, pitch_deg: float, q: np.ndarray,
                     cfg: MountConfig, seed: int = 0) -> VariantResult:
    hand_model.apply_variant(model, spec, nominal, z_cm / 100.0, np.radians(pitch_deg))
    ws = evaluate(model, spec, q, cfg.workspace)
    pts = ws.contact_points
    mean_w = float(ws.w_thumb[ws.contact].mean()) if len(pts) else float("nan")
    pca = pca_axis(pts) if len(pts) >= 2 else None
    best = (best_inlier_axis(pts, cfg.inlier_radius_m, cfg.ransac_trials, np.random.default_rng(seed))
            if len(pts) >= 2 else None)
    return VariantResult(z_cm, pitch_deg, mean_w, len(pts), pca, best, ws)


def score(variants: list[VariantResult], cfg: MountConfig) -> np.ndarray:
    w = np.array([v.mean_w for v in variants])
    inl = np.array([v.inliers for v in variants], float)
    w = np.nan_to_num(w, nan=0.0)
    wn = w / w.max() if w.max() > 0 else w
    inn = inl / inl.max() if inl.max() > 0 else inl
    return cfg.weight_manipulability * wn + cfg.weight_inliers * inn


def select(urdf=None, spec: HandSpec | None = None, cfg: MountConfig | None = None,
           progress=None) -> MountResult:
    """Sweep every variant; `progress(i, n, variant)` is called after each."""
    cfg = cfg or MountConfig()
    spec = spec or HandSpec()
    model = hand_model.load(urdf, spec)
    nominal = hand_model.nominal_placement(model, spec)
    q = sample_q(model, spec, cfg.workspace.samples, np.random.default_rng(cfg.workspace.seed))
    t0 = time.perf_counter()
    out = []
    grid = [(z, p) for z in cfg.z_cm for p in cfg.pitch_deg]
    for i, (z, p) in enumerate(grid):
        out.append(evaluate_variant(model, spec, nominal, z, p, q, cfg, seed=cfg.workspace.seed + i))
        if progress:
            progress(i + 1, len(grid), out[-1])
    s = score(out, cfg)
    chosen = out[int(np.argmax(s))]
    hand_model.apply_variant(model, spec, nominal, chosen.z_cm / 100, np.radians(chosen.pitch_deg))
    return MountResult(cfg, out, chosen, time.perf_counter() - t0)
