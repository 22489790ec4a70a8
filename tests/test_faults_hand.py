"""Fault injection on a running hand (DESIGN §9): each fault must leave the healthy sensors
publishing, with a status flag on the sick one, or stop with a clear message; nothing stored is
lost or half-written. Real Zenoh on loopback (in-process and separate processes), real OpenCV
replays, python-can virtual bus, real onnxruntime. The unplug is injected around a real replay
camera (no USB hardware here): see tests/hand_util.FlakyCamera.
"""
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from collections import Counter, defaultdict

import numpy as np
import pytest
from tensortouch.contracts.errors import ModelPackageError
from tensortouch.runtime.apps.hand import Hand
from tensortouch.runtime.apps.subscriber import Subscriber, alive_sensors, query_info

from tests.hand_util import (
    FlakyCamera,
    Plug,
    free_endpoint,
    hand_cfg,
    make_package,
    make_session,
    make_store,
    make_video,
    poke_frames,
    wait_until,
    write_frames,
)

SERIALS = ("TT-A", "TT-B", "TT-C")
SICK = "TT-B"
HEALTHY = ("TT-A", "TT-C")


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("faults")
    pkg = make_package(tmp / "models" / "difference-32")
    make_store(tmp / "store", SERIALS)
    videos = {s: make_video(tmp / f"{s}.avi", seed=i) for i, s in enumerate(SERIALS)}
    return tmp, pkg, videos


class Collector:
    """Counts what a real Zenoh subscriber receives, per sensor; remembers every status flag seen."""

    def __init__(self):
        self.lock = threading.Lock()
        self.counts = defaultdict(Counter)
        self.status = {}
        self.flags_seen = defaultdict(set)

    def on(self, kind):
        def cb(msg):
            sid = msg["sensor_id"] if isinstance(msg, dict) else msg.sensor_id
            with self.lock:
                self.counts[sid][kind] += 1
                if kind == "status":
                    self.status[sid] = msg
                    self.flags_seen[sid] |= set(msg["flags"])
        return cb

    def subscriber(self, endpoints):
        return Subscriber("*", connect=list(endpoints), on_contacts=self.on("contacts"),
                          on_status=self.on("status"), on_fields=self.on("fields"))

    def n(self, sid, kind="contacts"):
        with self.lock:
            return self.counts[sid][kind]

    def flags(self, sid):
        with self.lock:
            return set(self.status.get(sid, {}).get("flags", ()))


def snapshot(col, sids, kind="contacts"):
    return {s: col.n(s, kind) for s in sids}


def assert_kept_publishing(col, before, sids=HEALTHY, kind="contacts", min_new=10, timeout=10.0):
    assert wait_until(lambda: all(col.n(s, kind) - before[s] >= min_new for s in sids), timeout), \
        {s: col.n(s, kind) - before[s] for s in sids}


def running_hand(cfg, col, **kw):
    hand = Hand(cfg, **kw).start()
    sub = col.subscriber(cfg.listen)
    assert wait_until(lambda: all(col.n(s) > 5 for s in cfg_serials(cfg)), 20), dict(col.counts)
    return hand, sub


def cfg_serials(cfg):
    return [f.serial for f in cfg.fingers]


def _factory(hand_cfg_obj, overrides):
    from tensortouch.drivers.camera import camera_from_uri

    def make(f):
        if f.serial in overrides:
            return overrides[f.serial](f)
        return camera_from_uri(f.source_uri, **hand_cfg_obj.camera_options)
    return make


# ------------------------------------------------------------------------------------- camera faults

