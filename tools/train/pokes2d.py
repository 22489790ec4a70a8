"""Stage 3 core — where a poke at a known 3D point shows in the image (seed §III.G), sub-pixel.

The visible change of a poke is not centred on the image of the poked surface point: the camera sees
the inside of the dome from below, the indentation pushes the skin towards the camera, so the dots
around the contact spread out in a pattern whose centre of expansion, magnitude peak and shading ring
are all shifted from the contact point by amounts that depend on where the poke is (an
image-change centroid is 4–9 px off). So instead of a feature of the change, the detector matches
the whole observed dot motion with the motion predicted from the known geometry:

1. **dots** (`dot_centers`): dark skin dots of the baseline and the poke frame as sub-pixel
   darkness-weighted centroids; each baseline dot is matched to the nearest poke-frame dot
   (`track_dots`) → sparse image motion v_i at baseline positions x_i (accurate to ~0.05 px);
2. **prediction** (`FlowPredictor`): the surface displacement of the poke from FE (stage 2 re-solve
   of the calibration poke from its measured keypoints, at the frame's FE parameter), the rest gel,
   and the sensor design's lens (nominal fisheye). For a candidate image offset t and local scale s,
   the dot at x sees the rest surface point X = ray_nominal(q0 + (x − t − q0)/s) ∩ gel, moves to
   X + a·u(X), and its predicted image motion is s·(P(X + a·u) − P(X)) (P nominal projection, q0 the
   nominal image of the 3D poke point);
3. **fit** (`fit_offset`): robust least squares over (t, s, a) of predicted vs observed motion of the
   dots within `fit_radius_px` → the poke point's image q = q0 + t (the lens error is what t and s
   absorb). On twin calibration pokes (FE displacement of the twin itself) this is 0.5 px rms from
   the exact projection where the change centroid was 1.6–9 px (tests/test_train_pokes2d_detector.py).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PokeDetectConfig:
    dot_background_px: int = 7          # grey closing window (> a dot): darkness = local background − intensity
    dot_level: float = 0.35             # dot pixels: darkness above this × its 99.5th percentile
    refine: str = "centroid"            # sub-pixel centre: "centroid" (darkness-weighted) | "peak" (log-parabola)
    dot_min_px: int = 4                 # dots smaller than this (px) are noise
    match_max_px: float = 3.0           # a dot moves less than this between baseline and poke frame
    fit_radius_px: float = 25.0         # dots within this of the nominal poke image enter the fit
    robust_scale_px: float = 0.3        # soft-L1 scale of the motion residual
    max_offset_px: float = 15.0         # |t| beyond this: the fit failed (nominal lens is closer than that)


def dot_centers(gray: np.ndarray, cfg: PokeDetectConfig = PokeDetectConfig()) -> np.ndarray:
    """(N, 2) sub-pixel (x, y) centres of the dark dots of a grey image: darkness (local background −
    intensity) above a level → regions; each region's darkest pixel refined by a 3-point Gaussian
    (log-parabola) fit per axis, which neighbouring dots bias far less than a region centroid."""
    g = np.asarray(gray, float)
    bg = ndimage.uniform_filter(ndimage.grey_closing(g, size=cfg.dot_background_px), cfg.dot_background_px)
    dark = np.clip(bg - g, 0.0, None)
    level = cfg.dot_level * float(np.percentile(dark, 99.5))
    lab, n = ndimage.label(dark > level)
    if n == 0:
        return np.zeros((0, 2))
    idx = np.arange(1, n + 1)
    size = ndimage.sum(np.ones_like(dark), lab, idx)
    if cfg.refine == "centroid":
        cm = np.array(ndimage.center_of_mass(dark, lab, idx)).reshape(-1, 2)
        return cm[size >= cfg.dot_min_px][:, ::-1]
    peaks = np.array(ndimage.maximum_position(dark, lab, idx)).reshape(-1, 2)
    keep = (size >= cfg.dot_min_px) & (peaks[:, 0] > 0) & (peaks[:, 1] > 0) \
        & (peaks[:, 0] < dark.shape[0] - 1) & (peaks[:, 1] < dark.shape[1] - 1)
    r, c = peaks[keep, 0], peaks[keep, 1]
    L = np.log(np.maximum(dark, 1e-3))

    def sub(a, m, b):
        den = a - 2 * m + b
        return np.where(den < -1e-9, np.clip(0.5 * (a - b) / np.where(den < -1e-9, den, -1.0), -0.5, 0.5), 0.0)
    dy = sub(L[r - 1, c], L[r, c], L[r + 1, c])
    dx = sub(L[r, c - 1], L[r, c], L[r, c + 1])
    return np.column_stack([c + dx, r + dy])


def track_dots(base_gray: np.ndarray, cur_gray: np.ndarray, cfg: PokeDetectConfig = PokeDetectConfig()
               ) -> tuple[np.ndarray, np.ndarray]:
    """Dot positions in the baseline x (M, 2) and their motion v (M, 2) to the current frame (px);
    a dot is kept when its nearest current dot is within match_max_px and the match is mutual."""
    a, b = dot_centers(base_gray, cfg), dot_centers(cur_gray, cfg)
    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    d_ab, j = cKDTree(b).query(a)
    _, i_back = cKDTree(a).query(b)
    ok = (d_ab < cfg.match_max_px) & (i_back[j] == np.arange(len(a)))
    return a[ok], b[j[ok]] - a[ok]


class FlowPredictor:
    """Predicted dot motion of a poke from a surface displacement field and the nominal lens.

    lens: object with project(pts (...,3)) → px (...,2), rays(px) → (dirs, fov), center (3,);
    gel: object with intersect(origin, dirs) → (points, ok); nodes (N, 3) rest surface points, U (N, 3)
    their displacement (mm), interpolated linearly on the unrolled dome; q0 (2,) nominal image of the poke
    point."""

    def __init__(self, lens, gel, nodes: np.ndarray, U: np.ndarray, q0, cfg: PokeDetectConfig = PokeDetectConfig()):
        from scipy.interpolate import LinearNDInterpolator

        self.lens, self.gel, self.cfg = lens, gel, cfg
        nodes = np.asarray(nodes, float)
        self.U = np.asarray(U, float)
        self.q0 = np.asarray(q0, float)
        uv = gel.unrolled(nodes)                      # linear (barycentric) interpolation on the unrolled dome
        self.lin = LinearNDInterpolator(uv, self.U)
        self.tree = cKDTree(uv)

    def __call__(self, x: np.ndarray, t, s: float, a: float = 1.0) -> np.ndarray:
        pix = self.q0 + (np.asarray(x, float) - np.asarray(t, float) - self.q0) / s
        dirs, _ = self.lens.rays(pix)
        X, ok = self.gel.intersect(self.lens.center, dirs)
        uv = self.gel.unrolled(X)
        u = self.lin(uv)
        bad = ~np.isfinite(u).all(1)
        if bad.any():                                 # outside the node hull: nearest node
            u[bad] = self.U[self.tree.query(uv[bad])[1]]
        flow = s * (self.lens.project(X + a * u) - self.lens.project(X))
        return np.where(ok[:, None], flow, 0.0)


def fit_offset(x: np.ndarray, v: np.ndarray, predictor: FlowPredictor, cfg: PokeDetectConfig = PokeDetectConfig()
               ) -> dict:
    """Offset t (px) and scale s that make the predicted dot motion match the observed one.
    The displacement amplitude a is fitted too (the visible skin lags the FE state: gel hysteresis, a
    slightly different depth at the frame time). Returns {'xy': q0 + t, 'offset', 'scale', 'amplitude',
    'rms_px' (motion residual), 'dots', 'ok'}."""
    from scipy.optimize import least_squares

    x, v = np.asarray(x, float), np.asarray(v, float)
    sel = np.linalg.norm(x - predictor.q0, axis=1) < cfg.fit_radius_px
    x, v = x[sel], v[sel]
    if len(x) < 6:
        return {"xy": [float("nan")] * 2, "offset": [float("nan")] * 2, "scale": float("nan"),
                "rms_px": float("nan"), "dots": int(len(x)), "ok": False}
    r = least_squares(lambda p: (predictor(x, p[:2], p[2], p[3]) - v).ravel(), np.array([0.0, 0.0, 1.0, 1.0]),
                      loss="soft_l1", f_scale=cfg.robust_scale_px, bounds=([-30, -30, 0.8, 0.5], [30, 30, 1.25, 1.5]))
    t = r.x[:2]
    rms = float(np.sqrt(np.mean((predictor(x, t, r.x[2], r.x[3]) - v) ** 2)))
    ok = bool(np.hypot(*t) <= cfg.max_offset_px and np.isfinite(rms))
    return {"xy": (predictor.q0 + t).tolist(), "offset": t.tolist(), "scale": float(r.x[2]), "amplitude": float(r.x[3]),
            "rms_px": rms,
            "dots": int(len(x)), "ok": ok}
