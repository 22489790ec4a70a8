"""Physics backends of the twin: what the gel does for a poke's keypoints.

The contract (`Physics` protocol) is deliberately the FE result's shape (docs/fe.md) restricted to
what the twin needs, on a fixed set of rest surface nodes:

    solve(poke) -> PokeSolve   nodes (N,3) mm; per keypoint frame j: U (J,N,3) mm surface
                               displacement, RF (J,K,3) N force each indenter applies to the gel
                               (pressing down: RF_z < 0), RM (J,K,3) N*mm moment about the tip,
                               CAREA (J,K) mm^2, contact point (J,K,3), depth (J,K) mm.

Backends: `tools.twin.fe_physics.FEPhysics` (the default for recorded sessions: per-poke FE solves
of tools.fe, cached) and `HertzFallbackPhysics` below -- an analytic Hertz/Mindlin/Lubkin
half-space approximation used ONLY for fast tests and as an explicit fallback
(`--physics hertz-fallback`); it is not the twin's physics.

Between keypoints frames are interpolated linearly in the motion phase s (trajectory.py), see
`interpolate`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from .geometry import GelSurface
from .trajectory import INDENTER_SET, Poke, segment_phase

log = logging.getLogger(__name__)


@dataclass
class PokeSolve:
    nodes: np.ndarray       # (N,3) rest surface nodes
    U: np.ndarray           # (J,N,3)
    RF: np.ndarray          # (J,K,3)
    RM: np.ndarray          # (J,K,3)
    CAREA: np.ndarray       # (J,K)
    contact: np.ndarray     # (J,K,3) contact centroid (rest surface), nan when not touching
    depth: np.ndarray       # (J,K) mm indentation (0 when not touching)
    backend: str = ""
    key: str = ""


class Physics(Protocol):
    name: str

    def solve(self, poke: Poke) -> PokeSolve: ...


def keypoint_poses(poke: Poke) -> tuple[np.ndarray, np.ndarray]:
    """Tip positions (J,K,3) and rotation vectors (J,K,3) at the poke's keypoints."""
    K, J = poke.translation.shape[:2]
    pos = np.transpose(poke.position[:, None, :] + poke.translation, (1, 0, 2))
    rot = np.empty((J, K, 3))
    for k in range(K):
        R0 = Rotation.from_rotvec(poke.rotation[k])
        rot[:, k] = (Rotation.from_rotvec(poke.rotvec[k]) * R0).as_rotvec()
    return pos, rot


def motion_runs(poke: Poke, tol: float = 1e-6) -> list[tuple[int, int]]:
    """Keypoint index ranges [a, b] over which every indenter moves along one straight line at a
    constant step (e.g. the press steps), so the response is smooth in the keypoint parameter."""
    K, J = poke.translation.shape[:2]
    steps = np.concatenate([np.diff(poke.translation, axis=1), np.diff(poke.rotvec, axis=1)], axis=2)
    steps = np.transpose(steps, (1, 0, 2)).reshape(J - 1, -1)
    runs, a = [], 0
    for j in range(1, J - 1):
        if np.linalg.norm(steps[j] - steps[j - 1]) > tol * max(1.0, np.linalg.norm(steps[j - 1])):
            runs.append((a, j))
            a = j
    runs.append((a, J - 1))
    return runs


def interpolate(solve: PokeSolve, poke: Poke, t: np.ndarray, what: str, method: str = "pchip") -> np.ndarray:
    """Array `what` of the solve at session times t inside the poke's keypoint span.

    The keypoint parameter σ = j + s (segment j, min-jerk motion phase s) moves the indenters
    piecewise linearly; within each straight run of equal steps (motion_runs) the response is
    interpolated in σ by a monotone cubic (PCHIP), which follows the curvature of e.g. the
    force-depth curve; runs of one segment and method="linear" interpolate linearly in s.
    """
    arr = getattr(solve, what)
    j, s = segment_phase(poke.times, np.atleast_1d(t))
    if method == "linear":
        s = s.reshape((-1,) + (1,) * (arr.ndim - 1))
        return arr[j] + s * (arr[j + 1] - arr[j])
    from scipy.interpolate import PchipInterpolator

    sigma = j + s
    out = np.empty((len(sigma),) + arr.shape[1:])
    cache = solve.__dict__.setdefault("_interp", {})
    for a, b in motion_runs(poke):
        sel = (j >= a) & (j < b)
        if not sel.any():
            continue
        if b - a < 2:
            ss = (sigma[sel] - a).reshape((-1,) + (1,) * (arr.ndim - 1))
            out[sel] = arr[a] + ss * (arr[b] - arr[a])
            continue
        key = (what, a, b)
        if key not in cache:
            cache[key] = PchipInterpolator(np.arange(a, b + 1), arr[a:b + 1], axis=0)
        out[sel] = cache[key](sigma[sel])
    return out


