"""LeRobot camera over a TensorTouch sensor's published fields (reading rules: reading.ZenohReader)."""
from __future__ import annotations

from typing import Any

from lerobot.cameras.camera import Camera

from .configuration_tensortouch import TensorTouchCameraConfig
from .reading import ZenohReader
from .scale import to_image


class TensorTouchCamera(ZenohReader, Camera):
    """`read()` waits for the next fields message; `async_read(timeout_ms)` returns the newest one not
    returned yet (waiting up to timeout_ms); `read_latest(max_age_ms)` returns the newest one at once
    and raises TimeoutError when it is older than max_age_ms (a stopped or stalled runtime).

    `width`/`height` come from the config when given (a LeRobot robot needs them up front) and must
    then match the published grid; otherwise from the first frame."""

    what = "fields"

    def __init__(self, config: TensorTouchCameraConfig):
        Camera.__init__(self, config)
        self.config = config
        self._init_reader(config.sensor_id, config.connect, config.timeout_ms)
        self._shape: tuple[int, int] | None = None      # (height, width) of the published grid

    def __str__(self) -> str:
        return f"TensorTouchCamera({self.config.sensor_id})"

    def _already_connected(self) -> Exception:
        from lerobot.utils.errors import DeviceAlreadyConnectedError

        return DeviceAlreadyConnectedError(f"{self} is already connected")

    def _not_connected(self) -> Exception:
        from lerobot.utils.errors import DeviceNotConnectedError

        return DeviceNotConnectedError(f"{self} is not connected")

    @staticmethod
    def find_cameras() -> list[dict[str, Any]]:
        """Sensors alive at the meeting point (TENSORTOUCH_ENDPOINT, else loopback 7447; Zenoh liveliness)."""
        from tensortouch.runtime.apps.subscriber import alive_sensors
        from tensortouch.runtime.apps.zenoh_session import default_endpoint, open_session

        session = open_session(connect=[default_endpoint()], role="subscriber")
        try:
            return [{"name": f"TensorTouch {s}", "type": "tensortouch", "id": s} for s in alive_sensors(session)]
        finally:
            session.close()

    def connect(self, warmup: bool = True) -> None:
        self._subscribe(warmup, on_fields=self._on_fields)
        if warmup:
            self._check_shape()

    def _check_shape(self) -> None:
        want = (self.config.height, self.config.width)
        if None not in want and self._shape != want:
            self.disconnect()
            raise ValueError(f"{self}: config height × width {want[0]}×{want[1]} but the runtime publishes "
                             f"{self._shape[0]}×{self._shape[1]} fields")

    def _on_fields(self, frame) -> None:
        image = to_image(frame.data, frame.channels, self.config.channels)
        if self._shape is None:
            self._shape = image.shape[:2]
            if self.height is None or self.width is None:
                self.height, self.width = self._shape
        self._put(image, frame.seq)
