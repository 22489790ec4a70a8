"""Refresh the 2D–3D correspondence (θ/φ tables, gel centre) from poke correspondences (seed §III.G).

Each poke gives its image position (camera px) and its true position on the gel as (θ, φ) (from a
motion-capture/jig pose, or a twin's truth). Seed §III.G:

    dist = |(x, y) - (x_c, y_c)|,   θ = f_GPR(dist),   φ = atan2(y - y_c, x - x_c)

(with our sensor-frame convention φ = atan2(dy, dx), docs/fields.md, plus a fitted rotation φ0 of
the camera about the dome axis). The centre and a smooth odd-polynomial trend θ ≈ a1·d + a3·d³ are
fitted jointly by least squares (φ residuals in px, θ residuals scaled to px); a Gaussian process
(scikit-learn GaussianProcessRegressor) then models the remaining θ(d) residual, so far from the
pokes the mapping falls back to the trend. Dense tables are evaluated on the model grid, which the
preprocessor centres on the (new) gel centre with the crop radius R mapped to the grid's inscribed
circle; grid ↔ camera px goes through runtime.stages.preprocess.Preprocessor (to_raw / to_model) so the
tables match the runtime's crop exactly.

Pure: arrays in, arrays out. No pickle: the GP lives only for the evaluation of the tables.
"""
from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ...contracts.errors import CalibrationError
from ...runtime.stages.preprocess import Preprocessor

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GeometryFitConfig:
    min_pokes: int = 6                 # 5 centre/rotation/trend parameters; 6+ pokes reach mid-range θ
    length_scale_frac: float = 0.5     # GP RBF initial length scale as a fraction of the crop radius
    noise_rad: float = float(np.deg2rad(0.2))  # expected θ noise of one poke (GP white noise init)
    n_restarts: int = 2                # GP hyperparameter restarts (seeded)
    random_state: int = 0
    max_center_shift_frac: float = 0.25  # refuse a centre that moved more than this fraction of R


def model_to_camera(uv_px: np.ndarray, center: tuple[float, float], radius: float,
                    size: tuple[int, int]) -> np.ndarray:
    """Cluster centroids on the model grid (N,2) (u = column, v = row; pixel i spans [i, i+1] as in
    runtime.contacts) → camera px (N,2) through the runtime's own Preprocessor crop."""
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    x, y = Preprocessor(center[0], center[1], radius, tuple(size)).to_raw(uv[:, 0] - 0.5, uv[:, 1] - 0.5)
    return np.stack([x, y], axis=1)


