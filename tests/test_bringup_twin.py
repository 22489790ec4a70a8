"""A new sensor's first hour on the twin: a unit the calibration store does not know, as if it were a
new camera. The unit is poked where a recalibration guides (twin_bench's guided presses);
`calib init` (gel rim + nominal θ/φ) → `record` (the camera = a replay of the unit's twin
recording, the force gauge and the mocap = TCP line streams replaying its wrench and poses on the
wall clock) → `recalibrate` (the force correction from the recorded pokes; the GPR geometry step is measured
against the unit's truth and rolled back) → `run`
(a separate process, contacts read by a real Zenoh subscriber on loopback).

Real parts throughout: the twin renderer (7 guided presses, hertz-fallback physics: no FE), OpenCV, pyserial socket://,
the shipped int8 model in onnxruntime, the calibration store, Zenoh. About 5 minutes: slow.
"""
import argparse
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from tensortouch.contracts.session import load_session, read_table
from tensortouch.contracts.store import CalibrationStore
from tensortouch.drivers.gauge import format_tt
from tensortouch.drivers.mocap import format_pose
from tensortouch.runtime.apps.subscriber import Subscriber
from tensortouch.runtime.shells import commands

from tests.test_e2e_runtime import free_port, stop
from tests.test_record import LineServer

pytestmark = pytest.mark.slow
UNIT = "TWIN-BRINGUP-7"


def parse(argv):
    from tensortouch.tools.recalib import cli as recal_cli
    from tensortouch.tools.sessions import cli as sess_cli

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    commands.register(sub)
    sess_cli.register(sub)
    recal_cli.register(sub)
    return parser.parse_args(argv)


class Timed:
    """Lines due at recording times `t` (s), sent on the wall clock from the client's connection on."""

    def __init__(self, t, lines):
        self.t, self.lines, self.k, self.start = np.asarray(t), lines, 0, None

    def __call__(self, _):
        if self.start is None:
            self.start = time.monotonic()
        now = time.monotonic() - self.start
        out = []
        while self.k < len(self.t) and self.t[self.k] <= now:
            out.append(self.lines[self.k])
            self.k += 1
        return b"".join(out)


def feeds(twin_dir):
    """Gauge lines (|F| of the pressing indenter, 200 Hz) and mocap lines (the touching indenter's tip
    pose, as indenter 0) from the twin recording."""
    s = load_session(twin_dir)
    w = s.table("wrench")
    tw = np.unique(w[:, 0])
    mags = np.array([np.linalg.norm(w[w[:, 0] == t][:, 2:5], axis=1).max() for t in tw])
    gauge = Timed(tw, [format_tt(m) for m in mags])
    p = s.table("poses")
    touch = read_table(twin_dir / "truth" / "contact.csv", ["t", "indenter", "depth", "x", "y", "z", "area", "touching"])
    touch = touch[touch[:, 7] > 0]
    rows = []
    for t in np.unique(p[:, 0]):
        near = touch[np.abs(touch[:, 0] - t) < 0.02]
        if len(near):
            ind = near[0, 1]
            r = p[(p[:, 0] == t) & (p[:, 1] == ind)][0]
            rows.append((t, format_pose(0, r[2:5], r[5:9])))
    mocap = Timed([r[0] for r in rows], [r[1] for r in rows])
    return gauge, mocap


def record_twin(out):
    """The unit poked where a recalibration session guides (7 single-probe presses at the spots the
    shipped nominal geometry suggests), rendered with hertz-fallback physics (no FE)."""
    from tensortouch.tools.recalib.twin_bench import (
        TwinBenchConfig,
        guided_points,
        nominal_calibration,
        record_once,
    )
    from tensortouch.tools.twin.record import RecordConfig
    from tensortouch.tools.twin.trajectory import GuidedConfig

    bench = TwinBenchConfig()
    tables, _ = nominal_calibration(128)
    points = guided_points(tables, 7, np.radians(bench.reach_deg))
    cfg = RecordConfig(serial=UNIT, pokes=7, seed=1, physics="hertz-fallback", model_size=128, frame_format="mjpg",
                       guided=GuidedConfig(points, list(bench.fit_depths_mm), bench.probe, seed=1))
    return record_once(cfg, out, say=print)


