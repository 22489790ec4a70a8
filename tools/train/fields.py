"""Stage 5 core — FE surface data → 15-channel field images on the θ/φ grid (seed §III.H).

Channel contract: docs/fields.md (contracts.fields.CHANNELS). Contact channels are tractions (MPa):
per-node contact force (N) divided by the node's tributary area (mm²); the runtime multiplies by the
per-pixel gel area to get N per pixel, so Σ traction·pixel_area over the image ≈ total contact force.

Pure cores:
- `surface_angles`      θ (from +z) and φ = atan2(y, x) of points about the dome centre;
- `tributary_area`      per-node area (mm²) from surface triangles (or a Delaunay of the θ/φ disc);
- `transfer_nearest`    k-d tree (cKDTree) node → surface-vertex transfer;
- `interpolate_to_grid` linear interpolation on (θ, φ) with φ wrap-around padding (and the apex
                        replicated along φ, where φ is undefined);
- `smooth_fields`       Gaussian σ = 2 px inside the gel mask (normalized convolution: no rim leak);
- `fe_to_fields`        all of the above → (15, H, W) float32 in physical units;
- `compute_bounds`, `normalize_global`, `denormalize`, `normalize_per_image`, bounds JSON I/O;
- `attribute_contacts`  k-means (scipy.cluster.vq.kmeans2) of contact nodes, clusters assigned
                        one-to-one to the nearest indenters.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.cluster.vq import kmeans2
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
from scipy.optimize import linear_sum_assignment
from scipy.spatial import Delaunay, cKDTree

from ...contracts.errors import TensorTouchError
from ...contracts.fields import CHANNELS, N_CHANNELS
from ...contracts.files import atomic_write_json

log = logging.getLogger(__name__)


class FieldDataError(TensorTouchError):
    """Field images or their bounds file do not match the channel contract (docs/fields.md)."""


@dataclass(frozen=True)
class FieldConfig:
    """Seed §III.H numbers as named defaults."""

    gaussian_sigma_px: float = 2.0        # σ of the Gaussian smoothing, in model pixels
    phi_pad_rad: float = 0.6              # points within this of ±π are replicated across the seam
    apex_theta_rad: float = 0.02          # nodes closer than this to the dome axis are replicated along φ
    apex_copies: int = 24                 # number of φ copies of an apex node
    center_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)   # origin of θ/φ (dome sphere centre)
    bounds_margin: float = 0.0            # relative widening of global bounds (0 = exact min/max)
    min_bound_span: float = 1e-9          # lo == hi is widened to this span
    # Force-conserving contact tractions: a node's contact force is divided by the area its linear
    # interpolation kernel covers on the pixel grid (Σ_pixels weight·pixel_area) instead of its mesh
    # tributary area, so Σ traction·pixel_area over the image equals Σ node force exactly before the
    # smoothing (the mesh-area quotient scattered the image total by ~2.5 % rms around the FE force).
    conserve_force: bool = True
    conserve_min_ratio: float = 0.25      # a node seeing less than this fraction of its mesh area (the
                                          # mask rim) keeps the mesh area (no traction spikes)


def surface_angles(xyz: np.ndarray, cfg: FieldConfig = FieldConfig()) -> tuple[np.ndarray, np.ndarray]:
    """θ = angle from +z (rad), φ = atan2(y, x) ∈ (−π, π] of points (N, 3) mm about cfg.center_mm."""
    d = np.asarray(xyz, dtype=float) - np.asarray(cfg.center_mm, dtype=float)
    return np.arctan2(np.hypot(d[:, 0], d[:, 1]), d[:, 2]), np.arctan2(d[:, 1], d[:, 0])


def _disc(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    return np.stack([theta * np.cos(phi), theta * np.sin(phi)], 1)


def tributary_area(xyz: np.ndarray, triangles: np.ndarray | None = None,
                   cfg: FieldConfig = FieldConfig()) -> np.ndarray:
    """Per-node area (N,) mm²: one third of each adjacent surface triangle's area.

    Without `triangles`, the surface is triangulated by a Delaunay of the nodes' (θ cos φ, θ sin φ)
    disc (valid for a dome seen from its axis), and triangle areas are measured in 3D.
    """
    xyz = np.asarray(xyz, dtype=float)
    if triangles is None:
        triangles = Delaunay(_disc(*surface_angles(xyz, cfg))).simplices
    tri = np.asarray(triangles, dtype=int)
    a, b, c = xyz[tri[:, 0]], xyz[tri[:, 1]], xyz[tri[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    out = np.zeros(xyz.shape[0])
    for k in range(3):
        np.add.at(out, tri[:, k], area / 3.0)
    return out


def transfer_nearest(node_xyz: np.ndarray, node_values: np.ndarray, surface_xyz: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Values of the nearest FE node (k-d tree) at each surface vertex; also returns the distances (mm)."""
    dist, idx = cKDTree(np.asarray(node_xyz, dtype=float)).query(np.asarray(surface_xyz, dtype=float))
    return np.asarray(node_values)[idx], dist


