"""Configuration of a live V4L2 / OpenCV camera."""
from __future__ import annotations

from dataclasses import dataclass

from ....contracts.errors import CaptureError
from ..camera import CameraConfig

V4L2_EXPOSURE_UNIT_S = 100e-6
"""V4L2 `exposure_time_absolute` (OpenCV CAP_PROP_EXPOSURE on CAP_V4L2) counts 100 µs steps."""


@dataclass
class OpenCVCameraConfig(CameraConfig):
    """A camera opened with OpenCV. Give `device` (index, /dev/video path) or the USB `serial`.

    width/height/fps/exposure are requested from the device and read back; a device that refuses
    a value keeps running with what it delivers and a warning is logged (see `OpenCVCamera.info()`).
    Set a field to None to leave the device's own setting alone.
    """

    device: int | str | None = None
    serial: str | None = None
    width: int | None = 640
    height: int | None = 480
    fps: float | None = 120.0
    fourcc: str | None = "MJPG"
    exposure_s: float | None = None
    """Manual exposure time in s; None keeps the device's auto exposure."""
    api: str = "v4l2"
    """'v4l2' (Linux cameras) or 'any' (OpenCV picks: other OSes, or a video file for tests)."""
    auto_reconnect: bool = True
    """After a fault (unplugged, stalled) the next read reopens the device (re-finding a USB serial);
    if that fails the read raises a CaptureError saying so, and the following read tries again."""
    connect_timeout_s: float = 5.0
    """connect() fails when the first frame does not arrive within this time (s)."""

    def __post_init__(self) -> None:
        if self.device is None and not self.serial:
            raise CaptureError("OpenCVCameraConfig needs device (index or /dev/video path) or serial")
        if self.api not in ("v4l2", "any"):
            raise CaptureError(f"OpenCVCameraConfig.api is {self.api!r}, expected 'v4l2' or 'any'")
        if self.fourcc is not None and len(self.fourcc) != 4:
            raise CaptureError(f"OpenCVCameraConfig.fourcc is {self.fourcc!r}, expected 4 characters like 'MJPG'")
