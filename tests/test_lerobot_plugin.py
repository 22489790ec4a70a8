"""The LeRobot plugin distribution (integrations/lerobot) against a running `tensortouch run` on the demo.

Real parts: LeRobot 0.4.4's own plugin discovery and `make_cameras_from_configs`, `tensortouch run`
in its own process, Zenoh on loopback. Needs the plugin and LeRobot installed in the test venv
(.ci/run does: `pip install --no-deps lerobot==0.4.4 ./integrations/lerobot` plus draccus==0.10.0).
"""
import importlib.metadata
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from tensortouch.contracts import paths
from tensortouch.runtime.apps.subscriber import Subscriber
from tests.test_e2e_runtime import free_port, stop


def _missing() -> str | None:
    try:
        importlib.metadata.distribution("lerobot_camera_tensortouch")
        import lerobot.cameras  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - the reason is shown in the skip message
        return f"{type(exc).__name__}: {exc} (pip install --no-deps lerobot==0.4.4 ./integrations/lerobot draccus==0.10.0)"
    if not (paths.demo_dir() / "session.json").is_file():
        return "no demo recording"
    return None


pytestmark = pytest.mark.skipif(_missing() is not None, reason=str(_missing()))


@pytest.fixture(scope="module")
def runtime_endpoint():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "tensortouch.runtime.shells.cli", "run", "--loop", "--listen", endpoint],
                            env=dict(os.environ, PYTHONUNBUFFERED="1"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    yield endpoint, proc
    stop(proc)


def test_lerobot_factory_builds_the_camera_and_reads_fields(runtime_endpoint):
    from lerobot.cameras.utils import make_cameras_from_configs
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()                      # imports lerobot_camera_tensortouch (by its dist name)
    from lerobot_camera_tensortouch import (
        TensorTouchCamera,
        TensorTouchCameraConfig,
        from_image,
    )

    endpoint, _ = runtime_endpoint
    cfg = TensorTouchCameraConfig(sensor_id="TWIN-DEMO", connect=endpoint, timeout_ms=15000,
                                  channels=("disp_x", "disp_y", "disp_z"))
    assert cfg.type == "tensortouch"
    cams = make_cameras_from_configs({"gel": cfg})
    cam = cams["gel"]
    assert isinstance(cam, TensorTouchCamera)
    fields = {}
    lock = threading.Lock()

    def keep(f):
        with lock:
            fields[f.seq] = f.data[0:3].copy()

    with Subscriber("TWIN-DEMO", connect=[endpoint], on_fields=keep):
        cam.connect()
        try:
            assert cam.is_connected and (cam.height, cam.width) == (128, 128)
            img = cam.read()
            assert img.shape == (128, 128, 3) and img.dtype == np.uint8
            seen, t0 = set(), time.perf_counter()
            for _ in range(20):
                img = cam.async_read(timeout_ms=2000)
                seen.add(cam.last_read_seq)
            rate = 20 / (time.perf_counter() - t0)
            assert len(seen) == 20, seen                       # each async_read returns a new frame
            compared = 0
            for _ in range(10):
                img, seq = cam.async_read(timeout_ms=2000), cam.last_read_seq
                time.sleep(0.1)
                with lock:
                    ref = fields.get(seq)
                if ref is None:
                    continue                                   # the plain subscriber missed this one
                # fixed full scale 2.5 mm: pixel steps of 2.5/127 mm; half a step of rounding
                assert np.abs(from_image(img, cfg.channels) - ref).max() <= 2.5 / 127 * 0.51 + 1e-3
                compared += 1
            assert compared >= 5, compared
            assert cam.read_latest(max_age_ms=500).shape == (128, 128, 3)
            print(f"LeRobot camera: {rate:.1f} frames/s via async_read")
        finally:
            cam.disconnect()
    assert not cam.is_connected


def test_tactile_floats_wrench_and_top_contacts(runtime_endpoint):
    from lerobot_camera_tensortouch import (
        TensorTouchTactile,
        TensorTouchTactileConfig,
        feature_names,
    )

    endpoint, proc = runtime_endpoint
    tac = TensorTouchTactile(TensorTouchTactileConfig(sensor_id="TWIN-DEMO", connect=endpoint, top_k=8,
                                                      timeout_ms=15000))
    tac.connect()
    try:
        names = feature_names("tactile", 8)
        assert list(tac.features) == names and len(names) == 6 + 8 * 8
        pressed = None
        deadline = time.monotonic() + 20
        while pressed is None and time.monotonic() < deadline:
            s = tac.async_read(timeout_ms=2000)
            assert list(s) == names and all(isinstance(v, float) for v in s.values())
            if s["tactile.c0.present"] == 1.0:
                pressed = s
        assert pressed is not None, "no contact in 20 s of the looping demo"
        n = int(sum(pressed[f"tactile.c{i}.present"] for i in range(8)))
        # the wrench is the sum of the contacts' forces (all of them fit in top_k = 8 here)
        total = sum(pressed[f"tactile.c{i}.fz"] for i in range(n))
        assert abs(total - pressed["tactile.fz"]) < 1e-3 * max(1.0, abs(total))
        mags = [np.linalg.norm([pressed[f"tactile.c{i}.f{a}"] for a in "xyz"]) for i in range(n)]
        assert mags == sorted(mags, reverse=True)
        assert tac.read_latest(max_age_ms=500)["tactile.fz"] == tac.read_latest(max_age_ms=500)["tactile.fz"]
        # staleness: stop the runtime; the latest state ages and async_read times out
        stop(proc)
        time.sleep(0.6)
        with pytest.raises(TimeoutError, match="old"):
            tac.read_latest(max_age_ms=300)
        try:
            tac.async_read(timeout_ms=100)           # at most one state arrived after the last read
        except TimeoutError:
            pass
        with pytest.raises(TimeoutError, match="no new state"):
            tac.async_read(timeout_ms=100)
    finally:
        tac.disconnect()