def _pad_points(theta: np.ndarray, phi: np.ndarray, values: np.ndarray, cfg: FieldConfig):
    """Replicate points across the φ = ±π seam and the apex along φ (seed: 'extend the data')."""
    th, ph, va = [theta], [phi], [values]
    hi, lo = phi > np.pi - cfg.phi_pad_rad, phi < -np.pi + cfg.phi_pad_rad
    th += [theta[hi], theta[lo]]
    ph += [phi[hi] - 2 * np.pi, phi[lo] + 2 * np.pi]
    va += [values[hi], values[lo]]
    apex = theta < cfg.apex_theta_rad
    if np.any(apex):
        copies = np.linspace(-np.pi - cfg.phi_pad_rad, np.pi + cfg.phi_pad_rad, cfg.apex_copies)
        for p in copies:
            th.append(theta[apex]); ph.append(np.full(int(apex.sum()), p)); va.append(values[apex])
    return np.concatenate(th), np.concatenate(ph), np.concatenate(va)


def interpolate_to_grid(theta: np.ndarray, phi: np.ndarray, values: np.ndarray,
                        grid_theta: np.ndarray, grid_phi: np.ndarray, mask: np.ndarray | None = None,
                        cfg: FieldConfig = FieldConfig()) -> np.ndarray:
    """Linear interpolation of scattered (θ, φ) values (N, C) onto pixel tables (H, W) → (C, H, W).

    φ is wrapped with padding so the seam at ±π interpolates from both sides; pixels of the mask
    outside the points' hull (e.g. beyond the last node ring) take the nearest value; pixels outside
    the mask are 0.
    """
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        values = values[:, None]
    th, ph, va = _pad_points(np.asarray(theta, float), np.asarray(phi, float), values, cfg)
    gt, gp = np.asarray(grid_theta, float), np.asarray(grid_phi, float)
    gp = np.where(gp > np.pi, gp - 2 * np.pi, gp)
    mask = np.isfinite(gt) & np.isfinite(gp) if mask is None else (np.asarray(mask, bool) & np.isfinite(gt))
    q = np.stack([gt[mask], gp[mask]], 1)
    pts = np.stack([th, ph], 1)
    out_m = LinearNDInterpolator(pts, va)(q)
    bad = ~np.all(np.isfinite(out_m), axis=1)
    if np.any(bad):
        out_m[bad] = NearestNDInterpolator(pts, va)(q[bad])
    out = np.zeros((values.shape[1],) + gt.shape)
    out[:, mask] = out_m.T
    return out


def smooth_fields(images: np.ndarray, mask: np.ndarray, cfg: FieldConfig = FieldConfig()) -> np.ndarray:
    """Gaussian σ = cfg.gaussian_sigma_px per channel, normalized by the blurred mask (no leak at the rim)."""
    if cfg.gaussian_sigma_px <= 0:
        return np.asarray(images, dtype=float).copy()
    m = np.asarray(mask, dtype=float)
    norm = ndimage.gaussian_filter(m, cfg.gaussian_sigma_px, mode="constant")
    out = np.zeros(images.shape, dtype=float)
    inside = m > 0
    for c in range(images.shape[0]):
        blurred = ndimage.gaussian_filter(images[c] * m, cfg.gaussian_sigma_px, mode="constant")
        out[c][inside] = blurred[inside] / np.maximum(norm[inside], 1e-12)
    return out


def contact_area(mesh_area: np.ndarray, seen_area: np.ndarray, cfg: FieldConfig = FieldConfig()) -> np.ndarray:
    """Per-node area (mm²) that contact forces are divided by: the pixel-grid area of the node's
    interpolation kernel (`seen_area`) when `cfg.conserve_force`, else (and for rim nodes seeing less
    than `conserve_min_ratio` of it) the mesh tributary area."""
    mesh_area, seen_area = np.asarray(mesh_area, float), np.asarray(seen_area, float)
    if not cfg.conserve_force:
        return mesh_area
    return np.where(seen_area >= cfg.conserve_min_ratio * mesh_area, seen_area, mesh_area)


