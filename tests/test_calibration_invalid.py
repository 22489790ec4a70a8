"""A newly activated calibration whose tables are not finite (inf/NaN pixel_area, valid hashes) is refused
at hot reload, in the single-sensor frame loop (`tensortouch run`) and in a whole hand (`tensortouch
hand`): the sensor keeps publishing on the previous version with `calibration_invalid`, never crashes,
never reports `camera_lost`. NaN model output raises `model_output_invalid`. Real Zenoh on loopback,
real onnxruntime, real OpenCV replays."""
import dataclasses
import json
import shutil
import threading

import numpy as np
import pytest
from tensortouch.contracts.store import CalibrationStore, sha256_file
from tensortouch.drivers.camera import camera_from_uri
from tensortouch.runtime.apps.loop import LoopConfig, SensorLoop
from tensortouch.runtime.apps.publisher import Publisher
from tensortouch.runtime.pipeline import SensorPipeline
from tensortouch.runtime.stages.model import FieldModel, load_package

from tests.hand_util import (
    free_endpoint,
    hand_cfg,
    make_package,
    make_store,
    make_video,
    wait_until,
)
from tests.test_faults_hand import Collector, running_hand, snapshot

SERIALS = ("TT-A", "TT-B")
SICK = "TT-B"


def activate_bad_version(store_root, sid, value, table="pixel_area"):
    """Copy the active version to the next one with one table poisoned (hashes rewritten to match, so
    only the value check can catch it) and point CURRENT at it, as a careless tool would."""
    store = CalibrationStore(store_root)
    old = store.current(sid)
    new = f"v{int(old[1:]) + 1:04d}"
    vdir = store_root / sid / "versions"
    shutil.copytree(vdir / old, vdir / new)
    arr = np.load(vdir / new / f"{table}.npy")
    arr.reshape(-1)[arr.size // 2] = value
    np.save(vdir / new / f"{table}.npy", arr)
    meta = json.loads((vdir / new / "calibration.json").read_text())
    meta["version"] = new
    meta["files"][f"{table}.npy"] = sha256_file(vdir / new / f"{table}.npy")
    (vdir / new / "calibration.json").write_text(json.dumps(meta))
    (store_root / sid / "CURRENT").write_text(new + "\n")
    return old, new


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("calinvalid")
    pkg = make_package(tmp / "models" / "difference-32")
    videos = {s: make_video(tmp / f"{s}.avi", seed=i) for i, s in enumerate(SERIALS)}
    return tmp, pkg, videos


@pytest.mark.parametrize("value", [np.inf, np.nan])
def test_run_loop_refuses_nonfinite_hot_reload_and_keeps_publishing(rig, tmp_path, value):
    _, pkg, videos = rig
    store_root = make_store(tmp_path / "store", [SICK])
    store = CalibrationStore(store_root)
    package = load_package(pkg)
    pipeline = SensorPipeline(SICK, FieldModel(package, "fp32"), store.load(SICK))
    ep = free_endpoint()
    pub = Publisher(SICK, listen=[ep], info=lambda: {"model": {"name": package.name}})
    col = Collector()
    sub = col.subscriber([ep])
    cam = camera_from_uri(f"file:{videos[SICK]}", realtime=True, loop=True)
    loop = SensorLoop(cam, pipeline, pub, LoopConfig(calibration_poll_s=0.05, status_every_s=0.05), store=store)
    errors = []

    def run():
        try:
            with cam:
                loop.run()
        except BaseException as exc:  # noqa: BLE001 - the test asserts there is none
            errors.append(exc)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    try:
        assert wait_until(lambda: col.n(SICK) > 5, 20)
        old, _ = activate_bad_version(store_root, SICK, value)
        assert wait_until(lambda: "calibration_invalid" in col.flags(SICK), 10), col.status.get(SICK)
        assert col.status[SICK]["calibration_version"] == old
        before = snapshot(col, [SICK])
        assert wait_until(lambda: col.n(SICK) - before[SICK] >= 20, 10)            # still publishing
        assert th.is_alive() and not errors and pipeline.cal.version == old
        assert "camera_stalled" not in col.flags_seen[SICK]
        store.rollback(SICK, old)                   # CURRENT names a good version again: flag cleared
        assert wait_until(lambda: "calibration_invalid" not in col.flags(SICK), 10)
    finally:
        loop.stop()
        th.join(10)
        sub.close()
        pub.close()
    assert not errors, errors


@pytest.mark.parametrize("value", [np.inf, np.nan])
def test_hand_refuses_nonfinite_hot_reload_without_camera_lost(rig, tmp_path, value):
    tmp, pkg, videos = rig
    store_root = make_store(tmp_path / "store", SERIALS)
    cfg = dataclasses.replace(hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS}),
                              calibration_store=str(store_root))
    col = Collector()
    hand, sub = running_hand(cfg, col)
    try:
        old, _ = activate_bad_version(store_root, SICK, value)
        assert wait_until(lambda: "calibration_invalid" in col.flags(SICK), 10), col.status.get(SICK)
        assert col.status[SICK]["calibration_version"] == old
        before = snapshot(col, SERIALS)
        assert wait_until(lambda: all(col.n(s) - before[s] >= 20 for s in SERIALS), 10)
        assert "camera_lost" not in col.flags_seen[SICK]
        assert all(f.state == "running" for f in hand.fingers.values())
        assert "calibration_invalid" not in col.flags("TT-A")
        store = CalibrationStore(store_root)
        store.rollback(SICK, old)
        v_good = store.derive(SICK, {"gel_radius_px": 49.0})     # a good version after the bad one loads
        assert wait_until(lambda: col.status[SICK]["calibration_version"] == v_good, 10)
        assert wait_until(lambda: "calibration_invalid" not in col.flags(SICK), 5)
    finally:
        sub.close()
        hand.stop()


