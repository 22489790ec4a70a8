"""Gel surface geometry for the twin: rest surface of the FE gel (dome / flattened dome), ray
intersection from the camera below the base, outward normals, θ/φ, rim distance, surface samples.

Sensor frame = FE gel frame (docs/fe.md, docs/fields.md): origin at the centre of the gel base,
+z along the dome axis. θ = atan2(sqrt(x²+y²), z) is the angle of a surface point from the
dome axis seen from the centre of the cap sphere `profile` (runtime.stages.geometry.DomeProfile,
the same θ as the runtime's surface tables) -- continued onto the skirt; φ = atan2(y, x).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ...contracts.errors import TensorTouchError
from ...runtime.stages.geometry import DomeProfile

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GelSurface:
    """Spherical cap of base radius `radius` and height `cap_height` on a vertical skirt of
    height `skirt` (mm). A hemispherical dome is the case cap_height == radius."""

    radius: float = 12.0
    cap_height: float = 6.0
    skirt: float = 2.0

    @classmethod
    def from_fe(cls, gel) -> "GelSurface":
        """From a tools.fe GelGeometry (kinds dome and flattened_dome)."""
        if gel.kind == "dome":
            return cls(gel.radius, gel.radius, gel.skirt)
        if gel.kind == "flattened_dome":
            return cls(gel.radius, gel.cap_height, gel.skirt)
        raise TensorTouchError(f"gel.kind {gel.kind!r}: the twin camera renders dome and "
                               "flattened_dome gels only")

    @property
    def profile(self) -> DomeProfile:
        """The cap's sphere (the θ of runtime's surface tables is measured about its centre)."""
        return DomeProfile.of_cap(self.radius, self.cap_height, self.skirt)

    @property
    def top_z(self) -> float:
        return self.skirt + self.cap_height

    @property
    def rim_beta(self) -> float:
        """Cap polar angle (about the cap sphere centre) of the cap edge, rad."""
        return self.profile.edge_theta(self.radius)

    def intersect(self, origin, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays origin + t*dirs (origin inside the gel's base circle, below the cap sphere's top) -> first
        hit on the inner side of the outer surface (N..,3) and a validity mask."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        zc, rho = self.profile.center_z_mm, self.profile.radius_mm
        oc = o - np.array([0.0, 0.0, zc])
        b = np.sum(d * oc, axis=-1)
        c = float(oc @ oc) - rho * rho
        disc = b * b - c
        t_cap = -b + np.sqrt(np.clip(disc, 0.0, None))
        p_cap = o + t_cap[..., None] * d
        ok_cap = (disc >= 0) & (t_cap > 0) & (p_cap[..., 2] >= self.skirt - 1e-9)
        rxy = np.hypot(d[..., 0], d[..., 1])
        if o[0] == 0.0 and o[1] == 0.0:
            t_sk = np.where(rxy > 1e-12, self.radius / np.maximum(rxy, 1e-12), np.inf)
        else:       # origin off the axis (a unit whose camera sits beside the gel axis): ray vs. cylinder
            bb = d[..., 0] * o[0] + d[..., 1] * o[1]
            cc = o[0] ** 2 + o[1] ** 2 - self.radius ** 2
            a2 = np.maximum(rxy * rxy, 1e-24)
            t_sk = np.where(rxy > 1e-12, (-bb + np.sqrt(np.clip(bb * bb - a2 * cc, 0.0, None))) / a2, np.inf)
        p_sk = o + np.where(np.isfinite(t_sk), t_sk, 0.0)[..., None] * d
        ok_sk = np.isfinite(t_sk) & (p_sk[..., 2] >= 0.0) & (p_sk[..., 2] < self.skirt)
        pts = np.where(ok_cap[..., None], p_cap, p_sk)
        return pts, ok_cap | (~ok_cap & ok_sk)

    def normals(self, pts: np.ndarray) -> np.ndarray:
        """Outward unit normals at rest surface points."""
        pts = np.asarray(pts, dtype=np.float64)
        on_cap = pts[..., 2] >= self.skirt - 1e-9
        n_cap = pts - np.array([0.0, 0.0, self.profile.center_z_mm])
        n_sk = pts * np.array([1.0, 1.0, 0.0])
        n = np.where(on_cap[..., None], n_cap, n_sk)
        return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)

    def rim_distance(self, pts: np.ndarray) -> np.ndarray:
        """Arc length (mm) along the meridian from a surface point down to the base rim (z = 0)."""
        pts = np.asarray(pts, dtype=np.float64)
        r = np.hypot(pts[..., 0], pts[..., 1])
        beta = np.arctan2(r, pts[..., 2] - self.profile.center_z_mm)
        on_cap = pts[..., 2] >= self.skirt
        cap = self.profile.radius_mm * np.clip(self.rim_beta - beta, 0.0, None) + self.skirt
        return np.where(on_cap, cap, np.clip(pts[..., 2], 0.0, None))

    def point_at(self, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Surface point at angle θ from the axis (about the cap sphere centre) and azimuth φ."""
        theta, phi = np.broadcast_arrays(np.asarray(theta, float), np.asarray(phi, float))
        d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
        pts, ok = self.intersect(np.array([0.0, 0.0, self.profile.center_z_mm]), d)
        if not np.all(ok):
            raise TensorTouchError(f"GelSurface.point_at: θ outside the gel (expected 0..{self.theta_max:.3f} rad)")
        return pts

    @property
    def theta_max(self) -> float:
        """θ of the base rim (z = 0)."""
        return float(np.arctan2(self.radius, -self.profile.center_z_mm))

    def theta_phi(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """θ (from the axis, about the cap sphere centre) and φ = atan2(y, x), radians."""
        pts = np.asarray(pts, dtype=np.float64)
        return (np.arctan2(np.hypot(pts[..., 0], pts[..., 1]), pts[..., 2] - self.profile.center_z_mm),
                np.arctan2(pts[..., 1], pts[..., 0]))

    def unrolled(self, pts: np.ndarray) -> np.ndarray:
        """Flat map of the surface (azimuthal equidistant about the apex): (s cosφ, s sinφ) with s
        the meridian arc length from the apex (mm). Bijective on the gel surface."""
        pts = np.asarray(pts, dtype=np.float64)
        theta, phi = self.theta_phi(pts)
        s = self.profile.radius_mm * np.minimum(theta, self.rim_beta) + np.clip(self.skirt - pts[..., 2], 0.0, None)
        return np.stack([s * np.cos(phi), s * np.sin(phi)], axis=-1)

    def interpolator(self, nodes: np.ndarray, targets: np.ndarray):
        """Sparse matrix W (len(targets), len(nodes)): values at rest surface `nodes` -> linear
        (barycentric) interpolation at rest surface `targets`, on a Delaunay triangulation of the
        unrolled surface; targets outside the node hull take their nearest node."""
        import scipy.sparse as sp
        from scipy.spatial import Delaunay, cKDTree

        a, b = self.unrolled(nodes), self.unrolled(targets)
        tri = Delaunay(a)
        simplex = tri.find_simplex(b)
        inside = simplex >= 0
        T = tri.transform[simplex[inside]]
        bary2 = np.einsum("nij,nj->ni", T[:, :2], b[inside] - T[:, 2])
        bary = np.concatenate([bary2, 1.0 - bary2.sum(1, keepdims=True)], axis=1)
        rows = np.repeat(np.flatnonzero(inside), 3)
        cols = tri.simplices[simplex[inside]].ravel()
        vals = bary.ravel()
        _, near = cKDTree(a).query(b[~inside])
        rows = np.concatenate([rows, np.flatnonzero(~inside)])
        cols = np.concatenate([cols, near])
        vals = np.concatenate([vals, np.ones(len(near))])
        return sp.csr_matrix((vals, (rows, cols)), shape=(len(targets), len(nodes)))

    def samples(self, spacing: float = 0.5) -> np.ndarray:
        """Quasi-uniform rest surface points (N,3) with about `spacing` mm between neighbours."""
        rho, zc = self.profile.radius_mm, self.profile.center_z_mm
        area_cap = 2.0 * np.pi * rho * self.cap_height
        n_cap = max(16, int(area_cap / spacing ** 2))
        i = np.arange(n_cap) + 0.5
        cosb = 1.0 - i / n_cap * (1.0 - np.cos(self.rim_beta))  # uniform in area on the cap
        sinb = np.sqrt(1.0 - cosb ** 2)
        ang = np.pi * (3.0 - np.sqrt(5.0)) * i
        cap = np.stack([rho * sinb * np.cos(ang), rho * sinb * np.sin(ang), zc + rho * cosb], -1)
        pts = [cap]
        n_ring = max(8, int(2 * np.pi * self.radius / spacing))
        for z in np.arange(spacing / 2, self.skirt, spacing):
            a = np.linspace(0, 2 * np.pi, n_ring, endpoint=False) + z
            pts.append(np.stack([self.radius * np.cos(a), self.radius * np.sin(a), np.full(n_ring, z)], -1))
        return np.concatenate(pts)

