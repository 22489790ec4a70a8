"""LeRobot camera over a TensorTouch sensor's published fields (Zenoh subscriber, no polling thread:
Zenoh delivers each message on its own thread and the newest one is kept)."""
from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np
from lerobot.cameras.camera import Camera

from .configuration_tensortouch import TensorTouchCameraConfig
from .scale import to_image

log = logging.getLogger(__name__)


class TensorTouchCamera(Camera):
    """`read()` waits for the next fields message; `async_read(timeout_ms)` returns the newest one not
    returned yet (waiting up to timeout_ms); `read_latest(max_age_ms)` returns the newest one at once
    and raises TimeoutError when it is older than max_age_ms (a stopped or stalled runtime)."""

    def __init__(self, config: TensorTouchCameraConfig):
        super().__init__(config)
        self.config = config
        self._sub = None
        self._cond = threading.Condition()
        self._frame: np.ndarray | None = None
        self._arrived = 0.0          # time.perf_counter() when the newest frame arrived
        self._seq = -1               # its runtime sequence number
        self._count = 0              # frames received
        self._returned = 0           # value of _count when read()/async_read() last returned
        self.last_read_seq = -1      # runtime sequence number of the frame read()/async_read() last returned

    def __str__(self) -> str:
        return f"TensorTouchCamera({self.config.sensor_id})"

    @property
    def is_connected(self) -> bool:
        return self._sub is not None

    @staticmethod
    def find_cameras() -> list[dict[str, Any]]:
        """Sensors alive on the default loopback endpoint (Zenoh liveliness)."""
        from tensortouch.runtime.apps.publisher import open_session
        from tensortouch.runtime.apps.subscriber import alive_sensors

        session = open_session(None, connect=["tcp/127.0.0.1:7447"])
        try:
            return [{"name": f"TensorTouch {s}", "type": "tensortouch", "id": s} for s in alive_sensors(session)]
        finally:
            session.close()

    def connect(self, warmup: bool = True) -> None:
        from lerobot.utils.errors import DeviceAlreadyConnectedError

        from tensortouch.runtime.apps.subscriber import Subscriber

        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        self._sub = Subscriber(self.config.sensor_id, connect=[self.config.connect], on_fields=self._on_fields)
        if warmup:
            try:
                self.async_read(self.config.timeout_ms)
            except TimeoutError:
                self.disconnect()
                raise ConnectionError(f"{self}: no fields from {self.config.connect} within "
                                      f"{self.config.timeout_ms:.0f} ms; is `tensortouch run` publishing fields "
                                      "(not --no-fields) for this sensor?") from None

    def _on_fields(self, frame) -> None:
        image = to_image(frame.data, frame.channels, self.config.channels)
        with self._cond:
            self._frame, self._arrived, self._seq = image, time.perf_counter(), frame.seq
            self._count += 1
            if self.height is None:
                self.height, self.width = image.shape[:2]
            self._cond.notify_all()

    def _require(self) -> None:
        if not self.is_connected:
            from lerobot.utils.errors import DeviceNotConnectedError

            raise DeviceNotConnectedError(f"{self} is not connected")

    def read(self) -> np.ndarray:
        return self.async_read(self.config.timeout_ms)

    def async_read(self, timeout_ms: float = 200) -> np.ndarray:
        self._require()
        deadline = time.perf_counter() + timeout_ms / 1e3
        with self._cond:
            while self._count == self._returned:
                left = deadline - time.perf_counter()
                if left <= 0:
                    raise TimeoutError(f"{self}: no new fields within {timeout_ms:.0f} ms")
                self._cond.wait(left)
            self._returned = self._count
            self.last_read_seq = self._seq
            return self._frame

    def read_latest(self, max_age_ms: int = 500) -> np.ndarray:
        self._require()
        with self._cond:
            frame, arrived = self._frame, self._arrived
        if frame is None:
            raise RuntimeError(f"{self} has not received any fields yet")
        age_ms = (time.perf_counter() - arrived) * 1e3
        if age_ms > max_age_ms:
            raise TimeoutError(f"{self}: the latest fields are {age_ms:.0f} ms old (max {max_age_ms} ms)")
        return frame

    @property
    def latest_seq(self) -> int:
        """Runtime sequence number of the newest frame (-1 before the first)."""
        return self._seq

    def disconnect(self) -> None:
        self._require()
        sub, self._sub = self._sub, None
        sub.close()