def test_nan_model_output_raises_a_flag(rig, tmp_path):
    _, pkg, videos = rig
    store = CalibrationStore(make_store(tmp_path / "store", [SICK]))
    package = load_package(pkg)
    model = FieldModel(package, "fp32")

    class NanModel:                 # the real model, with NaN written into its output
        def __init__(self, inner):
            self.inner = inner

        def __call__(self, x):
            out = self.inner(x).copy()
            out[:, 3:7, 3:7] = np.nan
            return out

        def __getattr__(self, name):
            return getattr(self.inner, name)

    pipeline = SensorPipeline(SICK, NanModel(model), store.load(SICK))
    results = []
    cam = camera_from_uri(f"file:{videos[SICK]}", realtime=False)
    loop = SensorLoop(cam, pipeline, None, store=store, on_result=results.append)
    with cam:
        loop.run(max_frames=60)
    with_fields = [r for r in results if r.fields is not None]
    assert with_fields and all("model_output_invalid" in r.flags for r in with_fields)
    assert all(np.isfinite(r.force_n).all() and np.isfinite(r.fields).all() for r in with_fields)
    assert "model_output_invalid" in loop.flags


# Implausible versions that pass the old "finite and > 0" check; each is activated by pointing CURRENT at it
# (calibration.json is not hashed, so a hand edit is enough). "camera-less rim" drops the camera block, so
# only the runtime's check against the real frames can refuse the radius.
IMPLAUSIBLE = {
    "rim 1e9": {"gel_radius_px": 1e9},
    "rim 1e308": {"gel_radius_px": 1e308},
    "centre 1e308": {"gel_center_px": [1e308, 60.0]},
    "centre outside the image": {"gel_center_px": [400.0, 60.0]},
    "camera-less rim larger than the frame": {"camera": None, "gel_radius_px": 5000.0},
    "tables of another size than the model": "size16",
}


