"""Preprocess: circular gel crop around the calibrated center, resize to the model input, to float.

Shapes (S = model size; square unless a (height, width) pair is given):

    frame                    (H, W, 3) uint8 RGB, straight from the camera
    Preprocessor.crop(f)     (S, S, 3) uint8 RGB: gel window resized, outside the circle 0
    Preprocessor.apply(f)    (3, S, S) float32 CHW in [0, 1]            <- current image
    to_chw_float(u8)         (S, S, 3) uint8 -> (3, S, S) float32 in [0, 1]
    model_input(base, cur)   (1, 6, S, S) float32 NCHW: baseline channels 0-2, current 3-5

The crop window is a square of side `window` raw pixels centered on (cx, cy); pixels whose
center lies farther than `radius` from (cx, cy) are set to 0 (at full resolution, before the
resize), as are parts of the window outside the frame. Resizing uses cv2.INTER_AREA. To stay
fast, the window is reduced by exact 2x2 averages (OpenCV's integer INTER_AREA path) while it
is at least twice the output, then one INTER_AREA step finishes; this needs `window` to be a
multiple of 2**halvings, so it is the smallest such integer >= 2 * radius. The gel circle
therefore fills the output to within `(2**halvings - 1)` raw pixels (`radius_out` <= S / 2
gives the exact radius in output pixels; `to_model` / `to_raw` map points exactly).
`exact=True` skips the halvings (window = round(2 * radius), one slower INTER_AREA step).

Everything that depends only on the calibration and the frame size (window, mask, buffers) is
computed once, at the first frame of a given size.
"""
from __future__ import annotations

import logging
import math

import cv2
import numpy as np

from ...contracts.errors import CalibrationError, CaptureError

log = logging.getLogger(__name__)

INV_255 = np.float32(1.0 / 255.0)
MAX_PX = 65536.0          # no camera image is larger: a centre or radius beyond it is never a gel circle


