"""Twin camera: a 220° fisheye under the gel base, 9 LEDs around the lens, a dotted gel skin.

Projection is the equidistant fisheye model with the same distortion polynomial as
`cv2.fisheye` (r = f·θd, θd = α(1 + k1α² + k2α⁴ + k3α⁶ + k4α⁸), α = angle from the optical axis);
for α < 90° it equals cv2.fisheye.projectPoints (tested). The camera looks up +z; image column
≈ +x, row ≈ +y (docs/fields.md).

Rendering (vectorized numpy + cv2.remap), per frame:
1. every gel pixel q has a rest surface point X0(q); the deformed point X = X0 + u(q);
2. LED shading at X with the deformed normal (finite differences of X over the pixel grid):
   I0(q) = albedo(q) · (ambient + Σ_l b_l c_l max(0, -n·ŵ_l) · d_ref²/|w_l|²)  (inner skin faces -n);
3. forward image flow d(q) = proj(X) - q; the frame is I(p) = I0(q(p)) with q = p - d(q), solved
   by fixed-point iteration with cv2.remap (in-plane motion moves the dots, normal motion moves
   and re-shades them);
4. exposure gain, Gaussian read noise + shot noise, 8-bit, optional JPEG round trip.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .geometry import GelSurface

log = logging.getLogger(__name__)


@dataclass
class CameraConfig:
    """Nominal camera of a twin unit (px, mm, rad). 220° lens (seed §IV.A)."""

    width: int = 320
    height: int = 240
    focal_px: float = 74.0          # px per rad of field angle (equidistant)
    cx: float = 159.5
    cy: float = 119.5
    k: tuple = (0.0, 0.0, 0.0, 0.0)  # cv2.fisheye distortion k1..k4
    cam_z: float = -1.0             # mm: optical centre below the gel base
    fov_deg: float = 220.0


@dataclass
class LEDConfig:
    """9 LEDs on a ring around the lens (seed §IV.A), colors cycling R, G, B (BGR order below)."""

    count: int = 9
    ring_radius: float = 6.0        # mm
    z: float = -0.5                 # mm, just below the gel base
    colors_bgr: tuple = ((0.15, 0.25, 1.0), (0.2, 1.0, 0.25), (1.0, 0.35, 0.15))
    ambient: float = 0.06
    d_ref: float = 10.0             # mm, distance at which an LED gives its nominal brightness
    gain: float = 0.16


@dataclass
class PatternConfig:
    """Dark marker dots on a light skin."""

    spacing: float = 1.1            # mm between dot centres
    dot_radius: float = 0.28        # mm
    skin_albedo: float = 0.9
    dot_albedo: float = 0.12
    background: float = 0.02        # chassis seen outside the gel


@dataclass
class NoiseConfig:
    """Sensor noise (on 0..1 intensities) and optional JPEG-like compression."""

    read_sigma: float = 0.006
    shot_sigma: float = 0.01        # std at full intensity, scales with sqrt(I)
    exposure: float = 1.0
    jpeg_quality: int = 0           # 0 = off


class FisheyeModel:
    """Equidistant fisheye with cv2.fisheye's distortion polynomial."""

    def __init__(self, cfg: CameraConfig):
        self.cfg = cfg
        self.k = np.asarray(cfg.k, dtype=np.float64)
        self.center = np.array([0.0, 0.0, cfg.cam_z])

    def _distort(self, a):
        a2 = a * a
        k1, k2, k3, k4 = self.k
        return a * (1 + a2 * (k1 + a2 * (k2 + a2 * (k3 + a2 * k4))))

    def project(self, pts: np.ndarray) -> np.ndarray:
        """Sensor-frame points (...,3) mm -> pixel coordinates (...,2) = (col, row)."""
        d = np.asarray(pts, dtype=np.float64) - self.center
        rxy = np.hypot(d[..., 0], d[..., 1])
        alpha = np.arctan2(rxy, d[..., 2])
        r = self.cfg.focal_px * self._distort(alpha)
        s = np.where(rxy > 1e-12, r / np.maximum(rxy, 1e-12), 0.0)
        return np.stack([self.cfg.cx + s * d[..., 0], self.cfg.cy + s * d[..., 1]], axis=-1)

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (...,2) -> unit ray directions (...,3) and in-FOV mask."""
        uv = np.asarray(uv, dtype=np.float64)
        du, dv = uv[..., 0] - self.cfg.cx, uv[..., 1] - self.cfg.cy
        rd = np.hypot(du, dv) / self.cfg.focal_px
        a = rd.copy()
        if np.any(self.k):
            for _ in range(8):  # Newton on θd(α) = rd
                a2 = a * a
                k1, k2, k3, k4 = self.k
                f = self._distort(a) - rd
                df = 1 + a2 * (3 * k1 + a2 * (5 * k2 + a2 * (7 * k3 + a2 * 9 * k4)))
                a = a - f / df
        psi = np.arctan2(dv, du)
        dirs = np.stack([np.sin(a) * np.cos(psi), np.sin(a) * np.sin(psi), np.cos(a)], axis=-1)
        return dirs, a <= np.radians(self.cfg.fov_deg / 2)

    def rim_radius_px(self, gel: GelSurface) -> float:
        """Image radius of the gel rim (base circle, z = 0) around the optical centre."""
        return float(np.hypot(*(self.project(np.array([gel.radius, 0.0, 0.0])) -
                                [self.cfg.cx, self.cfg.cy])))


def dot_centres(gel: GelSurface, spacing: float) -> np.ndarray:
    return gel.samples(spacing)


@dataclass
class RestView:
    """Per-pixel rest geometry of one camera looking at one gel."""

    points: np.ndarray      # (H,W,3) mm, rest surface point seen by each pixel
    normals: np.ndarray     # (H,W,3) outward normals
    mask: np.ndarray        # (H,W) bool, pixel sees the gel
    albedo: np.ndarray      # (H,W) float
    grid: np.ndarray        # (H,W,2) float32 pixel coordinates (col,row)


def rest_view(model: FisheyeModel, gel: GelSurface, pattern: PatternConfig) -> RestView:
    cfg = model.cfg
    cols, rows = np.meshgrid(np.arange(cfg.width, dtype=np.float64), np.arange(cfg.height, dtype=np.float64))
    grid = np.stack([cols, rows], -1)
    dirs, in_fov = model.rays(grid)
    pts, ok = gel.intersect(model.center, dirs)
    mask = ok & in_fov
    pts = np.where(mask[..., None], pts, 0.0)
    normals = np.where(mask[..., None], gel.normals(pts), 0.0)
    # dots: anti-aliased by the local pixel footprint on the surface
    tree = cKDTree(dot_centres(gel, pattern.spacing))
    dist, _ = tree.query(pts[mask])
    foot = np.linalg.norm(np.gradient(pts, axis=1), axis=-1)[mask]
    edge = np.clip((dist - pattern.dot_radius) / np.maximum(foot, 1e-3) + 0.5, 0.0, 1.0)
    albedo = np.full(mask.shape, pattern.background)
    albedo[mask] = pattern.dot_albedo + (pattern.skin_albedo - pattern.dot_albedo) * edge
    return RestView(pts, normals, mask, albedo.astype(np.float32), grid.astype(np.float32))


@dataclass
class Renderer:
    """Renders frames of one twin unit (tools/twin/unit.py: TwinUnit.renderer, which holds the unit's
    optics and their defaults). `led_brightness` (9,) is the unit's per-LED factor."""

    model: FisheyeModel
    gel: GelSurface
    leds: LEDConfig
    pattern: PatternConfig
    noise: NoiseConfig
    led_brightness: np.ndarray | None = None
    iterations: int = 3
    shading_step: int = 2           # LED shading evaluated on every 2nd pixel and upsampled

    def __post_init__(self):
        self.view = rest_view(self.model, self.gel, self.pattern)
        ang = 2 * np.pi * np.arange(self.leds.count) / self.leds.count
        self.led_pos = np.stack([self.leds.ring_radius * np.cos(ang), self.leds.ring_radius * np.sin(ang),
                                 np.full(self.leds.count, self.leds.z)], -1)
        cols = np.array(self.leds.colors_bgr, dtype=np.float64)
        self.led_rgb = cols[np.arange(self.leds.count) % len(cols)]
        b = np.ones(self.leds.count) if self.led_brightness is None else np.asarray(self.led_brightness, float)
        self.led_rgb = self.led_rgb * b[:, None]
        m = self.view.mask
        rows = np.flatnonzero(m.any(1))
        cols_ = np.flatnonzero(m.any(0))
        pad = 2
        self.box = (slice(max(rows[0] - pad, 0), rows[-1] + pad + 1), slice(max(cols_[0] - pad, 0), cols_[-1] + pad + 1))
        self._rest = np.full(self.view.points.shape, self.pattern.background, dtype=np.float32)
        self._rest[self.box] = self.shade(np.zeros_like(self.view.points))

    @staticmethod
    def _fd_normals(X):
        n = np.cross(np.gradient(X, axis=1), np.gradient(X, axis=0))
        return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)

    def _rest_fd(self):
        """Finite-difference normals of the rest grid (full frame, float32), oriented outward."""
        if getattr(self, "_fd0", None) is None:
            v = self.view
            fd0 = self._fd_normals(v.points).astype(np.float32)
            sign = np.where(np.sum(fd0 * v.normals, -1, keepdims=True) < 0, -1.0, 1.0).astype(np.float32)
            self._fd0, self._sign = fd0 * sign, sign
        return self._fd0, self._sign

    def _normals(self, X, box):
        """Deformed normals on `box`: analytic rest normal + change of the finite-difference normal
        (the difference cancels the grid's edge artefacts at the gel rim). X is the deformed grid
        on `box` padded by one pixel where the frame allows (central differences inside)."""
        fd0, sign = self._rest_fd()
        n = self.view.normals[box] + sign[box] * self._fd_normals(X) - fd0[box]
        return (n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)).astype(np.float32)

    def _padded(self, box):
        H, W = self.view.mask.shape
        r0, r1 = max(box[0].start - 1, 0), min(box[0].stop + 1, H)
        c0, c1 = max(box[1].start - 1, 0), min(box[1].stop + 1, W)
        inner = (slice(box[0].start - r0, box[0].stop - r0), slice(box[1].start - c0, box[1].stop - c0))
        return (slice(r0, r1), slice(c0, c1)), inner

    def shade(self, u: np.ndarray, box=None) -> np.ndarray:
        """Intensity (h,w,3) float32 of the rest pixels in `box` (default: the gel's bounding box)
        for surface displacement u (H,W,3) mm."""
        v = self.view
        box = self.box if box is None else box
        pbox, inner = self._padded(box)
        Xp = (v.points[pbox] + u[pbox]).astype(np.float32)
        n = self._normals(Xp, pbox)[inner]
        X = Xp[inner]
        h, w = X.shape[:2]
        k = max(1, int(self.shading_step))
        if k > 1:  # LED shading is smooth at the mm scale: evaluate on every k-th pixel, upsample
            X, n = X[::k, ::k], n[::k, ::k]
        L = self.led_pos.astype(np.float32)
        wx = L[:, 0, None, None] - X[None, ..., 0]
        wy = L[:, 1, None, None] - X[None, ..., 1]
        wz = L[:, 2, None, None] - X[None, ..., 2]
        d2 = wx * wx + wy * wy + wz * wz
        dot = -(n[None, ..., 0] * wx + n[None, ..., 1] * wy + n[None, ..., 2] * wz)
        lam = np.maximum(dot, 0.0) * np.float32(self.leds.d_ref ** 2) / (d2 * np.sqrt(d2))
        acc = (self.led_rgb.T.astype(np.float32) @ lam.reshape(len(L), -1)).reshape(3, *lam.shape[1:]).transpose(1, 2, 0)
        if k > 1:
            acc = cv2.resize(np.ascontiguousarray(acc), (w, h), interpolation=cv2.INTER_LINEAR)
        inner_img = (np.float32(self.leds.ambient) + np.float32(self.leds.gain) * acc) * v.albedo[box][..., None]
        return np.where(v.mask[box][..., None], inner_img, np.float32(self.pattern.background)).astype(np.float32)

    def active_box(self, u: np.ndarray, tol: float = 1e-3):
        """Bounding box (with a margin) of the pixels whose displacement exceeds `tol` mm."""
        moving = np.abs(u).max(axis=-1) > tol
        if not moving.any():
            return None
        rows, cols = np.flatnonzero(moving.any(1)), np.flatnonzero(moving.any(0))
        pad = 3
        H, W = moving.shape
        return (slice(max(rows[0] - pad, 0), min(rows[-1] + pad + 1, H)),
                slice(max(cols[0] - pad, 0), min(cols[-1] + pad + 1, W)))

    def render_float(self, u: np.ndarray | None, gain: float = 1.0) -> np.ndarray:
        """Noise-free frame (H,W,3) in 0..1 for displacement u (H,W,3) (None = rest)."""
        box = None if u is None else self.active_box(u)
        if box is None:
            return (self._rest * gain).astype(np.float32)
        v = self.view
        I0 = self._rest.copy()
        I0[box] = self.shade(u, box)
        flow = np.zeros(v.grid.shape, dtype=np.float32)
        Xb = v.points[box] + u[box]
        flow[box] = np.where(v.mask[box][..., None], self.model.project(Xb) - v.grid[box], 0.0).astype(np.float32)
        q = v.grid - flow
        for _ in range(self.iterations):
            d = cv2.remap(flow, q[..., 0], q[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            q = v.grid - d
        img = cv2.remap(I0, q[..., 0], q[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                        borderValue=(self.pattern.background,) * 3)
        return img * np.float32(gain)

    def finish(self, img: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """Exposure, noise, 8-bit quantization and optional JPEG of a float frame."""
        nz = self.noise
        img = img * nz.exposure
        if rng is not None:
            sig = np.sqrt(np.float32(nz.read_sigma ** 2) + np.float32(nz.shot_sigma ** 2) * np.clip(img, 0, None))
            img = img + sig * rng.standard_normal(img.shape, dtype=np.float32)
        out = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
        if nz.jpeg_quality:
            ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(nz.jpeg_quality)])
            out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        return out

    def render(self, u: np.ndarray | None, gain: float = 1.0, rng: np.random.Generator | None = None) -> np.ndarray:
        """uint8 BGR frame (H,W,3)."""
        return self.finish(self.render_float(u, gain), rng)
