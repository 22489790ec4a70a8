"""LeRobot camera config for a TensorTouch sensor (type name "tensortouch")."""
from __future__ import annotations

from dataclasses import dataclass

from lerobot.cameras.configs import CameraConfig


@CameraConfig.register_subclass("tensortouch")
@dataclass(kw_only=True)
class TensorTouchCameraConfig(CameraConfig):
    """Fields of one sensor published by `tensortouch run`, as an RGB image.

    sensor_id: the sensor's id (its Zenoh key `tensortouch/<sensor_id>/fields`).
    connect: the runtime's Zenoh endpoint; None: where `tensortouch run` listens by default
        (TENSORTOUCH_ENDPOINT when set, else tcp/127.0.0.1:7447).
    channels: the three field channels shown as R, G, B (scale.FULL_SCALE gives their full scale).
    timeout_ms: how long `read()` and `connect(warmup=True)` wait for a new fields message.
    """

    sensor_id: str
    connect: str | None = None
    channels: tuple[str, str, str] = ("disp_x", "disp_y", "disp_z")
    timeout_ms: float = 2000.0
