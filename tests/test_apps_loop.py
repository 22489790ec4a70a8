"""The frame loop (runtime/apps/loop.py): a stalled camera is flagged and recovers, a dead one stops with a
message, black and frozen frames are flagged."""
import numpy as np
import pytest
from tensortouch.contracts.errors import CaptureError
from tensortouch.runtime.apps.loop import LoopConfig, SensorLoop
from tensortouch.runtime.pipeline import SensorPipeline
from tensortouch.runtime.stages.model import FieldModel, load_package
from tensortouch.tools.bench.models import write_difference_package

from tests.conftest import dome_calibration
from tests.test_e2e_runtime import SENSOR, SIZE, H, W


@pytest.fixture
def env(tmp_path, monkeypatch):
    write_difference_package(tmp_path / "models" / "difference-32", SIZE)
    monkeypatch.setenv("TENSORTOUCH_MODELS", str(tmp_path / "models"))
    monkeypatch.setenv("TENSORTOUCH_CALIBRATION", str(tmp_path / "calib"))
    return tmp_path


class StallingCamera:
    """Stand-in for a camera that stops delivering frames for a while (no hardware here)."""

    def __init__(self, frames, stall_from, stall_n):
        self.frames, self.stall_from, self.stall_n = frames, stall_from, stall_n
        self.i = 0
        self.stalls = 0

    def read(self, timeout_s=None):
        from tensortouch.drivers.camera.camera import EndOfStream, Frame

        if self.i == self.stall_from and self.stalls < self.stall_n:
            self.stalls += 1
            raise CaptureError("camera stopped delivering frames (read timeout 1.0 s)")
        if self.i >= len(self.frames):
            raise EndOfStream("end")
        f = Frame(self.frames[self.i], self.i / 30.0, self.i)
        self.i += 1
        return f


class RecordingPublisher:
    def __init__(self):
        self.status, self.contacts = [], 0

    def publish_fields(self, *a):
        return True

    def publish_contacts(self, *a):
        self.contacts += 1

    def publish_wrench(self, *a):
        return True

    def publish_status(self, status, seq=None, t=None):
        self.status.append(status)


def _pipeline(env):
    dome_calibration(env / "calib", SENSOR, size=SIZE, image=(W, H))
    from tensortouch.contracts.store import CalibrationStore

    pkg = load_package(env / "models" / "difference-32")
    return SensorPipeline(SENSOR, FieldModel(pkg, "fp32"), CalibrationStore(env / "calib").load(SENSOR))


def test_camera_stall_flags_status_and_recovers(env):
    rng = np.random.default_rng(0)
    frames = [np.clip(120 + rng.normal(0, 1, (H, W, 3)), 0, 255).astype(np.uint8) for _ in range(60)]
    pub = RecordingPublisher()
    loop = SensorLoop(StallingCamera(frames, 40, 5), _pipeline(env), pub,
                      LoopConfig(status_every_s=0.0, retry_wait_s=0.0))
    assert loop.run() == 60
    flagged = [s for s in pub.status if "camera_stalled" in s["flags"]]
    assert flagged, "no status carried camera_stalled"
    assert "camera_stalled" not in pub.status[-1]["flags"]  # cleared once frames flow again


def test_camera_dead_stops_with_message(env):
    frames = [np.full((H, W, 3), 120, np.uint8)] * 5
    loop = SensorLoop(StallingCamera(frames, 2, 10**6), _pipeline(env), RecordingPublisher(),
                      LoopConfig(max_camera_failures=5, retry_wait_s=0.0))
    from tensortouch.contracts.errors import TensorTouchError

    with pytest.raises(TensorTouchError, match="camera failed 5 times in a row"):
        loop.run()


def test_black_and_frozen_frames_flagged(env):
    frames = [np.zeros((H, W, 3), np.uint8)] * 50
    pub = RecordingPublisher()
    loop = SensorLoop(StallingCamera(frames, -1, 0), _pipeline(env), pub, LoopConfig(status_every_s=0.0))
    loop.run()
    flags = set(pub.status[-2]["flags"])
    assert {"frame_black", "camera_frozen"} <= flags
