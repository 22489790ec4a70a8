"""Geometry: per-pixel gel-surface tables (θ, φ → 3D point, normal, area) and lookups.

Pure numpy. The calibration stage (GPR on pokes, or a twin unit's truth) produces θ/φ per model
pixel; `surface_tables` turns them into 3D points, outward normals and per-pixel areas for an
axisymmetric gel profile; the runtime then only looks values up.

Sensor frame (docs/fields.md): origin at the centre of the gel base, +z along the dome axis; image
column ≈ +x, image row ≈ +y; φ = atan2(y, x); θ = angle from the +z axis.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DomeProfile:
    """Axisymmetric gel surface: a spherical cap of radius `radius_mm` whose sphere centre sits
    `center_z_mm` above the base plane (0 = hemisphere; < 0 = flattened dome)."""

    radius_mm: float = 16.0
    center_z_mm: float = 0.0

    @classmethod
    def of_cap(cls, base_radius_mm: float, cap_height_mm: float, skirt_mm: float = 0.0) -> "DomeProfile":
        """The sphere of a spherical cap of base radius a and height h standing on a vertical skirt:
        radius (a² + h²) / 2h, centre skirt + h − radius above the base plane (mm)."""
        a, h = base_radius_mm, cap_height_mm
        radius = (a * a + h * h) / (2.0 * h)
        return cls(radius_mm=radius, center_z_mm=skirt_mm + h - radius)

    def edge_theta(self, base_radius_mm: float) -> float:
        """θ of the cap's edge, where the sphere meets the circle of radius `base_radius_mm`, rad."""
        return float(np.arcsin(min(1.0, base_radius_mm / self.radius_mm)))

    def point(self, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
        r = self.radius_mm * np.sin(theta)
        z = self.center_z_mm + self.radius_mm * np.cos(theta)
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)

    def theta_max(self) -> float:
        """θ at which the cap meets the base plane (z = 0)."""
        c = np.clip(-self.center_z_mm / self.radius_mm, -1.0, 1.0)
        return float(np.arccos(c))


def equidistant_theta_phi(size: tuple[int, int], theta_edge: float) -> tuple[np.ndarray, np.ndarray]:
    """Nominal θ/φ of an ideal equidistant fisheye whose crop circle edge sees θ = theta_edge.

    Model pixel centres; distance from the grid centre normalized to 1 at the crop radius.
    """
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    dx = (xx + 0.5 - w / 2) / (w / 2)
    dy = (yy + 0.5 - h / 2) / (h / 2)
    d = np.hypot(dx, dy)
    return (d * theta_edge).astype(np.float32), np.arctan2(dy, dx).astype(np.float32)


def surface_tables(theta: np.ndarray, phi: np.ndarray, profile: DomeProfile,
                   theta_limit: float | None = None) -> dict[str, np.ndarray]:
    """θ/φ tables → surface_xyz (mm), outward normals, pixel_area (mm²), mask (on the gel)."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    limit = profile.theta_max() if theta_limit is None else theta_limit
    mask = np.isfinite(theta) & (theta <= limit)
    th = np.where(mask, theta, 0.0)
    xyz = profile.point(th, phi)
    # area = |dp/dθ × dp/dφ| · |det ∂(θ,φ)/∂(u,v)|: surface Jacobian from the profile (analytic
    # up to a central difference), image Jacobian from the tables (φ differentiated on the unit circle)
    eps = 1e-4
    tf = np.nan_to_num(theta, nan=0.0)
    dp_dt = (profile.point(tf + eps, phi) - profile.point(tf - eps, phi)) / (2 * eps)
    dp_dp = (profile.point(tf, phi + eps) - profile.point(tf, phi - eps)) / (2 * eps)
    surf = np.linalg.norm(np.cross(dp_dt, dp_dp), axis=-1)
    e = np.exp(1j * phi)
    dphi_v, dphi_u = (np.imag(np.conj(e) * g) for g in np.gradient(e))
    dth_v, dth_u = np.gradient(tf)
    det = np.abs(dth_u * dphi_v - dth_v * dphi_u)
    area = np.where(mask, surf * det, 0.0)
    centre = np.array([0.0, 0.0, profile.center_z_mm])
    normals = xyz - centre  # a spherical cap's outward normal is radial from the sphere centre
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    return {
        "theta": theta.astype(np.float32),
        "phi": phi.astype(np.float32),
        "surface_xyz": np.where(mask[..., None], xyz, 0.0).astype(np.float32),
        "normals": np.where(mask[..., None], normals, 0.0).astype(np.float32),
        "pixel_area": area.astype(np.float32),
        "mask": mask,
    }


def sample_bilinear(table: np.ndarray, u: float, v: float) -> np.ndarray:
    """Value of a (H, W[, C]) table at continuous pixel coordinates (u = column, v = row)."""
    h, w = table.shape[:2]
    u = float(np.clip(u, 0, w - 1))
    v = float(np.clip(v, 0, h - 1))
    u0, v0 = int(np.floor(u)), int(np.floor(v))
    u1, v1 = min(u0 + 1, w - 1), min(v0 + 1, h - 1)
    a, b = u - u0, v - v0
    return ((1 - a) * (1 - b) * table[v0, u0] + a * (1 - b) * table[v0, u1]
            + (1 - a) * b * table[v1, u0] + a * b * table[v1, u1])


SURFACE_GRID_MAX_SIDE = 32      # the `gel_surface` a sensor's info carries has at most this many points per side


def surface_grid(cal, max_side: int = SURFACE_GRID_MAX_SIDE) -> dict:
    """The calibrated gel surface (mm) block-averaged to <= max_side per side, for viewers."""
    h, w = cal.model_size
    step = max(1, -(-max(h, w) // max_side))
    gh, gw = h // step, w // step
    xyz = cal.surface_xyz[:gh * step, :gw * step].reshape(gh, step, gw, step, 3).mean(axis=(1, 3))
    mask = cal.mask[:gh * step, :gw * step].reshape(gh, step, gw, step).mean(axis=(1, 3)) > 0.5
    return {"grid": [gh, gw], "step": step, "xyz_mm": [round(float(v), 3) for v in xyz.ravel()],
            "mask": [bool(v) for v in mask.ravel()], "calibration_version": cal.version}
