"""Replay of a recorded session directory or a plain video file."""
from .camera import ReplayCamera
from .config import ReplayCameraConfig

__all__ = ["ReplayCamera", "ReplayCameraConfig"]
