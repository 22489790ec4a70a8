"""A TensorTouch sensor as a LeRobot robot: observation = named floats (+ cameras), no action."""
from __future__ import annotations

import logging
from functools import cached_property
from typing import Any

from lerobot.cameras.utils import make_cameras_from_configs
from lerobot.robots import Robot
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError
from lerobot_camera_tensortouch import TensorTouchTactile, TensorTouchTactileConfig

from .config_tensortouch import TensorTouchRobotConfig

log = logging.getLogger(__name__)


class TensorTouchRobot(Robot):
    """Reads a running `tensortouch run` (or `tensortouch hand`) over Zenoh; runs no model itself.

    `get_observation()` returns the newest state at once (the wrench and contacts of one runtime frame)
    and each camera's newest frame, and raises TimeoutError when either is older than
    `config.max_age_ms`. `send_action` accepts only the empty action: the sensor has no actuators.
    """

    config_class = TensorTouchRobotConfig
    name = "tensortouch"

    def __init__(self, config: TensorTouchRobotConfig):
        super().__init__(config)
        self.config = config
        self.tactile = TensorTouchTactile(TensorTouchTactileConfig(
            sensor_id=config.sensor_id, connect=config.connect, top_k=config.top_k, name=config.prefix,
            timeout_ms=config.timeout_ms))
        self.cameras = make_cameras_from_configs(config.cameras)

    def __str__(self) -> str:
        return f"TensorTouchRobot({self.config.sensor_id})"

    @cached_property
    def observation_features(self) -> dict[str, type | tuple]:
        cams = {k: (c.height, c.width, 3) for k, c in self.config.cameras.items()}
        return {**self.tactile.features, **cams}

    @cached_property
    def action_features(self) -> dict[str, type]:
        return {}

    @property
    def is_connected(self) -> bool:
        return self.tactile.is_connected and all(c.is_connected for c in self.cameras.values())

    def connect(self, calibrate: bool = True) -> None:
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        self.tactile.connect()
        try:
            for cam in self.cameras.values():
                cam.connect()
        except Exception:
            self._close_all()
            raise
        log.info("%s connected", self)

    @property
    def is_calibrated(self) -> bool:
        return True                    # the runtime applies the sensor's calibration

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def get_observation(self) -> dict[str, Any]:
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected; run `.connect()` first")
        obs: dict[str, Any] = self.tactile.read_latest(self.config.max_age_ms)
        for key, cam in self.cameras.items():
            obs[key] = cam.read_latest(int(self.config.max_age_ms))
        return obs

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected; run `.connect()` first")
        if action:
            raise ValueError(f"{self} is a sensor and takes no action; got keys {sorted(action)}")
        return {}

    def _close_all(self) -> None:
        for dev in (self.tactile, *self.cameras.values()):
            if dev.is_connected:
                dev.disconnect()

    def disconnect(self) -> None:
        if not (self.tactile.is_connected or any(c.is_connected for c in self.cameras.values())):
            raise DeviceNotConnectedError(f"{self} is not connected")
        self._close_all()
        log.info("%s disconnected", self)
