"""Find the gel rim in a rest image: re-centre the model crop (recalibration) or place the first crop (calib init).

A unit's optical centre and focal length move the gel's image: the bright disc of the dome in the
fisheye image is centred on the image of the dome axis and its radius scales with the focal length.
The runtime's crop (calibration.json `gel_center_px`, `gel_radius_px`) maps that disc to the model
grid; a crop that is off by a few px hands the model a shifted picture it was not trained on, and
the model answers with per-poke force scatter that no force correction can remove (docs/recalibration.md).

`fit_rim` finds the disc edge along radial rays from the current crop centre (sub-pixel crossing of
the half level between the disc and the background), fits a circle by linear least squares, rejects
outlier edge points and refits. Pure: a grey image in, a `RimFit` out. No truth, no model: the
recalibration session takes the image while the gel is at rest, before the first poke.

`recrop` returns a copy of a calibration with the crop moved/scaled (tables unchanged: a principal
point shift or focal scale moves/scales the image about the dome axis, so the same model-grid
tables apply to the re-cropped grid).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from ...contracts.errors import CalibrationError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RimConfig:
    rays: int = 360                    # radial profiles, evenly spread in angle
    inner_frac: float = 0.6            # profile starts at this fraction of the current radius
    outer_frac: float = 1.25           # and ends here (the background must be reached)
    step_px: float = 0.25              # profile sampling step
    disc_frac: float = 0.95            # disc brightness = 90th percentile of the profile inside this radius
    level: float = 0.3                 # edge = crossing of this fraction between background and disc (the
                                       # disc darkens towards its edge; 0.3 put the twin's rim within 0.1 % of its radius)
    outlier_px: float = 2.0            # edge points farther than this from the first circle are dropped
    min_points_frac: float = 0.6       # at least this share of rays must give an edge point
    max_rms_px: float = 1.0            # circle fit residual above this: no clean rim (occluded, dark)
    max_shift_frac: float = 0.15       # refuse a centre that moved more than this fraction of the radius
    max_scale_change: float = 0.10     # refuse a radius that changed by more than 10 %
    iterations: int = 2                # re-run the profiles from the fitted circle
    min_shift_px: float = 0.5          # smaller changes of centre ...
    min_scale_change: float = 0.005    # ... and radius keep the stored crop (no churn)


@dataclass(frozen=True)
class RimFit:
    center: tuple[float, float]        # camera px
    radius: float                      # camera px
    rms_px: float                      # edge points' distance to the circle (rms)
    points: int                        # edge points used
    shift_px: float                    # distance to the starting centre
    scale: float                       # radius / starting radius

    def to_dict(self) -> dict:
        return {"center_px": [float(v) for v in self.center], "radius_px": float(self.radius),
                "rms_px": float(self.rms_px), "points": int(self.points), "shift_px": float(self.shift_px),
                "scale": float(self.scale)}


def circle_lsq(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic least-squares circle (Kåsa) through points (N,2): centre (2,), radius."""
    x, y = pts[:, 0], pts[:, 1]
    a = np.c_[2 * x, 2 * y, np.ones_like(x)]
    c, *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    return c[:2], float(np.sqrt(c[2] + c[0] ** 2 + c[1] ** 2))


def edge_points(gray: np.ndarray, center: tuple[float, float], radius: float, cfg: RimConfig = RimConfig()) -> np.ndarray:
    """Outermost sub-pixel crossing of the half level on each radial profile: (M,2) camera px."""
    from scipy.ndimage import map_coordinates

    rs = np.arange(cfg.inner_frac * radius, cfg.outer_frac * radius, cfg.step_px)
    ang = np.linspace(0.0, 2 * np.pi, cfg.rays, endpoint=False)
    xs = center[0] + np.cos(ang)[:, None] * rs[None, :]
    ys = center[1] + np.sin(ang)[:, None] * rs[None, :]
    prof = map_coordinates(np.asarray(gray, np.float64), [ys.ravel(), xs.ravel()], order=1, mode="nearest")
    prof = prof.reshape(len(ang), len(rs))
    inside, outside = rs < cfg.disc_frac * radius, rs > 1.1 * radius
    disc = np.percentile(prof[:, inside], 90, axis=1)
    back = np.percentile(prof[:, outside], 10, axis=1)
    lvl = back + cfg.level * (disc - back)
    pts = []
    for k in range(len(ang)):
        if disc[k] - back[k] <= 0:
            continue
        above = np.flatnonzero(prof[k] >= lvl[k])
        if len(above) == 0 or above[-1] + 1 >= len(rs):
            continue
        j = above[-1]
        f = (prof[k, j] - lvl[k]) / max(prof[k, j] - prof[k, j + 1], 1e-12)
        r = rs[j] + f * cfg.step_px
        pts.append((center[0] + r * np.cos(ang[k]), center[1] + r * np.sin(ang[k])))
    return np.array(pts, float).reshape(-1, 2)


