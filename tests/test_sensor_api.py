"""The in-process API (runtime/sensor.py) gives the same contacts and wrench as `tensortouch run` over Zenoh.

Real parts: the shipped demo recording and model (onnxruntime), `tensortouch run` in its own process,
a real Zenoh subscriber on loopback in this one.
"""
import os
import subprocess
import sys
import threading

import numpy as np
import pytest
from tensortouch.contracts import paths
from tensortouch.contracts.errors import CaptureError
from tensortouch.runtime.apps.subscriber import Subscriber
from tensortouch.runtime.sensor import Sensor

from tests.test_e2e_runtime import free_port, stop

FRAMES = 50   # the demo's first contact is at frame 35


def _demo_available() -> bool:
    return (paths.demo_dir() / "session.json").is_file() and (paths.calibration_dir() / "TWIN-DEMO").is_dir()


pytestmark = pytest.mark.skipif(not _demo_available(), reason="shipped demo recording/calibration not present")


def test_api_matches_tensortouch_run_over_zenoh():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got_contacts, got_wrench = {}, {}
    lock = threading.Lock()

    def on_contacts(f):
        with lock:
            got_contacts[f.seq] = f.contacts

    def on_wrench(w):
        with lock:
            got_wrench[w.seq] = w

    with Subscriber("TWIN-DEMO", listen=[endpoint], on_contacts=on_contacts, on_wrench=on_wrench):
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen([sys.executable, "-m", "tensortouch.runtime.shells.cli", "run", "--fast", "--no-fields",
                                 "--frames", str(FRAMES), "--connect", endpoint],
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            proc.wait(timeout=120)
        finally:
            err = stop(proc)
        assert proc.returncode == 0, err
    sensor = Sensor.open(sensor_id="TWIN-DEMO")
    outs = {o.seq: o for o in sensor.stream(f"replay:{paths.demo_dir()}?realtime=0", max_frames=FRAMES)}
    assert len(outs) == FRAMES
    assert len(got_contacts) >= 0.8 * FRAMES, f"only {len(got_contacts)} contact messages arrived"
    with_contacts = 0
    for seq, contacts in got_contacts.items():
        mine = outs[seq].contacts
        assert len(mine) == len(contacts), seq
        for a, b in zip(mine, contacts):
            assert a["id"] == b.id
            np.testing.assert_allclose(a["position_mm"], b.position_mm, atol=1e-3)
            np.testing.assert_allclose(a["force_n"], b.force_n, atol=1e-3)
            np.testing.assert_allclose(a["area_mm2"], b.area_mm2, rtol=1e-3)
        with_contacts += bool(contacts)
    assert with_contacts >= 10, "the compared frames must include pokes"
    for seq, w in got_wrench.items():
        np.testing.assert_allclose(outs[seq].force_n, w.force_n, atol=1e-3)
        np.testing.assert_allclose(outs[seq].torque_nmm, w.torque_nmm, atol=1e-2)
    assert outs[FRAMES].fields is not None and outs[FRAMES].fields.shape[0] == len(sensor.channels)


def test_api_rejects_a_frame_that_is_not_rgb_uint8():
    sensor = Sensor.open(sensor_id="TWIN-DEMO")
    with pytest.raises(CaptureError, match="expected \\(H, W, 3\\) uint8 RGB"):
        sensor.process(np.zeros((240, 320), np.float32), 0.0)
