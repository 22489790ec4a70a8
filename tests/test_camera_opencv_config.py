"""Configuration of a live OpenCV camera (drivers/camera/opencv/config.py): defaults and refusals."""
import pytest
from tensortouch.contracts.errors import CaptureError
from tensortouch.drivers.camera.opencv.config import V4L2_EXPOSURE_UNIT_S, OpenCVCameraConfig


def test_defaults_and_a_serial_instead_of_a_device():
    c = OpenCVCameraConfig(device=0)
    assert (c.width, c.height, c.fps, c.fourcc, c.api) == (640, 480, 120.0, "MJPG", "v4l2")
    assert c.exposure_s is None and c.auto_reconnect
    assert OpenCVCameraConfig(serial="SN123").device is None
    assert round(2e-3 / V4L2_EXPOSURE_UNIT_S) == 20          # 2 ms is 20 V4L2 exposure steps


@pytest.mark.parametrize("kwargs, word", [
    ({}, "needs device"),
    ({"device": 0, "api": "dshow"}, "api is 'dshow'"),
    ({"device": 0, "fourcc": "MJPEG"}, "fourcc is 'MJPEG'"),
])
def test_bad_settings_name_the_field(kwargs, word):
    with pytest.raises(CaptureError, match=word):
        OpenCVCameraConfig(**kwargs)
