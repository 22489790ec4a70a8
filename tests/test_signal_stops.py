"""Signal stops, as an operator or a service manager sends them, to real subprocesses: `tensortouch hand`
stops cleanly (rc 0) on SIGTERM and SIGINT, also during start-up; `tensortouch run` and `hand` honour
SIGTERM while a replay waits across a recorded time gap. Real Zenoh (loopback), onnxruntime, OpenCV."""
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.hand_util import (
    free_endpoint,
    make_package,
    make_store,
    poke_frames,
    write_frames,
)

ROOT = Path(__file__).resolve().parents[1]
SERIALS = ("TT-A", "TT-B")


def gap_session(folder: Path, sensor_id: str, gap_s: float = 300.0) -> Path:
    """60 frames at 30 fps, then one frame `gap_s` later: a recording paused for minutes."""
    from tensortouch.contracts.session import (
        STREAM_COLUMNS,
        new_manifest,
        write_manifest,
        write_table,
    )

    frames = poke_frames(61)
    folder.mkdir(parents=True)
    write_frames(frames, folder / "frames.avi")
    t = np.arange(61) / 30.0
    t[-1] = t[-2] + gap_s
    write_table(folder / "frames.csv", STREAM_COLUMNS["frames"], np.stack([t, np.arange(61)], 1))
    write_manifest(folder, new_manifest(sensor_id, {"frames": {"file": "frames.csv", "video": "frames.avi"}},
                                        provenance={"source": "tests/test_signal_stops.py"}))
    return folder


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("signals")
    pkg = make_package(tmp / "models" / "difference-32")
    make_store(tmp / "calib", SERIALS)
    sessions = {s: gap_session(tmp / f"session-{s}", s) for s in SERIALS}
    toml = tmp / "hand.toml"
    fingers = "".join(f'[[finger]]\nname = "f{i}"\nserial = "{s}"\nsource = "replay:{sessions[s]}"\n'
                      for i, s in enumerate(SERIALS))
    toml.write_text(f'[hand]\nname = "sig"\nmodel = "{pkg}"\ncalibration_store = "{tmp / "calib"}"\n'
                    f'[zenoh]\nlisten = ["{free_endpoint()}"]\n{fingers}')
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TENSORTOUCH_MODELS": str(tmp / "models"),
           "TENSORTOUCH_CALIBRATION": str(tmp / "calib")}
    return tmp, pkg, sessions, toml, env


class Proc:
    """A `tensortouch` subprocess whose stderr is read line by line (time-stamped) in a thread."""

    def __init__(self, argv, env):
        self.p = subprocess.Popen([sys.executable, "-m", "tensortouch.runtime.shells.cli", *argv], stderr=subprocess.PIPE,
                                  stdout=subprocess.DEVNULL, text=True, env=env, cwd=ROOT)
        self.lines: list[tuple[float, str]] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self):
        for line in self.p.stderr:
            self.lines.append((time.monotonic(), line))

    def wait_for(self, text, timeout=60.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.p.poll() is None:
            if any(text in line for _, line in self.lines):
                return True
            time.sleep(0.05)
        return any(text in line for _, line in self.lines)

    @property
    def err(self):
        return "".join(line for _, line in self.lines)

    def stop(self, sig, timeout=20.0):
        t0 = time.monotonic()
        self.p.send_signal(sig)
        try:
            self.p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.p.kill()
            self.p.wait()
            self.reader.join(5)
            pytest.fail(f"no exit {timeout} s after {sig!r}: {self.err[-1500:]}")
        took = time.monotonic() - t0
        self.reader.join(5)
        return self.p.returncode, took


def _stops(rig, n, delays, marker=None):
    """n hand runs, each stopped by SIGTERM / SIGINT (alternating) `delays[i]` s after start, or after
    `marker` appeared on stderr when given."""
    _, _, _, toml, env = rig
    results = []
    for i in range(n):
        proc = Proc(["hand", str(toml), "--listen", free_endpoint()], env)
        if marker:
            assert proc.wait_for(marker), proc.err[-2000:]
        time.sleep(delays[i % len(delays)])
        sig = signal.SIGTERM if i % 2 == 0 else signal.SIGINT
        started = any("tensortouch hand" in line or "INFO" in line for _, line in proc.lines)
        rc, took = proc.stop(sig)
        results.append((rc, took))
        assert "FATAL" not in proc.err and rc not in (-6, 134, 1), (i, rc, proc.err[-3000:])
        if started or rc == 0:       # the command was running: a clean stop, nothing else
            assert rc == 0 and "Traceback" not in proc.err, (i, rc, proc.err[-3000:])
        else:                        # still in Python's own start-up: the signal's default (docs/runtime.md)
            assert rc == -sig, (i, rc, proc.err[-3000:])
    return results


def test_hand_stops_cleanly_on_sigterm_and_sigint_in_the_replay_gap(rig):
    """One SIGTERM and one SIGINT while both fingers wait 300 s for their next recorded frame."""
    results = _stops(rig, 2, [3.0], marker="Ctrl-C to stop")      # 60 frames take 2 s, then the gap
    assert all(took < 5 for _, took in results), results


@pytest.mark.slow
def test_hand_12_stops_at_any_moment_all_rc_0(rig):
    """Signals during start-up (model load, session open), while running and in the recorded gap."""
    results = _stops(rig, 12, [0.3, 1.0, 2.0, 3.5, 6.0])
    assert all(took < 20 for _, took in results), results          # start-up finishes, then the stop


def test_run_honours_sigterm_while_the_replay_waits_across_a_gap(rig):
    _, _, sessions, _, env = rig
    proc = Proc(["run", "--source", f"replay:{sessions['TT-A']}", "--listen", free_endpoint()], env)
    assert proc.wait_for("Ctrl-C to stop"), proc.err[-2000:]
    time.sleep(3.0)                           # the 60 frames are replayed in 2 s; then a 300 s gap
    assert proc.p.poll() is None
    rc, took = proc.stop(signal.SIGTERM)
    assert rc == 0 and took < 5, (rc, took, proc.err[-2000:])
    assert "Traceback" not in proc.err and "tensortouch run: 60 frames" in proc.err, proc.err[-2000:]
