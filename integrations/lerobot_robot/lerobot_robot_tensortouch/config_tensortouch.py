"""LeRobot robot config for one TensorTouch sensor (type name "tensortouch")."""
from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.cameras import CameraConfig
from lerobot.robots import RobotConfig


@RobotConfig.register_subclass("tensortouch")
@dataclass(kw_only=True)
class TensorTouchRobotConfig(RobotConfig):
    """A sensor-only "robot": its observation is the wrench and the top-K contacts of one sensor as
    named floats (lerobot_camera_tensortouch.tactile.feature_names), plus any `cameras` (for example
    the same sensor's fields as a `tensortouch` camera, with width, height and fps set). No actions.

    sensor_id: the sensor's id (Zenoh keys `tensortouch/<sensor_id>/wrench|contacts`).
    connect: the runtime's Zenoh endpoint; None: where `tensortouch run` listens by default
        (TENSORTOUCH_ENDPOINT when set, else tcp/127.0.0.1:7447).
    top_k: how many contacts, strongest first (absent ones are zeros with present = 0).
    prefix: the float names' prefix ("tactile" → "tactile.fx", "tactile.c0.x", ...).
    timeout_ms: how long `connect()` waits for the first state (and each camera's first frame).
    max_age_ms: `get_observation()` raises TimeoutError when the newest state (or a camera's newest
        frame) arrived longer ago than this: a stopped or stalled runtime never reads as zeros.
    """

    sensor_id: str
    connect: str | None = None
    top_k: int = 3
    prefix: str = "tactile"
    timeout_ms: float = 2000.0
    max_age_ms: float = 200.0
    cameras: dict[str, CameraConfig] = field(default_factory=dict)