def test_camera_unplugged_and_replugged_injected_around_real_replay(rig):
    from tensortouch.drivers.camera import camera_from_uri

    tmp, pkg, videos = rig
    cfg = hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS}, max_camera_failures=5,
                   reconnect_s=0.1, offline_after_s=1.0)
    plug = Plug()
    factory = _factory(cfg, {SICK: lambda f: FlakyCamera(camera_from_uri(f.source_uri, **cfg.camera_options), plug)})
    col = Collector()
    hand, sub = running_hand(cfg, col, camera_factory=factory)
    try:
        plug.unplugged = True
        before = snapshot(col, HEALTHY)
        assert wait_until(lambda: "camera_lost" in col.flags(SICK), 10), col.status.get(SICK)
        assert col.status[SICK]["state"] == "CAMERA_LOST"
        assert wait_until(lambda: SICK not in alive_sensors(sub, 0.3), 10)      # token withdrawn
        assert set(alive_sensors(sub, 0.5)) == set(HEALTHY)
        assert_kept_publishing(col, before)
        assert all("camera_lost" not in col.flags(s) for s in HEALTHY)
        sick_before = col.n(SICK)
        plug.unplugged = False                                                   # replugged
        assert wait_until(lambda: SICK in alive_sensors(sub, 0.3), 10)
        assert wait_until(lambda: col.n(SICK) > sick_before + 10, 15)
        assert wait_until(lambda: "camera_lost" not in col.flags(SICK), 5)
        assert hand.fingers["f1"].reconnects >= 1 and hand.fingers["f1"].state == "running"
    finally:
        sub.close()
        hand.stop()


def test_sensor_absent_at_start_joins_later(rig):
    from tensortouch.drivers.camera import camera_from_uri

    tmp, pkg, videos = rig
    cfg = hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS}, reconnect_s=0.1, offline_after_s=30.0)
    plug = Plug()
    plug.unplugged = True
    factory = _factory(cfg, {SICK: lambda f: FlakyCamera(camera_from_uri(f.source_uri, **cfg.camera_options), plug)})
    col = Collector()
    hand = Hand(cfg, camera_factory=factory).start()
    sub = col.subscriber(cfg.listen)
    try:
        assert wait_until(lambda: all(col.n(s) > 5 for s in HEALTHY), 20)
        assert wait_until(lambda: "camera_lost" in col.flags(SICK), 10), col.status.get(SICK)
        assert col.n(SICK) == 0 and SICK in alive_sensors(sub, 0.5)        # declared, flagged, no data
        plug.unplugged = False
        assert wait_until(lambda: col.n(SICK) > 5, 15)
        assert wait_until(lambda: "camera_lost" not in col.flags(SICK), 5)
    finally:
        sub.close()
        hand.stop()


def _black_frames():
    frames = poke_frames(90, seed=3)
    return frames[:35] + [np.zeros_like(frames[0])] * 55


def _frozen_frames():
    frame = poke_frames(1, seed=4, press=(0, 0))[0]
    return [frame] * 90


@pytest.mark.parametrize("make_frames, flag", [(_black_frames, "frame_black"), (_frozen_frames, "camera_frozen")])
def test_black_or_frozen_frames_flag_only_that_sensor(rig, tmp_path, make_frames, flag):
    tmp, pkg, videos = rig
    sick_video = write_frames(make_frames(), tmp_path / "sick.avi")
    sources = {s: f"file:{videos[s]}" for s in SERIALS}
    sources[SICK] = f"file:{sick_video}"
    cfg = hand_cfg(tmp, pkg, sources)
    col = Collector()
    hand, sub = running_hand(cfg, col)
    try:
        assert wait_until(lambda: flag in col.flags_seen[SICK], 15), dict(col.flags_seen)
        before = snapshot(col, SERIALS)
        assert_kept_publishing(col, before, sids=SERIALS, min_new=5)             # flagged, not stopped
        assert all(flag not in col.flags_seen[s] for s in HEALTHY)
    finally:
        sub.close()
        hand.stop()


