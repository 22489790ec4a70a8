"""A new sensor's first calibration: the gel disc found in a rest image, nominal θ/φ from a lens model.

`find_gel` locates the bright gel disc without any prior crop (Otsu threshold → largest blob → its
centre and equal-area radius) and then refines it with the rim fitter (runtime/calib/rim.py: sub-pixel
radial edges, least-squares circle). `nominal_tables` turns the rim circle into θ/φ tables on the
model grid from a lens model: an equidistant fisheye (image radius = f · field angle) on the dome
axis `camera_z_mm` below the gel base, whose focal length follows from the rim (the base circle
of the gel, radius `base_radius_mm`, is seen at field angle atan2(base_radius, -camera_z)). Each
model pixel's ray is intersected with the gel's cap sphere (runtime.stages.geometry.DomeProfile), which
gives θ about the sphere centre and φ = atan2(y, x); `surface_tables` adds points, normals, areas
and the mask (the cap only, up to the base circle; rays outside the lens's field of view are masked).

These are the first version of a sensor's calibration. Pokes refine them (`tensortouch
recalibrate --geometry`: GPR on poke correspondences, then the force correction).
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field

import numpy as np

from ...contracts.errors import CalibrationError
from ...contracts.store import ANY
from ..stages.geometry import DomeProfile, surface_tables
from ..stages.preprocess import Preprocessor
from .rim import RimConfig, RimFit, fit_rim

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LensModel:
    """Equidistant fisheye on the dome axis (the paper's sensor: a 220° lens under the gel)."""

    fov_deg: float = 220.0           # full field of view; rays beyond fov/2 are masked
    camera_z_mm: float = -1.0        # optical centre below the gel base plane (mm, ≤ 0)


@dataclass(frozen=True)
class GelShape:
    """Spherical cap on a short vertical skirt (mm); the paper's gel is 12 / 6 / 2."""

    base_radius_mm: float = 12.0
    cap_height_mm: float = 6.0
    skirt_mm: float = 2.0

    @property
    def profile(self) -> DomeProfile:
        return DomeProfile.of_cap(self.base_radius_mm, self.cap_height_mm, self.skirt_mm)

    @property
    def cap_edge_theta(self) -> float:
        """θ of the cap's edge (where it meets the skirt), rad."""
        return self.profile.edge_theta(self.base_radius_mm)

    def meta(self) -> dict:
        p = self.profile
        return {"shape": "flattened_dome" if self.cap_height_mm < self.base_radius_mm else "dome",
                "base_radius_mm": self.base_radius_mm, "cap_height_mm": self.cap_height_mm,
                "skirt_mm": self.skirt_mm, "radius_mm": p.radius_mm, "center_z_mm": p.center_z_mm,
                "theta": "angle from +z about (0, 0, center_z_mm) (runtime.stages.geometry.DomeProfile)"}


@dataclass(frozen=True)
class GelSearch:
    """How the disc is found without a prior crop."""

    min_radius_frac: float = 0.1     # the disc's radius is at least this share of the image's short side
    rim: RimConfig = field(default_factory=lambda: RimConfig(max_shift_frac=0.3, max_scale_change=0.3))


def find_gel(gray: np.ndarray, cfg: GelSearch = GelSearch(), where: str = "rest image") -> RimFit:
    """The gel disc (centre, radius in camera px) in a grey rest image; CalibrationError when absent."""
    import cv2

    g = np.asarray(gray, np.float64)
    if g.ndim == 3:
        g = g.mean(axis=2)
    if g.ndim != 2 or min(g.shape) < 16:
        raise CalibrationError(f"{where}: expected a grey or colour image, got shape {np.shape(gray)}")
    u8 = np.clip(g, 0, 255).astype(np.uint8)
    _, mask = cv2.threshold(cv2.GaussianBlur(u8, (5, 5), 0), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    n, _, stats, centroids = cv2.connectedComponentsWithStats(mask)
    if n < 2:
        raise CalibrationError(f"{where}: no bright gel disc (image is uniform); is the sensor lit?")
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    radius0 = float(np.sqrt(stats[k, cv2.CC_STAT_AREA] / np.pi))
    if radius0 < cfg.min_radius_frac * min(g.shape):
        raise CalibrationError(f"{where}: the brightest blob has radius {radius0:.1f} px, less than "
                               f"{cfg.min_radius_frac:.0%} of the image; is the gel in view and lit?")
    center0 = (float(centroids[k][0]), float(centroids[k][1]))
    fit = fit_rim(g, center0, radius0, cfg.rim, where=where)
    return RimFit(fit.center, fit.radius, fit.rms_px, fit.points, 0.0, 1.0)


def nominal_theta_phi(center: tuple[float, float], radius_px: float, size: tuple[int, int],
                      lens: LensModel = LensModel(), gel: GelShape = GelShape()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """θ, φ and the in-view mask per model pixel for the crop (center, radius_px) → (h, w) arrays."""
    if lens.camera_z_mm > 0:
        raise CalibrationError(f"lens camera_z_mm {lens.camera_z_mm}: the camera sits at or below the gel base (≤ 0)")
    h, w = (int(v) for v in size)
    pre = Preprocessor(center[0], center[1], radius_px, (h, w))
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = pre.to_raw(u, v)
    dx, dy = x - center[0], y - center[1]
    alpha_rim = float(np.arctan2(gel.base_radius_mm, -lens.camera_z_mm))
    alpha = np.hypot(dx, dy) / radius_px * alpha_rim            # equidistant: radius ∝ field angle
    phi = np.arctan2(dy, dx)
    d = np.stack([np.sin(alpha) * np.cos(phi), np.sin(alpha) * np.sin(phi), np.cos(alpha)], axis=-1)
    p = gel.profile
    oc = np.array([0.0, 0.0, lens.camera_z_mm - p.center_z_mm])
    b = d @ oc
    disc = b * b - (oc @ oc - p.radius_mm ** 2)
    s = -b + np.sqrt(np.clip(disc, 0.0, None))                  # the camera is inside the sphere
    pts = oc + s[..., None] * d                                 # relative to the sphere centre
    theta = np.arctan2(np.hypot(pts[..., 0], pts[..., 1]), pts[..., 2])
    in_view = (disc >= 0) & (alpha <= np.radians(lens.fov_deg) / 2)
    return theta, phi, in_view


def nominal_tables(center: tuple[float, float], radius_px: float, size: tuple[int, int],
                   lens: LensModel = LensModel(), gel: GelShape = GelShape()) -> dict[str, np.ndarray]:
    """The calibration store's tables (contracts.store.TABLES) from the lens model."""
    theta, phi, in_view = nominal_theta_phi(center, radius_px, size, lens, gel)
    theta = np.where(in_view, theta, np.nan)
    tables = surface_tables(theta, phi, gel.profile, theta_limit=gel.cap_edge_theta)
    tables["theta"] = np.where(tables["mask"], tables["theta"], 0.0).astype(np.float32)
    tables["phi"] = np.where(tables["mask"], tables["phi"], 0.0).astype(np.float32)
    return tables


def init_calibration(store, sensor_id: str, frames: list[np.ndarray], size: tuple[int, int],
                     lens: LensModel = LensModel(), gel: GelShape = GelShape(),
                     provenance: dict | None = None, search: GelSearch = GelSearch(),
                     base_version=ANY) -> tuple[str, RimFit]:
    """Find the gel in rest `frames` (RGB or grey), write nominal tables as a new version of
    `sensor_id` in `store` (a contracts.store.CalibrationStore); returns (version, rim fit).
    `base_version` as in CalibrationStore.write (None: only if the sensor has no version yet)."""
    from .rim import rest_image

    fit = find_gel(rest_image(frames), search, where=f"{sensor_id}: {len(frames)} rest frames")
    tables = nominal_tables(fit.center, fit.radius, size, lens, gel)
    hgt, wid = np.asarray(frames[0]).shape[:2]
    meta = {"camera": {"width": int(wid), "height": int(hgt)},
            "gel_center_px": [float(v) for v in fit.center], "gel_radius_px": float(fit.radius),
            "model_size": [int(size[0]), int(size[1])], "gel": gel.meta(),
            "provenance": {"method": "nominal-lens", "pokes": 0,
                           "lens": {"model": "equidistant", **asdict(lens)},
                           "rim": fit.to_dict(), "rest_frames": len(frames),
                           "notes": "nominal θ/φ; refine with tensortouch recalibrate --geometry",
                           **(provenance or {})}}
    version = store.write(sensor_id, tables, meta, base_version=base_version)
    log.info("%s: nominal calibration %s (gel centre %.1f, %.1f px, radius %.1f px)",
             sensor_id, version, fit.center[0], fit.center[1], fit.radius)
    return version, fit
