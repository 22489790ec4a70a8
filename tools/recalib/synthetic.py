"""Synthetic sensor units for testing and benchmarking the recalibration (no twin, no trained model).

A unit has a true force field and a "shipped model" whose force estimate carries a position- and
magnitude-dependent bias the model does not know about: a gel `stiffness_ratio` stiffer than
nominal (the model sees less deformation, so it under-reports by that factor), a gel centre shifted
by `center_shift` (normalized u, v) so the bias grows with the distance from the *true* centre, and a
mild nonlinearity in magnitude. The gauge reads the true force with relative and absolute noise.

Clearly synthetic: the digital twin (tools/twin) replaces this for the acceptance numbers.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ...runtime.stages.geometry import DomeProfile, equidistant_theta_phi, surface_tables
from .fit import PokeSet
from .pokes import PokeRules, candidate_pixels, suggest_next

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SyntheticUnit:
    stiffness_ratio: float = 1.2            # gel 20 % stiffer than the model was trained on
    center_shift: tuple = (0.06, -0.04)     # true gel centre offset, normalized model-grid units
    radial_bias: float = 0.25               # extra gain per (distance from true centre / 0.5)²
    magnitude_exp: float = 0.05             # gain ∝ (F / 2 N)^exp: mild nonlinearity
    gauge_rel_noise: float = 0.02
    gauge_abs_noise_n: float = 0.01
    jitter_px: float = 1.0                  # how far the user misses the suggested spot
    size: int = 32
    theta_edge: float = float(np.deg2rad(100.0))
    force_range_n: tuple = (0.8, 4.0)

    def tables(self) -> dict:
        theta, phi = equidistant_theta_phi((self.size, self.size), self.theta_edge)
        return surface_tables(theta, phi, DomeProfile(radius_mm=16.0))

    def true_gain(self, uv: np.ndarray, f_true: np.ndarray) -> np.ndarray:
        """|F_true| / |F_model| at normalized positions uv (N,2) and true forces (N,)."""
        c = 0.5 + np.asarray(self.center_shift)
        r2 = ((np.asarray(uv) - c) ** 2).sum(axis=1) / 0.25
        return self.stiffness_ratio * (1 + self.radial_bias * r2) * (np.asarray(f_true) / 2.0) ** self.magnitude_exp

    def observe(self, rng: np.random.Generator, uv_px: np.ndarray, f_true: np.ndarray, tables: dict) -> PokeSet:
        """Model predictions and gauge readings for contacts at model-grid positions uv_px (N,2)."""
        uv_px = np.asarray(uv_px, float).reshape(-1, 2)
        uv = uv_px / self.size
        rc = np.clip(uv_px[:, ::-1].astype(int), 0, self.size - 1)
        normals = tables["normals"][rc[:, 0], rc[:, 1]]
        pred_mag = f_true / self.true_gain(uv, f_true)
        pred = -normals * pred_mag[:, None]            # pushing into the gel
        gauge = f_true * (1 + self.gauge_rel_noise * rng.standard_normal(len(f_true))) \
            + self.gauge_abs_noise_n * rng.standard_normal(len(f_true))
        tp = np.stack([tables["theta"][rc[:, 0], rc[:, 1]], tables["phi"][rc[:, 0], rc[:, 1]]], axis=1)
        return PokeSet(pred, np.abs(gauge), uv, tp)

    def guided_pokes(self, rng: np.random.Generator, n: int, rules: PokeRules = PokeRules()) -> PokeSet:
        """n pokes at the session's suggested spots (farthest-point), missed by ~jitter_px."""
        t = self.tables()
        acc, uvs = [], []
        for _ in range(n):
            uv_px, xyz = suggest_next(t["mask"], t["theta"], t["surface_xyz"], acc, rules)
            missed = np.clip(uv_px + self.jitter_px * rng.standard_normal(2), 0.5, self.size - 0.5)
            if t["mask"][int(missed[1]), int(missed[0])]:
                uv_px = missed
            acc.append(xyz)
            uvs.append(uv_px)
        f = rng.uniform(*self.force_range_n, n)
        return self.observe(rng, np.array(uvs), f, t)

    def held_out(self, rng: np.random.Generator, n: int = 300, rules: PokeRules = PokeRules()) -> PokeSet:
        """n random contacts over the reachable gel (a dense held-out test set)."""
        t = self.tables()
        cand = candidate_pixels(t["mask"], t["theta"], rules)
        pick = cand[rng.integers(0, len(cand), n)]
        uv_px = pick[:, ::-1] + rng.uniform(0, 1, (n, 2))
        f = rng.uniform(0.5, 5.0, n)
        return self.observe(rng, uv_px, f, t)


def random_units(rng: np.random.Generator, n: int) -> list[SyntheticUnit]:
    """Units with manufacturing variation: stiffness 0.8–1.3, centre shift up to 0.08, radial bias 0–0.4."""
    out = []
    for _ in range(n):
        s = float(rng.uniform(0.8, 1.3))
        shift = tuple(float(v) for v in rng.uniform(-0.08, 0.08, 2))
        out.append(SyntheticUnit(stiffness_ratio=s, center_shift=shift, radial_bias=float(rng.uniform(0, 0.4)),
                                 magnitude_exp=float(rng.uniform(-0.05, 0.08))))
    return out