def test_garbled_jpeg_flags_the_sensor(rig, tmp_path):
    tmp, pkg, videos = rig
    session = make_session(tmp_path / "garbled", SICK, poke_frames(90, seed=5))
    data = bytearray((session / "frames.avi").read_bytes())
    soi = [i for i in range(len(data) - 1) if data[i] == 0xFF and data[i + 1] == 0xD8]
    rng = np.random.default_rng(0)
    for k in range(50, 60):                                   # scribble over ten JPEG frames
        data[soi[k] + 200: soi[k] + 1200] = rng.integers(0, 256, 1000, dtype=np.uint8).tobytes()
    (session / "frames.avi").write_bytes(bytes(data))
    sources = {s: f"file:{videos[s]}" for s in SERIALS}
    sources[SICK] = f"replay:{session}"
    cfg = hand_cfg(tmp, pkg, sources, max_camera_failures=5, reconnect_s=0.1)
    col = Collector()
    hand, sub = running_hand(cfg, col)
    try:
        assert wait_until(lambda: col.flags_seen[SICK] & {"camera_stalled", "camera_lost"}, 15), \
            dict(col.flags_seen)
        before = snapshot(col, HEALTHY)
        assert_kept_publishing(col, before)
        err = hand.fingers["f1"].last_error or ""
        assert "corrupt" in err or "garbled" in err or "unreadable" in err, err
        assert wait_until(lambda: hand.fingers["f1"].reconnects >= 1, 10)      # starts over, recovers
    finally:
        sub.close()
        hand.stop()


# ------------------------------------------------------------------------------------- network faults

SUB_SCRIPT = textwrap.dedent("""
    import json, os, sys, time
    from collections import Counter
    from tensortouch.runtime.apps.publisher import open_session
    mode, ep, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
    s = open_session(listen=[ep]) if mode == "listen" else open_session(connect=[ep])
    n = Counter()
    sub = s.declare_subscriber("tensortouch/*/contacts", lambda smp: n.update([str(smp.key_expr).split("/")[1]]))
    t0 = time.time()
    while time.time() - t0 < seconds:
        time.sleep(0.2)
        print(json.dumps(n), flush=True)
    sub.undeclare(); s.close()
    os._exit(0)
""")


def _spawn(mode, ep, seconds):
    return subprocess.Popen([sys.executable, "-c", SUB_SCRIPT, mode, ep, str(seconds)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=os.path.dirname(os.path.dirname(__file__)))


def _last_counts(proc, timeout=30):
    out, err = proc.communicate(timeout=timeout)
    lines = [ln for ln in out.splitlines() if ln.startswith("{")]
    assert lines, err[-2000:]
    return json.loads(lines[-1])


def test_subscriber_process_vanishing(rig):
    tmp, pkg, videos = rig
    cfg = hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS})
    col = Collector()
    hand, sub = running_hand(cfg, col)
    try:
        other = _spawn("connect", cfg.listen[0], 60)
        assert wait_until(lambda: other.stdout.readline().count("TT-") == 3, 20)
        other.kill()                                                          # vanishes, no goodbye
        other.communicate()
        before = snapshot(col, SERIALS)
        assert_kept_publishing(col, before, sids=SERIALS)
        errs = [f.publisher.stats.errors for f in hand.fingers.values()]
        assert all(sum(e.values()) == 0 for e in errs), errs
    finally:
        sub.close()
        hand.stop()


def test_zenoh_peer_restarting(rig):
    tmp, pkg, videos = rig
    peer_ep = free_endpoint()
    cfg = hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS})
    cfg = dataclasses.replace(cfg, connect=(peer_ep,))
    peer = _spawn("listen", peer_ep, 60)
    time.sleep(1.0)
    col = Collector()
    hand, sub = running_hand(cfg, col)
    try:
        assert wait_until(lambda: peer.stdout.readline().count("TT-") == 3, 20)
        peer.kill()
        peer.communicate()
        before = snapshot(col, SERIALS)
        assert_kept_publishing(col, before, sids=SERIALS)                     # while the peer is down
        peer = _spawn("listen", peer_ep, 6)                                   # same endpoint, new process
        counts = _last_counts(peer)
        assert all(counts.get(s, 0) >= 10 for s in SERIALS), counts          # the hand reconnected
    finally:
        if peer.poll() is None:
            peer.kill()
        sub.close()
        hand.stop()