def fe_to_fields(node_xyz: np.ndarray, u: np.ndarray, s: np.ndarray, contact_normal: np.ndarray,
                 contact_shear: np.ndarray, theta: np.ndarray, phi: np.ndarray, pixel_area: np.ndarray,
                 node_area: np.ndarray | None = None, triangles: np.ndarray | None = None,
                 surface_xyz: np.ndarray | None = None, cfg: FieldConfig = FieldConfig()) -> np.ndarray:
    """One FE frame → (15, H, W) float32 field image in physical units (docs/fields.md order).

    node_xyz (N, 3) mm: FE surface nodes at rest; u (N, 3) mm; s (N, 6) MPa as xx, yy, zz, xy, xz, yz;
    contact_normal / contact_shear (N, 3) N per node; theta/phi (H, W) rad and pixel_area (H, W) mm²
    from the calibration tables (pixels with area 0 are off the gel). node_area (N,) mm² (e.g. the FE's
    nodal contact area) or `triangles` to compute it; surface_xyz (M, 3): optional denser surface mesh
    that receives the nodal values by nearest node (k-d tree) before interpolation.
    With `cfg.conserve_force` (and no surface_xyz) contact forces are divided by `contact_area`.
    """
    node_xyz = np.asarray(node_xyz, dtype=float)
    n = node_xyz.shape[0]
    for name, arr, width in (("u", u, 3), ("s", s, 6), ("contact_normal", contact_normal, 3),
                             ("contact_shear", contact_shear, 3)):
        if np.shape(arr) != (n, width):
            raise FieldDataError(f"fe_to_fields: {name} has shape {np.shape(arr)}, expected ({n}, {width})")
    area = tributary_area(node_xyz, triangles, cfg) if node_area is None else np.asarray(node_area, float)
    if area.shape != (n,) or np.any(area < 0):
        raise FieldDataError(f"fe_to_fields: node_area must be (N={n},) and ≥ 0")
    pixel_area = np.asarray(pixel_area, dtype=float)
    mask = pixel_area > 0
    touched = np.flatnonzero(np.abs(np.asarray(contact_normal, float)).sum(1)
                             + np.abs(np.asarray(contact_shear, float)).sum(1) > 0)
    if cfg.conserve_force and surface_xyz is None and len(touched):
        area = area.copy()
        th0, ph0 = surface_angles(node_xyz, cfg)
        eye = np.zeros((n, len(touched)))
        eye[touched, np.arange(len(touched))] = 1.0
        kernel = interpolate_to_grid(th0, ph0, eye, theta, phi, mask, cfg)      # (m, H, W)
        area[touched] = contact_area(area[touched], (kernel * pixel_area).sum((1, 2)), cfg)
    safe = np.where(area > 0, area, np.inf)
    values = np.concatenate([np.asarray(u, float), np.asarray(s, float),
                             np.asarray(contact_normal, float) / safe[:, None],
                             np.asarray(contact_shear, float) / safe[:, None]], axis=1)
    pts = node_xyz
    if surface_xyz is not None:
        values, dist = transfer_nearest(node_xyz, values, surface_xyz)
        pts = np.asarray(surface_xyz, dtype=float)
        log.debug("k-d transfer: max node distance %.3f mm", float(dist.max()))
    th, ph = surface_angles(pts, cfg)
    img = interpolate_to_grid(th, ph, values, theta, phi, mask, cfg)
    return smooth_fields(img, mask, cfg).astype(np.float32)