def fit_rim(gray: np.ndarray, center0: tuple[float, float], radius0: float, cfg: RimConfig = RimConfig(),
            where: str = "rest image") -> RimFit:
    """The gel disc's circle in a grey rest image, starting from the stored crop (centre, radius)."""
    gray = np.asarray(gray, np.float64)
    if gray.ndim == 3:
        gray = gray.mean(axis=2)
    c, r = np.asarray(center0, float), float(radius0)
    rms, n = float("nan"), 0
    for _ in range(max(1, cfg.iterations)):
        pts = edge_points(gray, (float(c[0]), float(c[1])), r, cfg)
        if len(pts) < cfg.min_points_frac * cfg.rays:
            raise CalibrationError(f"{where}: the gel rim was found on {len(pts)} of {cfg.rays} rays (need "
                                   f"{cfg.min_points_frac:.0%}); is the gel in view, lit and untouched?")
        c, r = circle_lsq(pts)
        d = np.abs(np.hypot(pts[:, 0] - c[0], pts[:, 1] - c[1]) - r)
        keep = d < cfg.outlier_px
        if keep.sum() >= cfg.min_points_frac * cfg.rays:
            c, r = circle_lsq(pts[keep])
            pts = pts[keep]
        res = np.hypot(pts[:, 0] - c[0], pts[:, 1] - c[1]) - r
        rms, n = float(np.sqrt(np.mean(res ** 2))), len(pts)
    shift = float(np.hypot(c[0] - center0[0], c[1] - center0[1]))
    fit = RimFit((float(c[0]), float(c[1])), r, rms, n, shift, r / float(radius0))
    if rms > cfg.max_rms_px:
        raise CalibrationError(f"{where}: the gel rim is not a clean circle (rms {rms:.2f} px > {cfg.max_rms_px} px); "
                               "keep the gel untouched and evenly lit while the session starts")
    if shift > cfg.max_shift_frac * radius0 or abs(fit.scale - 1) > cfg.max_scale_change:
        raise CalibrationError(f"{where}: the gel rim is {shift:.1f} px from the stored centre and its radius changed "
                               f"×{fit.scale:.3f}; more than a field recalibration corrects (max "
                               f"{cfg.max_shift_frac:.0%} of the radius, ±{cfg.max_scale_change:.0%}); recalibrate at the bench")
    log.info("%s: rim centre (%.2f, %.2f) px (moved %.2f px), radius %.2f px (x%.4f), rms %.2f px on %d rays",
             where, c[0], c[1], shift, r, fit.scale, rms, n)
    return fit


def rest_image(frames: list[np.ndarray]) -> np.ndarray:
    """Mean grey image of a few frames (noise down by √n)."""
    if not frames:
        raise CalibrationError("no rest frames to find the gel rim in")
    acc = np.zeros(frames[0].shape[:2], np.float64)
    for f in frames:
        f = np.asarray(f, np.float64)
        acc += f.mean(axis=2) if f.ndim == 3 else f
    return acc / len(frames)


def crop_changes(cal, fit: RimFit, cfg: RimConfig = RimConfig()) -> dict:
    """calibration.json keys a re-crop changes: the centre if it moved ≥ cfg.min_shift_px, the radius if
    it changed by ≥ cfg.min_scale_change (smaller changes keep the stored value: no churn). {} = keep."""
    out = {}
    if fit.shift_px >= cfg.min_shift_px:
        out["gel_center_px"] = [float(v) for v in fit.center]
    if abs(fit.scale - 1.0) >= cfg.min_scale_change:
        out["gel_radius_px"] = float(fit.radius)
    return out


def recrop(cal, changes: dict):
    """A copy of Calibration `cal` with `changes` (from `crop_changes`) in its metadata (tables unchanged)."""
    return replace(cal, meta={**cal.meta, **changes}) if changes else cal