def test_can_bus_errors_flagged_without_stalling(rig):
    can = pytest.importorskip("can")
    tmp, pkg, videos = rig
    channel = f"faults-{uuid.uuid4().hex[:8]}"
    cfg = hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS},
                   can={"interface": "virtual", "channel": channel, "rate_hz": 100, "reopen_after_errors": 30,
                        "reopen_wait_s": 1.0})
    col = Collector()
    hand, sub = running_hand(cfg, col)
    rx = can.Bus(interface="virtual", channel=channel)
    try:
        assert rx.recv(2.0) is not None
        hand.can.bus.shutdown()                                               # interface gone: sends raise
        assert wait_until(lambda: all("can_errors" in col.flags(s) for s in SERIALS), 10), dict(col.status)
        before = snapshot(col, SERIALS)
        assert_kept_publishing(col, before, sids=SERIALS)                     # frame loops not stalled
        assert wait_until(lambda: hand.can.stats.reopens >= 1, 10)
        while rx.recv(0.0) is not None:
            pass
        assert rx.recv(2.0) is not None                                       # summaries flow again
        assert wait_until(lambda: all("can_errors" not in col.flags(s) for s in SERIALS), 10)
    finally:
        rx.shutdown()
        sub.close()
        hand.stop()


# ------------------------------------------------------------------------------------- stored files

def test_model_file_replaced_by_corrupt_one_while_running(rig, tmp_path):
    tmp, pkg, videos = rig
    model_dir = tmp_path / "model"
    shutil.copytree(pkg, model_dir)
    cfg = hand_cfg(tmp, model_dir, {s: f"file:{videos[s]}" for s in SERIALS}, model_poll_s=0.2)
    col = Collector()
    hand, sub = running_hand(cfg, col)
    try:
        old_hash = query_info(sub, "TT-A")["model_hash"]
        (model_dir / "model.int8.onnx").write_bytes(b"\x08\x01garbage, not an onnx graph" * 50)
        assert wait_until(lambda: all("model_invalid" in col.flags(s) for s in SERIALS), 10), dict(col.status)
        before = snapshot(col, SERIALS)
        assert_kept_publishing(col, before, sids=SERIALS)                     # old session keeps running
        assert query_info(sub, "TT-A")["model_hash"] == old_hash
        from tensortouch.tools.bench.models import write_difference_package

        write_difference_package(tmp_path / "new", 32, gain=3.0)             # a valid new model arrives
        for name in ("model.int8.onnx", "model.fp32.onnx", "manifest.json"):
            shutil.copyfile(tmp_path / "new" / name, model_dir / name)
        assert wait_until(lambda: all("model_invalid" not in col.flags(s) for s in SERIALS), 10)
        new_hash = query_info(sub, "TT-C")["model_hash"]
        assert new_hash != old_hash
        write_difference_package(tmp_path / "big", 64)                       # valid, but the wrong size
        for name in ("model.int8.onnx", "model.fp32.onnx", "manifest.json"):
            shutil.copyfile(tmp_path / "big" / name, model_dir / name)
        assert wait_until(lambda: all("model_invalid" in col.flags(s) for s in SERIALS), 10)
        before = snapshot(col, SERIALS)
        assert_kept_publishing(col, before, sids=SERIALS)
        assert query_info(sub, "TT-C")["model_hash"] == new_hash
    finally:
        sub.close()
        hand.stop()
    with pytest.raises(ModelPackageError, match="model.int8.onnx: SHA-256 does not match"):
        (model_dir / "model.int8.onnx").write_bytes(b"corrupt")
        Hand(cfg)                                                             # a restart refuses it clearly


def running_hand_on_store(rig, store_root, col):
    """A running hand of every serial (and its subscriber) reading a fresh calibration store at
    `store_root`; returns (hand, subscriber, store)."""
    from tensortouch.contracts.store import CalibrationStore

    tmp, pkg, videos = rig
    make_store(store_root, SERIALS)
    cfg = dataclasses.replace(hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS}),
                              calibration_store=str(store_root))
    hand, sub = running_hand(cfg, col)
    return hand, sub, CalibrationStore(store_root)


