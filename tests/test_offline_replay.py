"""One offline runtime: `replay_session` publishes what `tensortouch run` publishes.

The acceptance test runs `tensortouch run` on the shipped demo recording in its own process, with a
real Zenoh subscriber on loopback in this one, and replays the same recording here; a calibration made
in a temp store switches on two effects (one reads the session's temperature) and a small ONNX gain
correction. The shipped model and real onnxruntime/OpenCV/Zenoh are used; nothing is mocked.
"""
import ast
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from tensortouch.contracts import paths
from tensortouch.contracts.session import load_session
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.offline import cache_key, network_passes, replay_session
from tensortouch.runtime.stages.correction import ForceCorrection
from tensortouch.runtime.stages.model import load_package
from tensortouch.tools.bench.models import write_difference_package
from tensortouch.tools.recalib.replay import collect_frames, corrected_frames

from tests.conftest import dome_calibration
from tests.test_correction import gain_model
from tests.test_e2e_runtime import SENSOR, SIZE, H, W, free_port, write_poke_session

ROOT = Path(__file__).resolve().parents[1]
DEMO = "TWIN-DEMO"
EFFECTS = [{"name": "temperature_softening", "params": {"alpha": 0.02, "t_ref": 20.0}},
           {"name": "strain_stiffening", "params": {"k": 20.0}}]


def test_no_tool_builds_the_pipeline_by_hand():
    """Tools, the runtime's apps and the Sensor API build through runtime.pipeline.open_pipeline (the one
    constructor) or replay through runtime.offline, never SensorPipeline(...)."""
    found = []
    files = [*(ROOT / "tools").rglob("*.py"), *(f for f in (ROOT / "runtime").rglob("*.py") if f.name != "pipeline.py")]
    for f in sorted(files):
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.Call):
                fn = node.func
                name = fn.id if isinstance(fn, ast.Name) else fn.attr if isinstance(fn, ast.Attribute) else None
                if name == "SensorPipeline":
                    found.append(f"{f.relative_to(ROOT)}:{node.lineno}")
    assert not found, found
    out = subprocess.run(["grep", "-rn", "SensorPipeline(", str(ROOT / "tools"), str(ROOT / "runtime"), "--include=*.py"],
                         capture_output=True, text=True, check=False)
    assert [line for line in out.stdout.splitlines() if not line.startswith(str(ROOT / "runtime" / "pipeline.py"))] == []


def demo_store(root: Path, effects=EFFECTS, gain=1.1) -> CalibrationStore:
    """A copy of the demo unit's calibration with `effects` and a constant-gain correction active."""
    shutil.copytree(paths.calibration_dir() / DEMO, root / DEMO)
    store = CalibrationStore(root)
    files = {}
    changes = {"effects": effects}
    if gain is not None:
        files["correction.onnx"] = gain_model(root / "gain.onnx", 3, gain)
        changes["correction"] = {"file": "correction.onnx", "inputs": ["fmag", "u", "v"], "output": "gain"}
    store.derive(DEMO, changes, files=files)
    return store