def to_chw_float(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 -> (3, H, W) float32 in [0, 1] (new array)."""
    out = np.empty((image.shape[2],) + image.shape[:2], dtype=np.float32)
    np.multiply(image.transpose(2, 0, 1), INV_255, out=out)
    return out


def model_input(baseline: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Stack baseline and current (each (3, S, S) float32) into the (1, 6, S, S) network input."""
    if baseline.shape != current.shape or baseline.ndim != 3 or baseline.shape[0] != 3:
        raise CaptureError(f"model_input: baseline {baseline.shape} and current {current.shape} "
                           "must both be (3, S, S)")
    out = np.empty((1, 6) + current.shape[1:], dtype=np.float32)
    out[0, :3] = baseline
    out[0, 3:] = current
    return out


class Preprocessor:
    """Crop + mask + resize + float for one calibration (cx, cy, radius in raw px) and model size."""

    def __init__(self, cx: float, cy: float, radius: float, size: int | tuple[int, int],
                 exact: bool = False):
        self.cx, self.cy, self.radius = float(cx), float(cy), float(radius)
        if not (abs(self.cx) <= MAX_PX and abs(self.cy) <= MAX_PX and 0 < self.radius <= MAX_PX):
            raise CalibrationError(f"gel circle center ({cx}, {cy}) radius {radius} px: expected a finite "
                                   f"center and a radius in (0, {MAX_PX:g}] px")
        self.out_h, self.out_w = (size, size) if isinstance(size, (int, np.integer)) else map(int, size)
        if self.out_h <= 0 or self.out_w <= 0:
            raise CalibrationError(f"model size {size}: expected positive")
        need = 2.0 * self.radius / max(self.out_h, self.out_w)
        self.halvings = 0 if exact else max(0, int(math.floor(math.log2(need))) if need >= 2 else 0)
        step = 2 ** self.halvings
        self.window = max(step, int(math.ceil(2.0 * self.radius / step - 1e-9)) * step) if not exact \
            else max(1, int(round(2.0 * self.radius)))
        # window origin (integer pixel) so that the window center is as close as possible to (cx, cy);
        # pixel centers sit at integer coordinates
        self.x0 = int(math.floor(self.cx - (self.window - 1) / 2.0 + 0.5))
        self.y0 = int(math.floor(self.cy - (self.window - 1) / 2.0 + 0.5))
        self.scale_x = self.out_w / self.window  # output px per raw px
        self.scale_y = self.out_h / self.window
        self._frame_shape: tuple | None = None

    @property
    def frame_shape(self) -> tuple | None:
        """The frame shape prepared for (None before the first frame)."""
        return self._frame_shape

    # -- geometry --------------------------------------------------------------------------
    @property
    def radius_out(self) -> float:
        """Gel radius in output pixels (x direction); S / 2 up to the window rounding."""
        return self.radius * self.scale_x

    def to_model(self, x, y):
        """Raw pixel coordinates -> output pixel coordinates (pixel centers at integers)."""
        return ((np.asarray(x) - self.x0 + 0.5) * self.scale_x - 0.5,
                (np.asarray(y) - self.y0 + 0.5) * self.scale_y - 0.5)

    def to_raw(self, u, v):
        """Output pixel coordinates -> raw pixel coordinates (inverse of to_model)."""
        return ((np.asarray(u) + 0.5) / self.scale_x - 0.5 + self.x0,
                (np.asarray(v) + 0.5) / self.scale_y - 0.5 + self.y0)

    # -- precomputation --------------------------------------------------------------------
    def prepare(self, shape: tuple) -> None:
        """Precompute for frames of `shape` (H, W, 3). CalibrationError, before anything is allocated, when
        the gel circle cannot belong to such a frame: its centre outside the frame or its radius longer
        than the frame's long side (the window would be larger than the image it crops)."""
        h, w = shape[:2]
        if not (0 <= self.cx <= w and 0 <= self.cy <= h and self.radius <= max(w, h)):
            raise CalibrationError(f"gel circle at ({self.cx:.6g}, {self.cy:.6g}) radius {self.radius:.6g} px lies "
                                   f"outside the {w}x{h} camera frame or is larger than it (expected the centre "
                                   f"inside the frame and a radius <= {max(w, h)} px; wrong calibration for this "
                                   f"camera?)")
        n = self.window
        sx0, sy0 = max(self.x0, 0), max(self.y0, 0)
        sx1, sy1 = min(self.x0 + n, w), min(self.y0 + n, h)
        if sx1 <= sx0 or sy1 <= sy0:
            raise CalibrationError(f"gel circle at ({self.cx:.1f}, {self.cy:.1f}) radius {self.radius:.1f} px "
                                   f"lies outside the {w}x{h} camera frame (wrong calibration for this camera?)")
        self._src = (slice(sy0, sy1), slice(sx0, sx1))
        self._dst = (slice(sy0 - self.y0, sy1 - self.y0), slice(sx0 - self.x0, sx1 - self.x0))
        yy, xx = np.mgrid[self.y0:self.y0 + n, self.x0:self.x0 + n]
        inside = (xx - self.cx) ** 2 + (yy - self.cy) ** 2 <= self.radius ** 2
        self._mask = np.ascontiguousarray(inside[self._dst].astype(np.uint8))
        self._buf = np.zeros((n, n, 3), dtype=np.uint8)  # outside-mask pixels are never written
        self._halves = [np.empty((n >> k, n >> k, 3), dtype=np.uint8) for k in range(1, self.halvings + 1)]
        self._frame_shape = shape
        if (self.x0, self.y0, self.x0 + n, self.y0 + n) != (sx0, sy0, sx1, sy1):
            log.info("gel window %dx%d at (%d, %d) extends past the %dx%d frame; padded with 0",
                     n, n, self.x0, self.y0, w, h)

    # -- per frame -------------------------------------------------------------------------
    def crop(self, frame: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB -> (S, S, 3) uint8: masked gel window at model size (new array)."""
        if frame.shape != self._frame_shape or frame.dtype != np.uint8:
            if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
                raise CaptureError(f"frame {frame.shape} {frame.dtype}: expected (H, W, 3) uint8 RGB")
            self.prepare(frame.shape)
        src = frame[self._src]
        cv2.bitwise_and(src, src, dst=self._buf[self._dst], mask=self._mask)
        image = self._buf
        for half in self._halves:
            image = cv2.resize(image, half.shape[1::-1], dst=half, interpolation=cv2.INTER_AREA)
        return cv2.resize(image, (self.out_w, self.out_h), interpolation=cv2.INTER_AREA)

    def apply(self, frame: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB -> (3, S, S) float32 in [0, 1]: the model's view of this frame."""
        return to_chw_float(self.crop(frame))

    def __repr__(self) -> str:
        return (f"Preprocessor(center=({self.cx:.1f}, {self.cy:.1f}), radius={self.radius:.1f} px, "
                f"window={self.window} px at ({self.x0}, {self.y0}), halvings={self.halvings}, "
                f"out={self.out_h}x{self.out_w})")
