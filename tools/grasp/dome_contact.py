"""Fast physics of long objects (cables, pens) pressed into the sensor's gel dome.

What reaches the twin renderer is the gel surface displacement u (mm) at each rest surface point.
An object is a cylinder (radius a, axis direction e, axis point c in the sensor frame, mm) pressed
to depth d along the dome normal at its closest point, and displaced tangentially by s (mm, the
stick displacement since it first touched). The field is a line-contact profile along the object
(half-space approximation of a soft gel, the same family as the twin's Hertz fallback):

    t = position of a surface point along the object's axis, d(t) = a + R_dome − |A(t) − C| the
    local overlap of the object's cross-section at t with the dome sphere (centre C): the straight
    object leaves the curved dome, so the contact is a finite patch,
    r = distance of the surface point from the object's axis,
    b = √(2 R* d(t)) contact half-width, R* = 1/(1/a + 1/R_dome),
    w = d(t) − r²/(2R*) inside r ≤ b, d(t)·(b/r)^k outside (k = decay, ~1 for a line load),
    u = −w n + g(r) s, g = 1 inside, (b/r) outside,

tapered to zero towards the fixed rim and along the object beyond the gel. Two objects superpose
(the deeper profile wins per point, shear adds). This is an approximation for control studies,
not FE.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..twin.geometry import GelSurface


@dataclass(frozen=True)
class ObjectContact:
    """One object against the dome, sensor frame (mm)."""

    point: np.ndarray       # (3,) contact point on the rest dome surface
    axis: np.ndarray        # (3,) unit direction of the object's long axis
    radius: float           # object radius (mm)
    depth: float            # indentation along the dome normal (mm), ≥ 0
    shear: np.ndarray       # (3,) tangential stick displacement (mm)
    index: int = -1         # which object of the scene it is (logs only; the render ignores it)


@dataclass(frozen=True)
class DomeContactConfig:
    max_depth_mm: float = 2.5
    decay: float = 1.5
    rim_taper_mm: float = 3.0


def displacement(gel: GelSurface, points: np.ndarray, normals: np.ndarray, objects: list[ObjectContact],
                 cfg: DomeContactConfig | None = None) -> np.ndarray:
    """Surface displacement (N,3) mm at rest surface points (N,3) with outward normals (N,3)."""
    cfg = cfg or DomeContactConfig()
    P = np.asarray(points, float)
    u = np.zeros_like(P)
    w_best = np.zeros(len(P))
    R = gel.profile.radius_mm
    taper = np.clip(gel.rim_distance(P) / cfg.rim_taper_mm, 0.0, 1.0)
    for ob in objects:
        d = float(np.clip(ob.depth, 0.0, cfg.max_depth_mm))
        if d <= 0:
            continue
        a = float(ob.radius)
        Rs = 1.0 / (1.0 / a + 1.0 / R)
        centre = np.array([0.0, 0.0, gel.profile.center_z_mm])
        n0 = np.asarray(ob.point, float) - centre
        n0 /= np.linalg.norm(n0)
        e = np.asarray(ob.axis, float) - (np.asarray(ob.axis, float) @ n0) * n0   # tangent to the dome
        e /= np.linalg.norm(e)
        c_axis = centre + (R + a - d) * n0
        rel = P - c_axis
        t = rel @ e
        dt = np.clip(a + R - np.linalg.norm(c_axis[None] + t[:, None] * e[None] - centre, axis=1), 0.0, None)
        r = np.maximum(np.linalg.norm(rel - np.outer(t, e), axis=1) - (a - dt), 0.0)  # from the contact line
        b = np.sqrt(2.0 * Rs * np.maximum(dt, 1e-9))
        rb = np.maximum(r, b) / b
        w = np.where(r <= b, np.maximum(dt - r * r / (2 * Rs), 0.0), dt * rb ** (-cfg.decay))
        w = np.where(dt > 0, w, 0.0)
        g = np.where(dt > 0, np.where(r <= b, 1.0, 1.0 / rb), 0.0)
        u += (g * taper)[:, None] * np.asarray(ob.shear, float)[None, :]
        w_best = np.maximum(w_best, w)
    return u - (w_best * taper)[:, None] * normals
