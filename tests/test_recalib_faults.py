"""Faults during recalibration: gauge unplugged mid-session, garbage on the serial line, power loss
between write and rename (a real SIGKILL of a writer process), disk full (injected ENOSPC). In every
case the previous calibration survives intact and the user gets a clear message. Also: no pickle on
any load path."""
import errno
import hashlib
import os
import pickle
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from tensortouch.contracts.errors import CalibrationError, DeviceNotFoundError, TensorTouchError
from tensortouch.contracts.store import CalibrationStore
from tensortouch.drivers.gauge import ForceGauge, GaugeConfig, format_tt
from tensortouch.runtime.stages.contacts import Cluster
from tensortouch.runtime.stages.correction import ForceCorrection
from tensortouch.tools.recalib.fit import PokeSet, fit_correction
from tensortouch.tools.recalib.session import GaugeReference, SessionConfig, run_guided
from tensortouch.tools.recalib.store_ops import store_recalibration

from tests.conftest import dome_calibration

SENSOR = "TT-FAULT"
ROOT = Path(__file__).resolve().parents[1]


def snapshot(root: Path) -> dict:
    """Every file under the sensor folder → sha256 (CURRENT included; not the writers' lock file)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != ".lock"}


def committed(root: Path) -> dict:
    """Like snapshot, minus leftovers of an interrupted write (.tmp-* folders the store ignores)."""
    return {k: v for k, v in snapshot(root).items() if "/.tmp-" not in k and not k.startswith("versions/.tmp-")}


def a_fit():
    rng = np.random.default_rng(0)
    pred = np.column_stack([np.zeros(6), np.zeros(6), -rng.uniform(0.5, 3, 6)])
    return fit_correction(PokeSet(pred, 1.3 * np.abs(pred[:, 2]), rng.uniform(0.2, 0.8, (6, 2)), np.zeros((6, 2))))


@pytest.fixture
def store(tmp_path):
    dome_calibration(tmp_path / "calib", SENSOR)
    return CalibrationStore(tmp_path / "calib")


# ----- disk full ---------------------------------------------------------------------------------
@pytest.mark.parametrize("where", ["table", "correction_file", "fsync"])
def test_disk_full_injected_enospc_keeps_previous_calibration(store, monkeypatch, where):
    fit = a_fit()
    sensor_dir = store.root / SENSOR
    before = snapshot(sensor_dir)

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    if where == "table":
        monkeypatch.setattr("tensortouch.contracts.store.np.save", full)
    elif where == "correction_file":
        monkeypatch.setattr(Path, "write_bytes", full)
    else:
        monkeypatch.setattr("tensortouch.contracts.store.os.fsync", full)
    with pytest.raises(CalibrationError, match=r"the disk is full .*nothing was changed, the active calibration "
                                               r"is still v0001"):
        store_recalibration(store, store.load(SENSOR), {"pokes": 6}, correction=(fit.spec, fit.onnx_bytes))
    monkeypatch.undo()
    assert snapshot(sensor_dir) == before            # not even a temp folder left behind
    assert store.load(SENSOR).version == "v0001"


# ----- power loss --------------------------------------------------------------------------------
KILLER = textwrap.dedent("""
    import os, signal, sys
    import tensortouch.contracts.store as rc
    from tensortouch.contracts.store import CalibrationStore
    from tensortouch.tools.recalib.store_ops import store_recalibration
    sys.path.insert(0, {root!r})
    from tests.test_recalib_faults import a_fit
    step = sys.argv[2]
    die = lambda *a, **k: os.kill(os.getpid(), signal.SIGKILL)
    if step == "before_rename":
        rc.os.rename = die                        # data + hashes written and fsynced, not yet renamed
    else:
        rc.CalibrationStore._set_current = die    # version folder renamed, CURRENT not yet replaced
    store = CalibrationStore(sys.argv[1])
    fit = a_fit()
    store_recalibration(store, store.load("TT-FAULT"), {{"pokes": 6}}, correction=(fit.spec, fit.onnx_bytes))
    print("not killed")
