"""Replay of a recorded session directory or a plain video file."""
from drivers.camera.replay.camera import ReplayCamera
from drivers.camera.replay.config import ReplayCameraConfig

__all__ = ["ReplayCamera", "ReplayCameraConfig"]
