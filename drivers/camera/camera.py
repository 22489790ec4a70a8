"""The camera interface every capture backend implements (LeRobot-style, deliberately small).

A camera delivers `Frame`s: an (H, W, 3) uint8 RGB image, a timestamp in seconds and a running
index. Two ways to read:

- `read(timeout_s)` blocks until the *next* frame (one not returned before) and returns it;
  a replay at `realtime=False` therefore yields every recorded frame exactly once, in order.
- `read_latest()` returns the newest frame available now, without waiting for a new one and
  without queueing: a slow consumer skips frames instead of falling behind. It may return the same
  frame as the previous call (compare `Frame.index`). It waits only when no frame at all has been
  captured since `connect()`.

Faults (a device that disappears, a camera that stops delivering frames, an unreadable video)
raise `CaptureError` with a message naming the source; the end of a finite replay raises
`EndOfStream` (a `CaptureError` subclass) so a frame loop can tell "done" from "broken".
"""
from __future__ import annotations

import abc
import logging
from dataclasses import dataclass, field

import numpy as np

from ...contracts.errors import CaptureError

log = logging.getLogger(__name__)


class EndOfStream(CaptureError):
    """A finite source (replay without loop) has delivered its last frame."""


@dataclass(frozen=True)
class Frame:
    """One camera frame. `image` is (H, W, 3) uint8 RGB; `t` in s; `index` counts frames from 0.

    Live cameras stamp `t` with `time.monotonic()` when the frame arrived; replays report the
    recording's own clock (frames.csv), shifted by whole recording lengths when looping.
    """

    image: np.ndarray
    t: float
    index: int


@dataclass
class CameraConfig:
    """Fields shared by every backend."""

    read_timeout_s: float = field(default=1.0, kw_only=True)
    """(keyword-only, so each backend's own first field can be positional) `read()` raises CaptureError when no new frame arrives within this time (s)."""


class Camera(abc.ABC):
    """Abstract camera: connect/disconnect, read/read_latest, context manager."""

    def __init__(self, config: CameraConfig):
        self.config = config

    # -- lifecycle -------------------------------------------------------------------------
    @abc.abstractmethod
    def connect(self) -> None:
        """Open the source; raises DeviceNotFoundError / CaptureError with a clear message."""

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Release the source. Safe to call twice."""

    @property
    @abc.abstractmethod
    def is_connected(self) -> bool:
        """True between a successful connect() and disconnect()."""

    # -- frames ----------------------------------------------------------------------------
    @abc.abstractmethod
    def read(self, timeout_s: float | None = None) -> Frame:
        """Block until the next frame (not returned before) and return it."""

    @abc.abstractmethod
    def read_latest(self) -> Frame:
        """The newest frame available now; may repeat the previous one (same `index`)."""

    # -- description -----------------------------------------------------------------------
    @property
    def name(self) -> str:
        """A short human-readable name of the source, used in messages."""
        return type(self).__name__

    def info(self) -> dict:
        """What the source actually delivers (for status / sensor-info replies)."""
        return {"source": self.name}

    # -- helpers ---------------------------------------------------------------------------
    def _require_connected(self) -> None:
        if not self.is_connected:
            raise CaptureError(f"{self.name}: not connected (call connect() or use 'with camera:')")

    def __enter__(self) -> "Camera":
        self.connect()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.disconnect()

    def __repr__(self) -> str:
        state = "connected" if self.is_connected else "disconnected"
        return f"<{type(self).__name__} {self.name} {state}>"


def to_rgb(image: np.ndarray | None, where: str) -> np.ndarray:
    """Convert a decoded OpenCV image (BGR, BGRA or gray) to (H, W, 3) uint8 RGB, or raise."""
    import cv2

    if image is None or not isinstance(image, np.ndarray) or image.size == 0:
        raise CaptureError(f"{where}: no image decoded (unreadable or garbled frame)")
    if image.dtype != np.uint8:
        raise CaptureError(f"{where}: frame dtype {image.dtype}, expected uint8")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    raise CaptureError(f"{where}: frame shape {image.shape}, expected (H, W, 3) color or (H, W) gray")