def test_calibration_replaced_by_corrupt_one_while_running(rig, tmp_path):
    from tests.conftest import dome_calibration

    store_root = tmp_path / "store"
    col = Collector()
    hand, sub, store = running_hand_on_store(rig, store_root, col)
    try:
        v_old = store.current(SICK)
        v_bad = dome_calibration(store_root, SICK, size=32, image=(160, 120), radius_px=48.0)
        table = store_root / SICK / "versions" / v_bad / "theta.npy"
        table.write_bytes(table.read_bytes()[:100])                           # truncated / corrupt table
        assert wait_until(lambda: "calibration_invalid" in col.flags(SICK), 10), col.status.get(SICK)
        assert col.status[SICK]["calibration_version"] == v_old               # still on the good one
        before = snapshot(col, SERIALS)
        assert_kept_publishing(col, before, sids=SERIALS)
        assert all("calibration_invalid" not in col.flags(s) for s in HEALTHY)
        v_good = dome_calibration(store_root, SICK, size=32, image=(160, 120), radius_px=49.0)
        assert wait_until(lambda: col.status[SICK]["calibration_version"] == v_good, 10)
        assert wait_until(lambda: "calibration_invalid" not in col.flags(SICK), 5)
    finally:
        sub.close()
        hand.stop()


DISK_FULL_WRITE = textwrap.dedent("""
    import resource, signal, sys
    sys.path.insert(0, sys.argv[2])
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)          # get EFBIG instead of being killed
    resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048))
    from tests.conftest import dome_calibration
    from tensortouch.contracts.errors import CalibrationError
    try:
        dome_calibration(sys.argv[1], "TT-B", size=32, image=(160, 120), radius_px=47.0)
    except CalibrationError as exc:
        cause = exc.__cause__
        print(type(cause).__name__, getattr(cause, "errno", None), exc)
        sys.exit(3)
    print("written")
""")


def _mount_tmpfs(path, size="1m"):
    path.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    return r.returncode == 0


def test_disk_full_during_calibration_write(rig, tmp_path):
    """A full disk (tmpfs at its size limit where mounting is allowed, else a file-size limit in a
    separate process) fails the write; the running hand and the stored versions are untouched."""
    from tests.conftest import dome_calibration

    disk = tmp_path / "disk"
    mounted = _mount_tmpfs(disk)
    store_root = disk / "store"
    col = Collector()
    hand, sub, store = running_hand_on_store(rig, store_root, col)
    try:
        v_old = store.current(SICK)
        if mounted:
            filler = disk / "filler"
            fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
            try:
                while os.write(fd, b"\0" * 4096):
                    pass
            except OSError as exc:
                assert exc.errno == 28
            finally:
                os.close(fd)
            from tensortouch.contracts.errors import CalibrationError

            with pytest.raises(CalibrationError, match="nothing was stored") as info:
                dome_calibration(store_root, SICK, size=32, image=(160, 120), radius_px=47.0)
            # ENOSPC, or numpy's own "N requested and M written" OSError (errno None) from np.save
            assert isinstance(info.value.__cause__, OSError) and info.value.__cause__.errno in (28, None)
        else:
            r = subprocess.run([sys.executable, "-c", DISK_FULL_WRITE, str(store_root),
                                os.path.dirname(os.path.dirname(__file__))], capture_output=True, text=True)
            assert r.returncode == 3 and "OSError" in r.stdout, r.stdout + r.stderr   # EFBIG / short write
        assert store.current(SICK) == v_old and store.versions(SICK) == [v_old]
        leftovers = [p.name for p in (store_root / SICK / "versions").iterdir() if p.name != v_old]
        assert leftovers == []                                                 # nothing half-written
        store.load(SICK)                                                       # hashes still verify
        before = snapshot(col, SERIALS)
        assert_kept_publishing(col, before, sids=SERIALS)
        assert all("calibration_invalid" not in col.flags(s) for s in SERIALS)
        if mounted:
            filler.unlink()
            v_new = dome_calibration(store_root, SICK, size=32, image=(160, 120), radius_px=47.0)
            assert wait_until(lambda: col.status[SICK]["calibration_version"] == v_new, 10)
    finally:
        sub.close()
        hand.stop()
        if mounted:
            subprocess.run(["umount", str(disk)], capture_output=True)