def poke_recording(tmp_path: Path):
    """(session, package, store): a synthetic poke recording, a small difference network, and a
    nominal calibration with strain stiffening (k = 40) and a constant 1.1 gain correction."""
    session = write_poke_session(tmp_path / "session")
    pkg = load_package(write_difference_package(tmp_path / "m" / "d", SIZE))
    dome_calibration(tmp_path / "calib", SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    store = CalibrationStore(tmp_path / "calib")
    store.derive(SENSOR, {"effects": [{"name": "strain_stiffening", "params": {"k": 40.0}}],
                          "correction": {"file": "correction.onnx", "inputs": ["fmag", "u", "v"], "output": "gain"}},
                 files={"correction.onnx": gain_model(tmp_path / "gain.onnx", 3, 1.1)})
    return session, pkg, store


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    from tensortouch.runtime.stages.model import find_package

    if not (paths.demo_dir() / "session.json").is_file():
        pytest.skip("no demo recording")
    root = tmp_path_factory.mktemp("offline")
    store = demo_store(root / "calib")
    return {"root": root, "store": store, "package": find_package(None), "cal": store.load(DEMO)}


def run_and_replay(session: Path, package, store: CalibrationStore, sensor: str, min_touched: int):
    """`tensortouch run` on `session` (own process, Zenoh to a subscriber here) vs `replay_session`:
    the same contacts and wrench on every frame; returns the replayed results."""
    from tensortouch.runtime.apps.subscriber import Subscriber

    cal = store.load(sensor)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    contacts, wrench, lock = {}, {}, threading.Lock()

    def on_contacts(m):
        with lock:
            contacts[m.seq] = m

    def on_wrench(m):
        with lock:
            wrench[m.seq] = m

    env = dict(os.environ, TENSORTOUCH_CALIBRATION=str(store.root), PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT))
    with Subscriber(sensor, listen=[endpoint], on_contacts=on_contacts, on_wrench=on_wrench):
        run = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", "run", "--source", f"replay:{session}",
                              "--model", str(package.folder), "--no-fields", "--connect", endpoint], check=False,
                             env=env, capture_output=True, text=True, timeout=300, cwd=ROOT)
        time.sleep(1.0)
    assert run.returncode == 0, run.stderr[-3000:]
    results = list(replay_session(session, package, cal))
    n = len(load_session(session).table("frames"))
    assert len(results) == n
    with lock:
        got = dict(contacts), dict(wrench)
    # every frame's message arrived (the first few may precede the subscription's propagation)
    assert len(got[0]) >= n - 5 and len(got[1]) >= n - 5, (len(got[0]), len(got[1]))
    compared = touched = 0
    for r in results:
        if r.seq not in got[0] or r.seq not in got[1]:
            continue
        pub, w = got[0][r.seq], got[1][r.seq]
        assert pub.t == pytest.approx(r.t, abs=1e-9)
        assert [c.id for c in pub.contacts] == [c.id for c in r.clusters]
        for c, k in zip(pub.contacts, r.clusters):
            np.testing.assert_allclose(c.position_mm, k.position_mm, atol=1e-6)
            np.testing.assert_allclose(c.force_n, k.force_n, rtol=1e-6, atol=1e-9)
            assert c.age_frames == k.age_frames
        np.testing.assert_allclose(w.force_n, r.force_n, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(w.torque_nmm, r.torque_nmm, rtol=1e-6, atol=1e-6)
        compared += 1
        touched += bool(r.clusters)
    assert compared >= n - 5 and touched >= min_touched, (compared, touched)
    # the effects and the correction were on: raw model forces differ, and no covariate was missing
    raw = list(replay_session(session, package, cal, correction=ForceCorrection(None, None), effects=False))
    fz = [(r.force_n[2], s.force_n[2]) for r, s in zip(results, raw) if r.clusters and s.clusters]
    assert fz and not np.allclose(*zip(*fz), rtol=1e-3)
    assert not any("effect_covariate_missing" in r.flags or "effects_invalid" in r.flags for r in results)
    return results


@pytest.mark.slow
def test_run_and_replay_session_publish_the_same_contacts_and_forces(demo):
    """The shipped demo and model, a temperature-dependent effect fed by the session's stream."""
    cal = demo["cal"]
    assert cal.meta["effects"] and cal.meta["correction"]
    run_and_replay(paths.demo_dir(), demo["package"], demo["store"], DEMO, min_touched=20)


def test_run_and_replay_session_agree_on_a_small_recording(tmp_path):
    """The same check, fast: a synthetic poke recording and a small difference network."""
    session, pkg, store = poke_recording(tmp_path)
    run_and_replay(session, pkg, store, SENSOR, min_touched=10)


@pytest.mark.slow
def test_cached_network_passes_replay_the_same_and_follow_the_key(demo, tmp_path):
    pkg, cal = demo["package"], demo["cal"]
    live = list(replay_session(paths.demo_dir(), pkg, cal))
    first = list(replay_session(paths.demo_dir(), pkg, cal, cache=tmp_path))
    assert len(list(tmp_path.glob("*.npz"))) == 1
    again = list(replay_session(paths.demo_dir(), pkg, cal, cache=tmp_path))
    for a, b, c in zip(live, first, again):
        assert a.seq == b.seq == c.seq and a.state == c.state and a.flags == c.flags
        assert c.fields is None
        np.testing.assert_array_equal(a.force_n, c.force_n)
        assert [k.id for k in a.clusters] == [k.id for k in c.clusters]
    passes, cached = network_passes(paths.demo_dir(), pkg, cal, cache=tmp_path)
    assert cached and len(passes) == len(live)
    # another effect or correction keeps the key; the geometry and the pipeline configuration do not
    store = demo["store"]
    session = load_session(paths.demo_dir())
    key = cache_key(session, pkg, cal, "int8")
    store.derive(DEMO, {"effects": EFFECTS[1:]})
    assert cache_key(session, pkg, store.load(DEMO), "int8") == key
    store.derive(DEMO, {"gel_radius_px": cal.meta["gel_radius_px"] + 1.0})
    assert cache_key(session, pkg, store.load(DEMO), "int8") != key
    contacts = pkg.manifest.setdefault("runtime", {}).setdefault("contacts", {})
    old = contacts.get("merge_n")
    contacts["merge_n"] = 123.0
    try:
        assert cache_key(session, pkg, cal, "int8") != key
    finally:
        contacts["merge_n"] = old


def test_recalibration_replays_with_the_effect_stage(tmp_path):
    """The recalibration's fit surface (tools.recalib.replay) is the runtime's output with the
    calibration's effects applied and the correction off; its re-applied correction is what the
    runtime publishes with that correction on."""
    session, pkg, store = poke_recording(tmp_path)
    cal = store.load(SENSOR)
    frames = collect_frames(session, cal, pkg, "fp32", cache=tmp_path / "cache")
    assert len(frames) == 90 and sum(len(c) for _, c in frames) > 10
    no_corr = list(replay_session(session, pkg, cal, precision="fp32", correction=ForceCorrection(None, None)))
    raw = list(replay_session(session, pkg, cal, precision="fp32", correction=ForceCorrection(None, None),
                              effects=False))
    assert [len(c) for _, c in frames] == [len(a.clusters) for a in no_corr] == [len(b.clusters) for b in raw]
    seen = [(c.force_n, n.force_n, r.force_n) for (_, cl), a, b in zip(frames, no_corr, raw)
            for c, n, r in zip(cl, a.clusters, b.clusters)]
    assert seen
    np.testing.assert_allclose([s[0] for s in seen], [s[1] for s in seen], rtol=1e-12)     # effects applied
    assert not np.allclose([s[0] for s in seen], [s[2] for s in seen], rtol=1e-3)          # ... and they matter
    published = list(replay_session(session, pkg, cal, precision="fp32"))
    refit = corrected_frames(frames, cal)
    for (t, cl), r in zip(refit, published):
        assert t == r.t and [c.id for c in cl] == [c.id for c in r.clusters]
        np.testing.assert_allclose([c.force_n for c in cl], [c.force_n for c in r.clusters], rtol=1e-9, atol=1e-12)
