"""Camera source strings (drivers/camera/factory.py): schemes, options, overrides, and what is refused."""
import numpy as np
import pytest
from tensortouch.contracts.errors import CaptureError
from tensortouch.drivers.camera import (
    ReplayCameraConfig,
    config_from_uri,
)

from tests.test_drivers_camera import write_session


def test_source_strings(tmp_path):
    root = write_session(tmp_path / "s", np.arange(3) * 0.1, "images")
    cfg = config_from_uri(f"replay:{root}?loop=1&realtime=false&speed=2")
    assert isinstance(cfg, ReplayCameraConfig) and cfg.loop and not cfg.realtime and cfg.speed == 2.0
    assert isinstance(config_from_uri(str(root)), ReplayCameraConfig)
    cfg = config_from_uri("v4l2:2?width=1280&height=720&fps=60&exposure_s=0.002")
    assert (cfg.device, cfg.width, cfg.height, cfg.fps, cfg.exposure_s) == (2, 1280, 720, 60.0, 0.002)
    assert config_from_uri("/dev/video1").device == "/dev/video1"
    assert config_from_uri("usb:TT0042", width=320).serial == "TT0042"
    assert config_from_uri("v4l2:0?fourcc=none").fourcc is None
    for bad, msg in [("v4l2:0?colour=red", "unknown option"), ("v4l2:0?width=wide", "width"),
                     (f"replay:{root}?loop=maybe", "loop"), ("replay:", "nothing after"),
                     ("v4l2:0?width", "key=value"), (str(tmp_path / "missing.avi"), "no such")]:
        with pytest.raises(CaptureError, match=msg):
            config_from_uri(bad)