def test_new_twin_unit_first_hour(tmp_path):
    twin = record_twin(tmp_path / "twin")
    store = CalibrationStore(tmp_path / "store")
    assert UNIT not in store.sensors()

    # 1. calib init: the rim and a nominal lens model
    args = parse(["calib", "init", "--source", f"replay:{twin}?realtime=0", "--sensor", UNIT, "--store", str(store.root)])
    assert args.func(args) == 0
    v1 = store.load(UNIT)
    assert v1.version == "v0001" and v1.meta["provenance"]["method"] == "nominal-lens"
    from tensortouch.tools.twin.unit import TwinUnit, true_tables

    unit = TwinUnit(UNIT)
    assert np.hypot(*np.subtract(v1.gel_center_px, unit.gel_center_px)) < 0.5
    assert abs(v1.gel_radius_px / unit.gel_radius_px - 1) < 0.01
    truth = true_tables(unit, v1.model_size[0])
    both = v1.mask & truth["mask"]
    err1 = np.degrees(np.abs(v1.theta - truth["theta"])[both])
    assert both.sum() > 0.7 * truth["mask"].sum() and err1.mean() < 1.0, err1.mean()

    # 2. record: camera = paced replay of the twin recording, gauge + mocap over TCP
    gauge_lines, mocap_lines = feeds(twin)
    gauge, mocap = LineServer(gauge_lines, 0.002), LineServer(mocap_lines, 0.004)
    rec = tmp_path / "rec"
    try:
        args = parse(["record", "--source", f"replay:{twin}", "--sensor", UNIT, "--out", str(rec),
                      "--ft", gauge.url, "--mocap", mocap.url])
        assert args.func(args) == 0
    finally:
        gauge.close()
        mocap.close()
    s = load_session(rec)
    assert {"frames", "wrench", "poses"} <= set(s.streams)
    assert s.table("wrench")[:, 4].max() > 0.5

    # 3. recalibrate: the force correction from the recorded pokes (the gauge stream)
    base = ["recalibrate", "--sensor", UNIT, "--source", f"replay:{rec}", "--store", str(store.root),
            "--gauge", "session", "--pokes", "7"]
    lines = []
    args = parse(base + ["--report", str(tmp_path / "r.json")])
    assert args.func(args, say=lines.append) == 0, "\n".join(lines)
    v2 = store.load(UNIT)
    assert v2.version == "v0002" and v2.meta["correction"] is not None
    assert np.array_equal(v2.theta, v1.theta)

    # 3b. the GPR geometry step from the mocap poses, measured against the unit's truth where the pokes
    # were (the guided spots reach 31.5° from the apex) and over the whole gel; kept only for the numbers
    lines = []
    args = parse(base + ["--geometry", "--force"])
    assert args.func(args, say=lines.append) == 0, "\n".join(lines)
    v3 = store.load(UNIT)
    reach = truth["theta"] <= np.radians(31.5)
    rows = {}
    for name, cal in (("nominal", v1), ("--geometry", v3)):
        m = cal.mask & truth["mask"]
        e = np.degrees(np.abs(cal.theta - truth["theta"]))
        rows[name] = (float(e[m & reach].mean()), float(e[m].mean()))
        print(f"θ error vs the unit's truth, {name}: {rows[name][0]:.2f}° mean within the poked reach, "
              f"{rows[name][1]:.2f}° over the gel")
    assert rows["nominal"][0] < 0.2 and rows["--geometry"][0] < 5.0, rows
    args = parse(["calib", "rollback", UNIT, "--to", "v0002", "--store", str(store.root)])
    assert args.func(args) == 0 and store.current(UNIT) == "v0002"

    # 4. run it: contacts over Zenoh from the recorded session with the new calibration
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got, status = [], []
    with Subscriber(UNIT, listen=[endpoint], on_contacts=got.append, on_status=status.append):
        proc = subprocess.Popen([sys.executable, "-m", "tensortouch.runtime.shells.cli", "run", "--source", f"replay:{rec}", "--sensor", UNIT,
                                 "--fast", "--no-fields", "--connect", endpoint],
                                env=dict(os.environ, TENSORTOUCH_CALIBRATION=str(store.root)),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            proc.wait(timeout=300)
        finally:
            err = stop(proc)
        time.sleep(0.5)
    assert proc.returncode == 0, err
    assert status and status[-1]["calibration_version"] == "v0002"
    pressed = [f for f in got if f.contacts]
    assert len(pressed) > 50, len(pressed)
    peak = max(sum(c.force_mag_n for c in f.contacts) for f in pressed)
    assert 0.3 * s.table("wrench")[:, 4].max() < peak < 3 * s.table("wrench")[:, 4].max()
