"""Configuration of a replayed recording (session directory or plain video file)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ....contracts.errors import CaptureError
from ..camera import CameraConfig

DEFAULT_VIDEO_FPS = 30.0
"""Clock of a plain video file whose container does not state a frame rate (frames/s)."""


@dataclass
class ReplayCameraConfig(CameraConfig):
    """Replay `path`: a session directory (session.json + frames.csv + frames.avi | frames/) or a
    plain video file (.avi MJPG, .mp4 mp4v; its clock is frame number / fps).

    realtime=True paces frames by their recorded clock (times `1/speed`); False delivers them as
    fast as they decode. loop=True starts over after the last frame (timestamps keep increasing).
    """

    path: str | Path = ""
    realtime: bool = True
    loop: bool = False
    speed: float = 1.0
    fps: float | None = None
    """Plain video only: override the container's frame rate (frames/s)."""

    def __post_init__(self) -> None:
        if not str(self.path):
            raise CaptureError("ReplayCameraConfig.path is empty: give a session directory or a video file")
        self.path = Path(self.path).expanduser()
        if self.speed <= 0:
            raise CaptureError(f"ReplayCameraConfig.speed is {self.speed}, expected > 0")
        if self.fps is not None and self.fps <= 0:
            raise CaptureError(f"ReplayCameraConfig.fps is {self.fps}, expected > 0")