# ------------------------------------------------------------------------------------- recording

def _recording_disk(tmp_path, free_kb=None):
    """(folder, preexec, mounted): a 512 KB tmpfs (optionally filled to `free_kb` left) where
    mounting is allowed, else a plain folder and a file-size limit (`free_kb` or 256 KB) for the recorder."""
    import resource
    import signal

    disk = tmp_path / "recdisk"
    if _mount_tmpfs(disk, "512k"):
        if free_kb is not None:
            st = os.statvfs(disk)
            left = st.f_bavail * st.f_frsize - free_kb * 1024
            (disk / "filler").write_bytes(b"\0" * max(0, left))
        return disk, None, True

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)          # EFBIG instead of being killed
        cap = (free_kb or 256) * 1024
        resource.setrlimit(resource.RLIMIT_FSIZE, (cap, cap))
    return disk, limit, False


@pytest.mark.parametrize("kinds, free_kb", [("fields,contacts,wrench,status", None), ("contacts,wrench,status", 8)],
                         ids=["fields", "jsonl-only"])
def test_disk_full_while_recording(rig, tmp_path, kinds, free_kb):
    """`tensortouch listen --save` (a real separate process) records a running hand onto a disk
    that fills up: the recorder stops with a clear message naming the file, what it saved stays
    readable (no temp files, no partial .npy, no partial JSONL line), and the hand keeps
    publishing to its other subscribers without errors."""
    tmp, pkg, videos = rig
    disk, preexec, mounted = _recording_disk(tmp_path, free_kb)
    cfg = hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS})
    col = Collector()
    hand, sub = running_hand(cfg, col)
    rec = disk / "rec"
    try:
        r = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", "listen", "--connect", cfg.listen[0],
                            "--save", str(rec), "--kinds", kinds, "--timeout", "60", "--json"],
                           capture_output=True, text=True, timeout=90, preexec_fn=preexec,
                           cwd=os.path.dirname(os.path.dirname(__file__)))
        assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
        assert "Traceback" not in r.stderr, r.stderr[-2000:]
        msg = [ln for ln in r.stderr.splitlines() if ln.startswith("tensortouch listen:")]
        assert msg and str(rec) in msg[-1] and "cannot save" in msg[-1], r.stderr[-2000:]
        assert ("No space left" in msg[-1] or "requested and" in msg[-1]) if mounted else "File too large" in msg[-1]
        assert not [p for p in rec.rglob("*") if ".tmp" in p.name]          # no temp files left behind
        saved = list(rec.rglob("*.npy"))
        for p in saved:                                                      # every .npy is complete
            assert np.load(p).shape == (15, 32, 32), p
        assert bool(saved) == kinds.startswith("fields")
        lines = 0
        for p in rec.rglob("*.jsonl"):                                       # every JSONL line is whole
            text = p.read_text()
            assert text == "" or text.endswith("\n"), p
            for ln in text.splitlines():
                assert json.loads(ln)["seq"] >= 0
                lines += 1
        assert lines > 0
        before = snapshot(col, SERIALS)
        assert_kept_publishing(col, before, sids=SERIALS)                    # the hand did not notice
        errs = [f.publisher.stats.errors for f in hand.fingers.values()]
        assert all(sum(e.values()) == 0 for e in errs), errs
    finally:
        sub.close()
        hand.stop()
        if mounted:
            subprocess.run(["umount", str(disk)], capture_output=True)
