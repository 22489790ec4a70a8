"""`tensortouch record`: frames from the camera layer, a force gauge and a mocap stream into a session.

Real parts: the replay camera on the shipped demo (OpenCV), pyserial `socket://` clients to TCP
servers in this test that speak the gauge and mocap line protocols, the session writer and validator.
"""
import argparse
import socket
import threading
import time

import numpy as np
import pytest
from tensortouch.contracts import paths
from tensortouch.contracts.errors import SessionError
from tensortouch.contracts.session import load_session
from tensortouch.drivers.camera import camera_from_uri
from tensortouch.drivers.gauge import format_tt
from tensortouch.drivers.mocap import format_pose, parse_pose
from tensortouch.tools.sessions import cli

pytestmark = pytest.mark.skipif(not (paths.demo_dir() / "session.json").is_file(), reason="no demo recording")


class LineServer:
    """A TCP server on loopback that sends `line(k)` every `period_s` to the one client it accepts."""

    def __init__(self, line, period_s=0.005):
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.sock.getsockname()[1]}"
        self.line, self.period_s = line, period_s
        self.stop = threading.Event()
        self.sent = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        self.sock.settimeout(10)
        try:
            conn, _ = self.sock.accept()
        except OSError:
            return
        with conn:
            k = 0
            while not self.stop.is_set():
                data = self.line(k)
                try:
                    conn.sendall(data)
                except OSError:
                    return
                self.sent.append(data)
                k += 1
                time.sleep(self.period_s)

    def close(self):
        self.stop.set()
        self.thread.join(timeout=5)
        self.sock.close()


def parse(argv):
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


def test_record_frames_gauge_and_mocap_into_a_valid_session(tmp_path):
    gauge = LineServer(lambda k: format_tt(0.01 * (k % 100)))
    mocap = LineServer(lambda k: format_pose(0, (0.1 * k, -1.0, 14.0), (1, 0, 0, 0)), period_s=0.01)
    out = tmp_path / "rec"
    try:
        args = parse(["record", "--source", f"replay:{paths.demo_dir()}", "--sensor", "NEW-UNIT", "--out", str(out),
                      "--frames", "20", "--ft", gauge.url, "--mocap", mocap.url, "--format", "ffv1"])
        assert args.func(args) == 0
    finally:
        gauge.close()
        mocap.close()
    s = load_session(out)
    assert s.sensor_id == "NEW-UNIT" and s.streams["frames"]["lossless"]
    frames, wrench, poses = s.table("frames"), s.table("wrench"), s.table("poses")
    assert len(frames) == 20 and frames[0, 0] == 0.0
    # paced replay at 30 fps: the recorded clock follows the arrivals
    assert 0.5 < frames[-1, 0] < 1.5, frames[-1, 0]
    # the gauge sends every 5 ms, the mocap every 10 ms during the ~0.63 s recording
    assert len(wrench) > 40 and len(poses) > 20, (len(wrench), len(poses))
    sent_forces = {round(0.01 * k, 4) for k in range(100)}
    assert set(np.round(wrench[:, 4], 4)) <= sent_forces
    assert np.all(wrench[:, [2, 3, 5, 6, 7]] == 0)
    sent_x = [parse_pose(line)[1][0] for line in mocap.sent]
    assert set(np.round(poses[:, 2], 3)) <= set(np.round(sent_x, 3))
    assert np.all(poses[:, 5] == 1.0)
    assert np.all(wrench[:, 0] >= 0) and np.all(np.diff(wrench[:, 0]) > 0) and wrench[-1, 0] <= frames[-1, 0] + 0.05
    # lossless: the replayed recording gives the source's frames bit for bit
    with camera_from_uri(f"replay:{paths.demo_dir()}?realtime=0") as src, \
            camera_from_uri(f"replay:{out}?realtime=0") as rec:
        for _ in range(20):
            np.testing.assert_array_equal(src.read().image, rec.read().image)


def test_record_refuses_an_existing_session_and_needs_a_sensor_id(tmp_path):
    args = parse(["record", "--source", f"replay:{paths.demo_dir()}", "--out", str(paths.demo_dir())])
    from tensortouch.contracts.errors import TensorTouchError

    with pytest.raises(TensorTouchError, match="--sensor is required"):
        args.func(args)
    args = parse(["record", "--source", f"replay:{paths.demo_dir()}", "--sensor", "X", "--out",
                  str(paths.demo_dir()), "--frames", "1"])
    with pytest.raises(SessionError, match="already holds a session"):
        args.func(args)
