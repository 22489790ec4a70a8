"""Fast physics of long objects (cables, pens) pressed into the sensor's gel dome.

What reaches the twin renderer is the gel surface displacement u (mm) at each rest surface point.
An object is a cylinder (radius a, axis direction e, axis point c in the sensor frame, mm) pressed
to depth d along the dome normal at its closest point, and displaced tangentially by s (mm, the
stick displacement since it first touched). The field is a line-contact profile along the object
(half-space approximation of a soft gel, the same family as the twin's Hertz fallback):

    t = position of a surface point along the object's axis, d(t) = a + R_dome − |A(t) − C| the
    local overlap of the object's cross-section at t with the dome sphere (centre C): the straight
    object leaves the curved dome, so the contact is a finite patch,
    r = arc distance on the dome from the great circle through the object's contact line,
    R* = 1/(1/a + 1/R_dome); the overlap half-width √(2 R* d(t)), and the contact half-width
    b = √(R* d(t)), 1/√2 of it (the gel beside the object sinks too, as in Hertz contact),
    w = d(t) − r²/(2R*) inside r ≤ b (the object's shape; d/2 at the edge),
        (d(t)/2)·exp(−(r − b)/λ) outside (λ = `tail_mm`),
    u = −w n + g(r) s, g = 1 inside, exp(−(r − b)/λ) outside,

tapered to zero towards the fixed rim and along the object beyond the gel. Two objects superpose
(the deeper profile wins per point, shear adds). λ = 1.6 mm is fitted to FE of the twin's standard
dome (tools.fe: cylinders of radius 4 and 1.09 mm pressed 0.6 and 1.2 mm across its apex; RMS error
of w 0.008–0.035 mm over the 8 mm beside the object, against 0.10–0.51 mm for the power law used
before; docs/decisions/2026-11-26-grasp-gel-profile-fitted-to-fe.md, checked by a slow test in
tests/test_grasp_dome_contact.py). On the flank (25°, 40° from the apex) and to 2 mm deep the same λ stays
within 0.08 mm RMS of FE; the shear tail uses the same λ, within 0.065 mm RMS of a 0.5 mm slide, though FE's
shear tail widens with depth (docs/decisions/2026-12-07-grasp-gel-profile-flank-depth-shear.md, slow tests
beside the first). This is an approximation for control studies, not FE.
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
    tail_mm: float = 1.6            # λ: how fast the gel beside the contact rises back (fitted to FE, above)
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
        m = np.cross(n0, e)                                         # across the object, tangent at its contact
        r = R * np.arcsin(np.clip(np.abs((P - centre) @ m) / R, 0.0, 1.0))   # along the dome from the contact line
        b = np.sqrt(Rs * dt)                                        # contact half-width
        tail = np.exp(-np.maximum(r - b, 0.0) / cfg.tail_mm)
        w = np.where(r <= b, dt - r * r / (2 * Rs), 0.5 * dt * tail)
        w = np.where(dt > 0, w, 0.0)
        g = np.where(dt > 0, tail, 0.0)
        u += (g * taper)[:, None] * np.asarray(ob.shear, float)[None, :]
        w_best = np.maximum(w_best, w)
    return u - (w_best * taper)[:, None] * normals