""")


@pytest.mark.parametrize("step", ["before_rename", "before_current"])
def test_power_loss_sigkill_mid_write_keeps_previous_calibration(store, tmp_path, step):
    sensor_dir = store.root / SENSOR
    before = snapshot(sensor_dir)
    script = tmp_path / "killer.py"
    script.write_text(KILLER.format(root=str(ROOT)))
    proc = subprocess.run([sys.executable, str(script), str(store.root), step], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == -9, proc.stderr[-2000:]
    after = committed(sensor_dir)
    assert store.current(SENSOR) == "v0001"
    assert {k: v for k, v in after.items() if k.startswith(("CURRENT", "versions/v0001"))} == before
    cal = store.load(SENSOR)                          # hashes verified
    assert cal.version == "v0001" and cal.meta.get("correction") is None
    if step == "before_rename":
        assert store.versions(SENSOR) == ["v0001"]
        assert list((sensor_dir / "versions").glob(".tmp-*")), "the interrupted write should leave only a temp folder"
    else:
        assert store.versions(SENSOR) == ["v0001", "v0002"]   # complete but never activated
    # the next recalibration works and becomes active
    fit = a_fit()
    v = store_recalibration(store, cal, {"pokes": 6}, correction=(fit.spec, fit.onnx_bytes))
    assert store.current(SENSOR) == v and store.load(SENSOR).meta["correction"]["output"] == "gain"


# ----- gauge faults in a session --------------------------------------------------------------------
def cl(f, uv, xyz):
    return Cluster(id=-1, uv_px=uv, position_mm=xyz, normal=(0, 0, 1), area_mm2=1.0, force_n=(0.0, 0.0, -f),
                   force_mag_n=f, pixels=5, perimeter_px=8.0, circularity=0.9)


def live_frames(master, store, n_pokes, unplug_after=None, garbage=False, gain=1.3, dt=0.01, gap=40):
    """Frames stamped with time.monotonic() (like a live camera); the 'gauge' (pty master) streams the
    true force = gain × sensor force, optionally with garbage between lines, and can be unplugged."""
    cal = store.load(SENSOR)
    from tests.recalib_util import poke_positions

    uvs, xyz = poke_positions(cal, n_pokes)
    for i in range(n_pokes):
        if unplug_after is not None and i == unplug_after:
            os.close(master)                       # cable pulled
        prof = np.r_[np.linspace(0.2, 2.0, 8), np.full(12, 2.0), np.linspace(2.0, 0.2, 4), np.zeros(gap)]
        for f in prof:
            f = f + 0.1 * i if f > 0 else 0.0
            if unplug_after is None or i < unplug_after:
                os.write(master, (b"#?\x00garbage\r\n" if garbage else b"") + format_tt(gain * f))
            time.sleep(dt)
            yield time.monotonic(), ([cl(f, tuple(uvs[i]), tuple(xyz[i]))] if f > 0 else [])


def test_gauge_garbage_lines_are_skipped_and_pokes_paired(store):
    master, slave = os.openpty()
    gauge = ForceGauge(GaugeConfig(os.ttyname(slave), timeout_s=2.0)).open().start()
    try:
        out = run_guided(live_frames(master, store, 5, garbage=True), store.load(SENSOR), GaugeReference(gauge),
                         SessionConfig(pokes=5), say=lambda m: None)
    finally:
        gauge.close()
        os.close(master)
        os.close(slave)
    assert out.complete and len(out.accepted) == 5
    for p in out.accepted:
        assert p.ref_force_n / p.pred_mag == pytest.approx(1.3, rel=0.03)
    assert gauge.garbage == 0   # garbage lines were counted and skipped; every valid line resets the count


def test_gauge_unplugged_mid_session_aborts_clearly_and_stores_nothing(store):
    master, slave = os.openpty()
    gauge = ForceGauge(GaugeConfig(os.ttyname(slave), timeout_s=2.0)).open().start()
    before = snapshot(store.root / SENSOR)
    said = []
    try:
        with pytest.raises(DeviceNotFoundError, match="disconnected"):
            run_guided(live_frames(master, store, 6, unplug_after=2), store.load(SENSOR), GaugeReference(gauge),
                       SessionConfig(pokes=6), say=said.append)
    finally:
        gauge.close()
        os.close(slave)
    assert sum("accepted" in m for m in said) == 2
    assert snapshot(store.root / SENSOR) == before


def test_cli_gauge_unplugged_message_names_active_version(tmp_path):
    """Through `tensortouch recalibrate --gauge serial:<pty>`: the error says nothing was stored."""
    from tensortouch.tools.recalib import cli

    from tests.recalib_util import SENSOR as S
    from tests.recalib_util import setup_env, write_recording
    from tests.test_recalib_cli import parse

    package, store = setup_env(tmp_path)
    session, _, _ = write_recording(tmp_path / "session", package, store, n_pokes=5)
    master, slave = os.openpty()

    def gauge_then_unplug():
        for _k in range(30):
            os.write(master, format_tt(1.0))
            time.sleep(0.005)
        os.close(master)

    th = threading.Thread(target=gauge_then_unplug)
    th.start()
    before = snapshot(store.root / S)
    args = parse(["recalibrate", "--sensor", S, "--source", f"replay:{session}?realtime=1", "--store", str(store.root),
                  "--model", str(package.folder), "--precision", "fp32", "--gauge", f"serial:{os.ttyname(slave)}"])
    try:
        with pytest.raises(TensorTouchError, match=r"disconnected.*\nsession aborted: nothing was stored, the active "
                                                   r"calibration is still v0001"):
            cli.cmd_recalibrate(args, say=lambda m: None)
    finally:
        th.join()
        os.close(slave)
    assert snapshot(store.root / S) == before


# ----- no pickle ---------------------------------------------------------------------------------------
def test_no_pickle_on_any_load_path(store, monkeypatch):
    fit = a_fit()
    store_recalibration(store, store.load(SENSOR), {"pokes": 6}, correction=(fit.spec, fit.onnx_bytes))

    def forbidden(*a, **k):
        raise AssertionError("pickle used on a load path")

    for name in ("load", "loads", "Unpickler"):
        monkeypatch.setattr(pickle, name, forbidden)
    cal = store.load(SENSOR)
    corr = ForceCorrection.from_calibration(cal)
    out = corr(np.array([[0.0, 0.0, -1.0]]), np.array([[0.5, 0.5]]), np.zeros((1, 2)))
    assert out[0, 2] == pytest.approx(-1.3, rel=0.05)
    monkeypatch.undo()
    # a pickled object array smuggled in as a table (hash updated too) is refused by allow_pickle=False
    folder = cal.folder
    np.save(folder / "theta.npy", np.array([{"evil": 1}] * 4, dtype=object), allow_pickle=True)
    import json
    meta = json.loads((folder / "calibration.json").read_text())
    meta["files"]["theta.npy"] = hashlib.sha256((folder / "theta.npy").read_bytes()).hexdigest()
    (folder / "calibration.json").write_text(json.dumps(meta))
    with pytest.raises(CalibrationError, match="cannot load table 'theta'"):
        store.load(SENSOR)
    # and the recalibration code itself never imports pickle/joblib
    for path in list((ROOT / "tools" / "recalib").glob("*.py")) + [ROOT / "drivers" / "gauge.py"]:
        text = path.read_text()
        assert "import pickle" not in text and "joblib" not in text, path


def test_cli_silent_gauge_on_loop_url_times_out_clearly(tmp_path):
    """`--gauge loop://` with nothing talking: 'not responding' after the gauge timeout, nothing stored."""
    from tensortouch.tools.recalib import cli

    from tests.recalib_util import SENSOR as S
    from tests.recalib_util import setup_env, write_recording
    from tests.test_recalib_cli import parse

    package, store = setup_env(tmp_path)
    session, _, _ = write_recording(tmp_path / "session", package, store, n_pokes=5)
    before = snapshot(store.root / S)
    args = parse(["recalibrate", "--sensor", S, "--source", f"replay:{session}", "--store", str(store.root),
                  "--model", str(package.folder), "--precision", "fp32", "--gauge", "loop://"])
    with pytest.raises(TensorTouchError, match=r"force gauge loop://: no valid reading for 2.0 s \(not responding"):
        cli.cmd_recalibrate(args, say=lambda m: None)
    assert snapshot(store.root / S) == before