def contact_force_from_image(img: np.ndarray, pixel_area: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total contact normal and shear force (N, 3 each) of a (15, H, W) physical field image."""
    a = np.asarray(pixel_area, dtype=float)
    return (np.tensordot(img[9:12], a, axes=([1, 2], [0, 1])),
            np.tensordot(img[12:15], a, axes=([1, 2], [0, 1])))


# ---------------------------------------------------------------- normalization and bounds JSON

def compute_bounds(images, cfg: FieldConfig = FieldConfig()) -> dict[str, list[float]]:
    """Global per-channel [lo, hi] over an iterable of (15, H, W) images (the seed's bounds JSON)."""
    lo = np.full(N_CHANNELS, np.inf)
    hi = np.full(N_CHANNELS, -np.inf)
    for img in images:
        img = np.asarray(img)
        if img.shape[0] != N_CHANNELS:
            raise FieldDataError(f"compute_bounds: image has {img.shape[0]} channels, expected {N_CHANNELS}")
        lo = np.minimum(lo, img.reshape(N_CHANNELS, -1).min(1))
        hi = np.maximum(hi, img.reshape(N_CHANNELS, -1).max(1))
    if not np.all(np.isfinite(lo)):
        raise FieldDataError("compute_bounds: no images or non-finite values")
    span = np.maximum(hi - lo, cfg.min_bound_span)
    lo, hi = lo - cfg.bounds_margin * span, lo + span + cfg.bounds_margin * span
    return {name: [float(lo[i]), float(hi[i])] for i, name in enumerate(CHANNELS)}


def _bounds_arrays(bounds: dict) -> tuple[np.ndarray, np.ndarray]:
    missing = [c for c in CHANNELS if c not in bounds]
    if missing:
        raise FieldDataError(f"bounds: missing channels {missing} (expected docs/fields.md names)")
    b = np.array([bounds[c] for c in CHANNELS], dtype=float)
    if not np.all(np.isfinite(b)) or np.any(b[:, 0] > b[:, 1]):
        raise FieldDataError("bounds: every channel needs finite [lo, hi] with lo ≤ hi")
    return b[:, 0], b[:, 1]


def normalize_global(img: np.ndarray, bounds: dict) -> np.ndarray:
    """(15, H, W) physical → [0, 1] with the dataset bounds: y = (v − lo) / (hi − lo), clipped."""
    lo, hi = _bounds_arrays(bounds)
    span = np.where(hi > lo, hi - lo, 1.0)
    return np.clip((img - lo[:, None, None]) / span[:, None, None], 0.0, 1.0).astype(np.float32)


def denormalize(y: np.ndarray, bounds: dict) -> np.ndarray:
    """Inverse of normalize_global: value = lo + y·(hi − lo) (docs/fields.md). Works on (..., 15, H, W)."""
    lo, hi = _bounds_arrays(bounds)
    return lo[:, None, None] + np.asarray(y) * (hi - lo)[:, None, None]


def normalize_per_image(img: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-image min/max contrast normalization (seed's 'local statistics'; for viewing) → (y, lo, hi)."""
    flat = img.reshape(img.shape[0], -1)
    lo, hi = flat.min(1), flat.max(1)
    span = np.where(hi > lo, hi - lo, 1.0)
    return ((img - lo[:, None, None]) / span[:, None, None]).astype(np.float32), lo, hi


def write_bounds(path: str | Path, bounds: dict) -> None:
    """Atomic write of bounds.json ({"channels": [...], "units": ..., "bounds": {name: [lo, hi]}})."""
    _bounds_arrays(bounds)
    from ...contracts.fields import CHANNEL_UNITS

    doc = {"schema": "tensortouch.bounds", "schema_version": 1, "channels": list(CHANNELS),
           "units": list(CHANNEL_UNITS), "bounds": {c: list(map(float, bounds[c])) for c in CHANNELS}}
    atomic_write_json(path, doc)


def read_bounds(path: str | Path) -> dict[str, list[float]]:
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise FieldDataError(f"{path}: cannot read bounds JSON ({exc})") from None
    if doc.get("channels") != list(CHANNELS):
        raise FieldDataError(f"{path}: channels {doc.get('channels')} differ from docs/fields.md order")
    bounds = doc.get("bounds", {})
    _bounds_arrays(bounds)
    return {c: list(bounds[c]) for c in CHANNELS}


# ---------------------------------------------------------------- multi-indenter attribution

def attribute_contacts(contact_xyz: np.ndarray, indenter_xyz: np.ndarray, seed: int = 0) -> np.ndarray:
    """Label (M,) ∈ [0, I) of each contact node: k-means with k = I (started at the indenter
    positions), then clusters assigned one-to-one to indenters by least total centroid distance."""
    pts = np.asarray(contact_xyz, dtype=float)
    ind = np.asarray(indenter_xyz, dtype=float).reshape(-1, 3)
    k = ind.shape[0]
    if pts.shape[0] == 0:
        return np.zeros(0, dtype=int)
    if k == 1:
        return np.zeros(pts.shape[0], dtype=int)
    k_eff = min(k, pts.shape[0])
    init = ind if k_eff == k else pts[:k_eff]
    centroids, labels = kmeans2(pts, init.copy(), minit="matrix", iter=20, seed=seed)
    cost = np.linalg.norm(centroids[:, None, :] - ind[None, :, :], axis=2)
    cost = np.where(np.isfinite(cost), cost, 1e12)
    rows, cols = linear_sum_assignment(cost)
    mapping = np.zeros(k_eff, dtype=int)
    mapping[rows] = cols
    return mapping[labels]
