"""Helpers shared by the hand / fault / view tests: tiny model package, replay videos, configs.

Everything here is real (onnxruntime package, MJPG videos decoded by cv2, calibration store on
disk); the only stand-in is `FlakyCamera`, which plays an unplug by raising CaptureError from a
real replay camera for a while (no USB hardware on this machine).
"""
from __future__ import annotations

import socket
import time
from pathlib import Path

from tensortouch.contracts.errors import CaptureError, DeviceNotFoundError
from tensortouch.runtime.apps.hand_config import parse_hand_config

SIZE = 32
IMAGE = (160, 120)


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def wait_until(pred, timeout=10.0, step=0.02):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return pred()


def make_package(folder: Path) -> Path:
    """A deterministic difference network (fields follow the image change): real contacts, fast."""
    from tensortouch.tools.bench.models import write_difference_package

    return write_difference_package(folder, SIZE)


def poke_frames(n: int = 90, seed: int = 0, press=(45, 75), dx: float = 25.0):
    """Rest frames, a blob pressing at (centre + dx) during `press`, rest again. RGB uint8."""
    import cv2  # noqa: F401 - callers write them with cv2
    import numpy as np

    w, h = IMAGE
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    rest = np.zeros((h, w, 3), np.float32)
    rest[...] = (110, 120, 130)
    rest[(xx - w / 2) ** 2 + (yy - h / 2) ** 2 > 50 ** 2] = 0
    out = []
    for k in range(n):
        img = rest.copy()
        if press[0] <= k < press[1]:
            blob = np.exp(-((xx - (w / 2 + dx)) ** 2 + (yy - h / 2) ** 2) / (2 * 6.0 ** 2))
            img += 90 * blob[..., None]
        img += rng.normal(0, 0.8, img.shape)
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out


def write_frames(frames, path: Path, fps: float = 30.0) -> Path:
    """RGB frames as an MJPG video (the benchmarks' writer, at 30 frames/s by default)."""
    from tensortouch.tools.bench.runtime_bench import write_video

    return write_video(frames, path, fps)


def make_video(path: Path, n: int = 90, seed: int = 0, dx: float = 25.0) -> Path:
    return write_frames(poke_frames(n, seed, dx=dx), path)


def make_store(root: Path, serials) -> Path:
    from tests.conftest import dome_calibration

    for s in serials:
        dome_calibration(root, s, size=SIZE, image=IMAGE, radius_px=50.0)
    return root


def hand_cfg(tmp: Path, package: Path, sources: dict, *, can: dict | None = None, **hand):
    """sources: {serial: source uri}; fingers named f0, f1, ... in order."""
    fingers = [{"name": f"f{i}", "serial": s, "source": src} for i, (s, src) in enumerate(sources.items())]
    data = {"hand": {"name": "test-hand", "model": str(package), "calibration_store": str(tmp / "store"),
                     "status_every_s": 0.1, **hand},
            "zenoh": {"listen": [free_endpoint()]}, "finger": fingers,
            "camera": {"realtime": True, "loop": True}}
    if can is not None:
        data["can"] = can
    return parse_hand_config(data, "test hand config")


def make_session(folder: Path, sensor_id: str, frames, fps: float = 30.0) -> Path:
    """A session directory (session.json + frames.csv + frames.avi) holding `frames`."""
    import numpy as np
    from tensortouch.contracts.session import STREAM_COLUMNS, new_manifest, write_manifest, write_table

    folder.mkdir(parents=True)
    write_frames(frames, folder / "frames.avi", fps)
    n = len(frames)
    write_table(folder / "frames.csv", STREAM_COLUMNS["frames"], np.stack([np.arange(n) / fps, np.arange(n)], 1))
    write_manifest(folder, new_manifest(sensor_id, {"frames": {"file": "frames.csv", "video": "frames.avi"}},
                                        provenance={"source": "tests/hand_util.py"}))
    return folder


class Plug:
    """The USB cable of an injected unplug: shared by every FlakyCamera of one finger."""

    def __init__(self):
        self.unplugged = False


class FlakyCamera:
    """Wraps a real camera; while `plug.unplugged`, connect() and read() fail like a pulled USB cable."""

    def __init__(self, camera, plug: Plug):
        self.camera = camera
        self.plug = plug
        self.connects = 0

    @property
    def unplugged(self):
        return self.plug.unplugged

    def connect(self):
        if self.unplugged:
            raise DeviceNotFoundError(f"{self.camera.name}: no such device (unplugged, injected)")
        self.connects += 1
        if not self.camera.is_connected:
            self.camera.connect()

    def disconnect(self):
        self.camera.disconnect()

    @property
    def is_connected(self):
        return self.camera.is_connected

    @property
    def name(self):
        return self.camera.name

    def info(self):
        return self.camera.info()

    def read(self, timeout_s=None):
        if self.unplugged:
            time.sleep(0.01)
            raise CaptureError(f"{self.camera.name}: device disappeared (unplugged, injected)")
        return self.camera.read(timeout_s)

    def read_latest(self):
        return self.read()