def activate_implausible(store_root, sid, case):
    """Make the next version of `sid` implausible as IMPLAUSIBLE[case] says and activate it; returns
    (the previous version, the new one)."""
    from tests.conftest import dome_calibration
    from tests.hand_util import IMAGE

    store = CalibrationStore(store_root)
    old = store.current(sid)
    change = IMPLAUSIBLE[case]
    if change == "size16":          # a whole, hashed calibration with 16x16 tables: the model is 32x32
        return old, dome_calibration(store_root, sid, size=16, image=IMAGE, radius_px=50.0)
    new = f"v{int(old[1:]) + 1:04d}"
    vdir = store_root / sid / "versions"
    shutil.copytree(vdir / old, vdir / new)
    meta = json.loads((vdir / new / "calibration.json").read_text())
    meta.update({"version": new, **change})
    meta = {k: v for k, v in meta.items() if v is not None}
    (vdir / new / "calibration.json").write_text(json.dumps(meta))
    (store_root / sid / "CURRENT").write_text(new + "\n")
    return old, new


@pytest.mark.parametrize("case", list(IMPLAUSIBLE))
def test_run_loop_refuses_implausible_hot_reload_and_keeps_publishing(rig, tmp_path, case):
    _, pkg, videos = rig
    store_root = make_store(tmp_path / "store", [SICK])
    store = CalibrationStore(store_root)
    package = load_package(pkg)
    pipeline = SensorPipeline(SICK, FieldModel(package, "fp32"), store.load(SICK))
    ep = free_endpoint()
    pub = Publisher(SICK, listen=[ep], info=lambda: {"model": {"name": package.name}})
    col = Collector()
    sub = col.subscriber([ep])
    cam = camera_from_uri(f"file:{videos[SICK]}", realtime=True, loop=True)
    loop = SensorLoop(cam, pipeline, pub, LoopConfig(calibration_poll_s=0.05, status_every_s=0.05), store=store)
    errors = []

    def run():
        try:
            with cam:
                loop.run()
        except BaseException as exc:  # noqa: BLE001 - the test asserts there is none
            errors.append(exc)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    try:
        assert wait_until(lambda: col.n(SICK) > 5, 20)
        old, new = activate_implausible(store_root, SICK, case)
        assert wait_until(lambda: "calibration_invalid" in col.flags(SICK), 10), col.status.get(SICK)
        assert col.status[SICK]["calibration_version"] == old
        before = snapshot(col, [SICK])
        assert wait_until(lambda: col.n(SICK) - before[SICK] >= 20, 10)            # still publishing
        assert th.is_alive() and not errors and pipeline.cal.version == old
        assert col.status[SICK]["calibration_version"] == old
        store.rollback(SICK, old)
        assert wait_until(lambda: "calibration_invalid" not in col.flags(SICK), 10)
    finally:
        loop.stop()
        th.join(10)
        sub.close()
        pub.close()
    assert not errors, errors


@pytest.mark.parametrize("case", ["rim 1e9", "centre 1e308", "camera-less rim larger than the frame",
                                  "tables of another size than the model"])
def test_hand_refuses_implausible_hot_reload_without_camera_lost(rig, tmp_path, case):
    tmp, pkg, videos = rig
    store_root = make_store(tmp_path / "store", SERIALS)
    cfg = dataclasses.replace(hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS}),
                              calibration_store=str(store_root))
    col = Collector()
    hand, sub = running_hand(cfg, col)
    try:
        old, _ = activate_implausible(store_root, SICK, case)
        assert wait_until(lambda: "calibration_invalid" in col.flags(SICK), 10), col.status.get(SICK)
        assert col.status[SICK]["calibration_version"] == old
        before = snapshot(col, SERIALS)
        assert wait_until(lambda: all(col.n(s) - before[s] >= 20 for s in SERIALS), 10)
        assert "camera_lost" not in col.flags_seen[SICK]
        assert all(f.state == "running" for f in hand.fingers.values())
        assert hand.fingers["f1"].pipeline.cal.version == old
        assert "calibration_invalid" not in col.flags("TT-A")
    finally:
        sub.close()
        hand.stop()
