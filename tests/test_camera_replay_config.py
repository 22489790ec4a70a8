"""Configuration of a replayed recording (drivers/camera/replay/config.py): path, speed and fps checks."""
from pathlib import Path

import pytest
from tensortouch.contracts.errors import CaptureError
from tensortouch.drivers.camera.replay.config import DEFAULT_VIDEO_FPS, ReplayCameraConfig


def test_path_is_expanded_and_defaults_pace_in_real_time():
    c = ReplayCameraConfig(path="~/rec/s1")
    assert c.path == Path.home() / "rec" / "s1"
    assert c.realtime and not c.loop and c.speed == 1.0 and c.fps is None
    assert DEFAULT_VIDEO_FPS == 30.0


@pytest.mark.parametrize("kwargs, word", [
    ({}, "path is empty"),
    ({"path": "v.avi", "speed": 0}, "speed is 0, expected > 0"),
    ({"path": "v.avi", "fps": -5.0}, "fps is -5.0, expected > 0"),
])
def test_bad_settings_name_the_field(kwargs, word):
    with pytest.raises(CaptureError, match=word):
        ReplayCameraConfig(**kwargs)
