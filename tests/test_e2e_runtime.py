"""End to end: `tensortouch run` on a replayed recording → a separate `tensortouch listen` process.

Real parts only: OpenCV capture of an MJPG recording, onnxruntime on a test network built here
(a deterministic difference network, never committed), real Zenoh sessions on loopback in two
separate processes.
"""
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from tensortouch.contracts.session import STREAM_COLUMNS, new_manifest, write_manifest, write_table
from tensortouch.tools.bench.models import write_difference_package

from tests.conftest import dome_calibration

W, H, SIZE, SENSOR = 160, 120, 32, "TT-E2E"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_poke_session(folder: Path, n: int = 90, fps: float = 30.0) -> Path:
    """Rest frames, then a blob pressing at the right of the gel, then release."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:H, 0:W]
    rest = np.zeros((H, W, 3), np.float32)
    rest[...] = (110, 120, 130)
    rest[(xx - W / 2) ** 2 + (yy - H / 2) ** 2 > 50 ** 2] = 0
    vw = cv2.VideoWriter(str(folder / "frames.avi"), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    for k in range(n):
        img = rest.copy()
        if 30 <= k < 70:
            blob = np.exp(-((xx - (W / 2 + 25)) ** 2 + (yy - H / 2) ** 2) / (2 * 6.0 ** 2))
            img += 90 * blob[..., None]
        img += rng.normal(0, 0.8, img.shape)
        vw.write(cv2.cvtColor(np.clip(img, 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
    vw.release()
    t = np.arange(n) / fps
    write_table(folder / "frames.csv", STREAM_COLUMNS["frames"], np.stack([t, np.arange(n)], 1))
    write_manifest(folder, new_manifest(SENSOR, {"frames": {"file": "frames.csv", "video": "frames.avi"}},
                                        provenance={"source": "test_e2e_runtime synthetic poke"}))
    return folder


def run_and_listen(tmp_path, session, run_extra: list, listen_extra: list):
    """`tensortouch run` (looping replay of `session`, models/calibration under tmp_path) in one process,
    `tensortouch listen SENSOR` in another on loopback; returns (listener CompletedProcess, run stderr)."""
    env = dict(os.environ, TENSORTOUCH_CALIBRATION=str(tmp_path / "calib"),
               TENSORTOUCH_MODELS=str(tmp_path / "models"), PYTHONUNBUFFERED="1")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cli = [sys.executable, "-m", "tensortouch.runtime.shells.cli"]
    runtime = subprocess.Popen(cli + ["run", "--source", f"replay:{session}", "--listen", endpoint, "--loop"] + run_extra,
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(1.0)
        listener = subprocess.run(cli + ["listen", SENSOR, "--connect", endpoint] + listen_extra,
                                  env=env, capture_output=True, text=True, timeout=90)
    finally:
        err = stop(runtime)
    return listener, err


def stop(proc: subprocess.Popen) -> str:
    """Terminate a `tensortouch run` process (kill if it does not exit) and return its stderr."""
    proc.terminate()
    try:
        _, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    return err


def test_run_to_separate_listener_process(tmp_path):
    session = write_poke_session(tmp_path / "session")
    write_difference_package(tmp_path / "models" / "difference-32", SIZE)
    dome_calibration(tmp_path / "calib", SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    out = tmp_path / "saved"
    listener, err = run_and_listen(tmp_path, session, [], ["--count", "150", "--json", "--save", str(out)])
    assert listener.returncode == 0, listener.stderr
    msgs = [json.loads(line) for line in listener.stdout.splitlines() if line.startswith("{")]
    kinds = {m.get("kind") for m in msgs}
    assert {"fields", "contacts", "status"} <= kinds, (kinds, listener.stdout[-2000:], err[-2000:])
    for m in msgs:
        assert m.get("sensor_id") == SENSOR
    fields = [m for m in msgs if m["kind"] == "fields"]
    assert fields[0]["shape"] == [15, SIZE, SIZE]
    status = [m for m in msgs if m["kind"] == "status"][-1]
    assert "inference" in json.dumps(status)
    # the poke is at the right of the gel: the strongest contact is right of centre and pushes in
    contacts = [c for m in msgs if m["kind"] == "contacts" for c in m["contacts"]]
    assert contacts, "no contact published during the poke"
    strongest = max(contacts, key=lambda c: c["force_mag_n"])
    assert strongest["position_mm"][0] > 3.0 and abs(strongest["position_mm"][1]) < 3.0
    assert strongest["force_n"][2] < 0 and strongest["force_mag_n"] > 0.05
    saved = list(out.glob("**/*.npy"))
    assert saved and np.load(saved[0]).shape == (15, SIZE, SIZE)


def test_run_without_model_says_how_to_build_one(tmp_path):
    env = dict(os.environ, TENSORTOUCH_MODELS=str(tmp_path / "none"))
    r = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", "run"], env=env, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2
    assert "no trained model is installed" in r.stderr and "tensortouch train all" in r.stderr
    assert "Traceback" not in r.stderr