def _equivalent_radius(name: str) -> float:
    spec = INDENTER_SET[name]
    p = spec["params"]
    return {"sphere": lambda: p["radius"], "flat": lambda: 3.0 * p["radius"],
            "cylinder": lambda: 1.5 * p["radius"], "box_edge": lambda: 0.5 * p["width"],
            "torus": lambda: 2.0 * p["minor_radius"]}.get(spec["shape"], lambda: 5.0)()


@dataclass
class HertzFallbackPhysics:
    """Analytic fallback (tests, quick previews): Hertz normal contact of the indenter's
    equivalent sphere with the cap sphere, Mindlin stick/slip tangential load, Lubkin torsion,
    half-space surface displacement fields, tapered to zero at the fixed rim. Not FE."""

    gel: GelSurface
    shear_modulus: float = 0.06      # MPa, the FE standard gel's mu0
    friction: float = 2.2
    node_spacing: float = 0.5
    name: str = "hertz-fallback"

    def __post_init__(self):
        self.nodes = self.gel.samples(self.node_spacing)
        self.node_normals = self.gel.normals(self.nodes)
        self.taper = np.clip(self.gel.rim_distance(self.nodes) / 3.0, 0.0, 1.0)

    def solve(self, poke: Poke) -> PokeSolve:
        pos, rot = keypoint_poses(poke)
        J, K = pos.shape[:2]
        N = len(self.nodes)
        U = np.zeros((J, N, 3))
        RF, RM = np.zeros((J, K, 3)), np.zeros((J, K, 3))
        area, depth = np.zeros((J, K)), np.zeros((J, K))
        contact = np.full((J, K, 3), np.nan)
        G = self.shear_modulus
        Es = 4.0 * G  # E/(1-nu^2), nu = 0.5
        zc, rho = np.array([0.0, 0.0, self.gel.profile.center_z_mm]), self.gel.profile.radius_mm
        for k in range(K):
            R = _equivalent_radius(poke.indenters[k])
            Rs = 1.0 / (1.0 / R + 1.0 / rho)
            anchor, anchor_rot = None, None
            for j in range(J):
                Rj = Rotation.from_rotvec(rot[j, k])
                centre = pos[j, k] + Rj.apply([0.0, 0.0, R])
                dc = centre - zc
                dist = np.linalg.norm(dc)
                n = dc / dist
                d = (rho + R) - dist
                if d <= 0:
                    anchor = None
                    continue
                xc = zc + rho * n
                a = np.sqrt(Rs * d)
                Fn = 4.0 / 3.0 * Es * np.sqrt(Rs) * d ** 1.5
                if anchor is None:
                    anchor, anchor_rot = pos[j, k].copy(), Rj
                mv = pos[j, k] - anchor
                s = mv - (mv @ n) * n
                kt = 16.0 / 3.0 * G * a
                Q = kt * s
                if np.linalg.norm(Q) > self.friction * Fn:  # gross slip: the stick point follows
                    Q = Q / np.linalg.norm(Q) * self.friction * Fn
                    s = Q / kt
                    anchor = pos[j, k] - s
                beta = float((Rj * anchor_rot.inv()).as_rotvec() @ n)
                T = 16.0 / 3.0 * G * a ** 3 * beta
                Tmax = 3 * np.pi / 16 * self.friction * Fn * a
                if abs(T) > Tmax:
                    T = np.sign(T) * Tmax
                    beta = T / (16.0 / 3.0 * G * a ** 3)
                rf = -Fn * n + Q
                RF[j, k], area[j, k], depth[j, k], contact[j, k] = rf, np.pi * a * a, d, xc
                RM[j, k] = np.cross(xc - pos[j, k], rf) + T * n
                U[j] += self._field(xc, n, a, d, Rs, s, beta)
        return PokeSolve(self.nodes, U, RF, RM, area, contact, depth, self.name)

    def _field(self, xc, n, a, d, Rs, s, beta) -> np.ndarray:
        rel = self.nodes - xc
        r = np.linalg.norm(rel - np.outer(rel @ n, n), axis=1)
        inside = r <= a
        ra = np.maximum(r, a) / a
        w_in = d - r * r / (2 * Rs)
        w_out = d / np.pi * ((2 - ra ** 2) * np.arcsin(1 / ra) + np.sqrt(np.maximum(ra ** 2 - 1, 0)))
        w = np.where(inside, w_in, w_out)
        g = np.where(inside, 1.0, 2 / np.pi * np.arcsin(1 / ra))
        u = -w[:, None] * n + g[:, None] * s
        if beta:
            tw = np.where(inside, 1.0, 1.0 / ra ** 3)
            u += beta * tw[:, None] * np.cross(n, rel)
        return u * self.taper[:, None]