def camera_to_model(xy: np.ndarray, center: tuple[float, float], radius: float,
                    size: tuple[int, int]) -> np.ndarray:
    """Inverse of `model_to_camera`."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    u, v = Preprocessor(center[0], center[1], radius, tuple(size)).to_model(xy[:, 0], xy[:, 1])
    return np.stack([u + 0.5, v + 0.5], axis=1)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def fit_center(xy: np.ndarray, theta: np.ndarray, phi: np.ndarray, center0: tuple[float, float],
               radius: float) -> dict:
    """Joint least squares of gel centre (px), rotation φ0 (rad) and trend θ ≈ a1·d + a3·d³."""
    xy = np.asarray(xy, float)
    d0 = np.hypot(xy[:, 0] - center0[0], xy[:, 1] - center0[1])
    a1 = float(np.median(theta[d0 > 0.05 * radius] / d0[d0 > 0.05 * radius])) if np.any(d0 > 0.05 * radius) \
        else float(np.pi / 2 / radius)

    def resid(p):
        xc, yc, phi0, b1, b3 = p
        dx, dy = xy[:, 0] - xc, xy[:, 1] - yc
        d = np.hypot(dx, dy)
        r_phi = d * _wrap(phi - phi0 - np.arctan2(dy, dx))
        r_theta = (theta - (b1 * d + b3 * d ** 3)) / a1
        return np.concatenate([r_phi, r_theta])

    sol = least_squares(resid, [center0[0], center0[1], 0.0, a1, 0.0], x_scale=[radius * 0.1, radius * 0.1, 0.1,
                        a1, a1 / radius ** 2], loss="soft_l1", f_scale=1.0)
    xc, yc, phi0, b1, b3 = sol.x
    r = resid(sol.x)
    n = len(xy)
    return {"center": (float(xc), float(yc)), "phi0": float(phi0), "trend": (float(b1), float(b3)),
            "rms_phi_px": float(np.sqrt(np.mean(r[:n] ** 2))), "rms_theta_px": float(np.sqrt(np.mean(r[n:] ** 2)))}


class ThetaOfDistance:
    """θ(d) = trend(d) + GP residual(d); d in camera px, θ in rad."""

    def __init__(self, d: np.ndarray, theta: np.ndarray, trend: tuple[float, float], radius: float,
                 cfg: GeometryFitConfig):
        from sklearn.exceptions import ConvergenceWarning
        from sklearn.gaussian_process import GaussianProcessRegressor
        from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

        self.trend = trend
        d = np.concatenate([[0.0], np.asarray(d, float)])       # anchor: the apex is θ = 0
        th = np.concatenate([[0.0], np.asarray(theta, float)])
        resid = th - self._trend(d)
        amp = max(float(np.std(resid)), cfg.noise_rad)
        kernel = (ConstantKernel(amp ** 2, (1e-8, 1.0))
                  * RBF(cfg.length_scale_frac * radius, (0.1 * radius, 4.0 * radius))
                  + WhiteKernel(cfg.noise_rad ** 2, (1e-10, (10 * cfg.noise_rad) ** 2)))
        self.gp = GaussianProcessRegressor(kernel, n_restarts_optimizer=cfg.n_restarts,
                                           random_state=cfg.random_state, normalize_y=False)
        with warnings.catch_warnings():   # hyperparameters at a bound are expected with 6–7 points
            warnings.simplefilter("ignore", ConvergenceWarning)
            self.gp.fit(d[:, None], resid)

    def _trend(self, d):
        return self.trend[0] * d + self.trend[1] * d ** 3

    def __call__(self, d: np.ndarray) -> np.ndarray:
        d = np.asarray(d, float)
        return self._trend(d) + self.gp.predict(d.reshape(-1, 1)).reshape(d.shape)


@dataclass
class GeometryFit:
    center: tuple[float, float]   # new gel centre, camera px
    phi0: float                   # camera rotation about the dome axis, rad
    theta: np.ndarray             # (H, W) rad on the new model grid
    phi: np.ndarray               # (H, W) rad
    residual_deg: dict            # per-poke θ/φ residuals of the final mapping
    fit: dict                     # centre/trend fit diagnostics


def grid_theta_phi(f: ThetaOfDistance, phi0: float, center: tuple[float, float], radius: float,
                   size: tuple[int, int]):
    """Dense θ/φ tables on the model grid cropped around `center` (pixel centres mapped to camera
    px by the runtime's Preprocessor, so the tables match what the runtime will crop)."""
    h, w = size
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = Preprocessor(center[0], center[1], radius, (h, w)).to_raw(uu, vv)
    dx, dy = x - center[0], y - center[1]
    theta = f(np.hypot(dx, dy))
    phi = _wrap(np.arctan2(dy, dx) + phi0)
    return theta.astype(np.float32), phi.astype(np.float32)


def refresh_geometry(xy_cam: np.ndarray, theta_true: np.ndarray, phi_true: np.ndarray,
                     center0: tuple[float, float], radius: float, size: tuple[int, int],
                     cfg: GeometryFitConfig = GeometryFitConfig()) -> GeometryFit:
    """Pokes (camera px ↔ true θ, φ) → new centre and θ/φ tables on the re-centred model grid."""
    xy = np.asarray(xy_cam, float).reshape(-1, 2)
    theta_true = np.asarray(theta_true, float).ravel()
    phi_true = np.asarray(phi_true, float).ravel()
    if len(xy) < cfg.min_pokes:
        raise CalibrationError(f"geometry refresh needs at least {cfg.min_pokes} pokes with known 3D "
                               f"positions, got {len(xy)}")
    fc = fit_center(xy, theta_true, phi_true, center0, radius)
    shift = float(np.hypot(fc["center"][0] - center0[0], fc["center"][1] - center0[1]))
    if shift > cfg.max_center_shift_frac * radius:
        raise CalibrationError(f"geometry refresh: gel centre moved {shift:.1f} px (> {cfg.max_center_shift_frac:.0%} "
                               "of the crop radius); check the poke positions or recalibrate at the bench")
    xc, yc = fc["center"]
    d = np.hypot(xy[:, 0] - xc, xy[:, 1] - yc)
    f = ThetaOfDistance(d, theta_true, fc["trend"], radius, cfg)
    theta, phi = grid_theta_phi(f, fc["phi0"], (xc, yc), radius, size)
    res_t = np.degrees(f(d) - theta_true)
    res_p = np.degrees(_wrap(np.arctan2(xy[:, 1] - yc, xy[:, 0] - xc) + fc["phi0"] - phi_true))
    log.info("geometry refresh: centre (%.2f, %.2f) px (moved %.2f px), phi0 %.2f deg, theta rms %.3f deg",
             xc, yc, shift, np.degrees(fc["phi0"]), float(np.sqrt(np.mean(res_t ** 2))))
    return GeometryFit(center=(xc, yc), phi0=fc["phi0"], theta=theta, phi=phi,
                       residual_deg={"theta": res_t.tolist(), "phi": res_p.tolist()},
                       fit={**fc, "center_shift_px": shift})


def theta_phi_from_xyz(xyz_mm: np.ndarray, center_z_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """True (θ, φ) of gel-surface points (sensor frame, mm) for a spherical-cap dome."""
    p = np.asarray(xyz_mm, float).reshape(-1, 3)
    return np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2] - center_z_mm), np.arctan2(p[:, 1], p[:, 0])
