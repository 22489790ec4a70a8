"""The workbench's deployed-network model: real frames through the runtime's SensorPipeline.

A tiny twin session (analytic physics, 15 fps, 32 px calibration) and a tiny deterministic network
package (tools.bench.models difference network: real onnxruntime, fields follow the image change)
are made in a temp dir; nothing is committed. The slow acceptance on FE twin sessions with the
shipped network is tests/test_workbench_net_twin.py.
"""
import argparse
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.contracts.session import load_session
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.pipeline import open_pipeline
from tensortouch.runtime.stages.effects import Registry
from tensortouch.runtime.stages.model import load_package
from tensortouch.tools.scoring import match_contacts
from tensortouch.tools.workbench import cli
from tensortouch.tools.workbench.compare import run_compare
from tensortouch.tools.workbench.network import NetworkModel, replay, temperature_of

pytest.importorskip("tensortouch.tools.twin.record")
SENSOR = "TWIN-WBT"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from tensortouch.tools.bench.models import write_difference_package
    from tensortouch.tools.twin.record import RecordConfig, Recorder
    from tensortouch.tools.twin.unit import TwinUnit, write_true_calibration

    root = tmp_path_factory.mktemp("wbnet")
    cfg = RecordConfig(serial=SENSOR, pokes=4, seed=3, physics="hertz-fallback", frame_format="mjpg", model_size=32)
    cfg.rig = replace(cfg.rig, camera_fps=15.0)
    cfg.trajectory = replace(cfg.trajectory, indenters=("sphere5", "flat4"), kinds=("press",))
    session = Recorder(cfg, root / "session").run()
    write_true_calibration(TwinUnit(SENSOR), root / "store", 32)
    package = write_difference_package(root / "pkg", 32)
    return {"session": session, "store": root / "store", "package": package, "root": root}


@pytest.fixture
def env(tiny, tmp_path, monkeypatch):
    monkeypatch.setenv("TENSORTOUCH_CACHE", str(tmp_path / "cache"))
    store = tmp_path / "store"
    shutil.copytree(tiny["store"], store)
    return dict(tiny, store=store, tmp=tmp_path, monkeypatch=monkeypatch)


def _correction(store: CalibrationStore) -> str:
    """Store a real zero-constrained gain forest (ONNX) as the sensor's correction."""
    pytest.importorskip("sklearn")
    from tensortouch.tools.recalib.fit import FitConfig, PokeSet, fit_forest, to_onnx
    from tensortouch.tools.recalib.store_ops import store_recalibration

    rng = np.random.default_rng(0)
    f = rng.normal(size=(40, 3))
    pokes = PokeSet(f, np.linalg.norm(f, axis=1) * rng.uniform(0.6, 1.6, 40), rng.uniform(0, 1, (40, 2)),
                    rng.uniform(0, 1, (40, 2)))
    cfg = FitConfig()
    spec = {"file": "correction.onnx", "inputs": list(cfg.inputs), "output": "gain"}
    return store_recalibration(store, store.load(SENSOR), {"method": "test"},
                               correction=(spec, to_onnx(fit_forest(pokes, cfg), len(cfg.inputs), cfg)))


def test_match_pairs_each_indenter_with_the_nearest_cluster_inside_the_gate():
    tips = np.array([[0.0, 0, 0], [10.0, 0, 0], [50.0, 0, 0]])
    cents = np.array([[9.0, 0, 0], [1.0, 0, 0], [0.5, 0, 0]])
    assert match_contacts(tips, cents, 6.0).tolist() == [2, 0, -1]
    assert match_contacts(tips, cents[:0], 6.0).tolist() == [-1, -1, -1]
    assert match_contacts(tips[:1], cents[:1], 6.0).tolist() == [-1]       # 9 mm away: not its contact


def test_replay_gives_the_numbers_the_runtime_pipeline_publishes(env):
    """Raw pass (effects/correction off) + replay == SensorPipeline with effects and correction on."""
    store = CalibrationStore(env["store"])
    _correction(store)
    store.derive(SENSOR, {"effects": [{"name": "viscoelastic_relaxation", "params": {"g1": 0.3, "tau": 0.5}},
                                      {"name": "strain_stiffening", "params": {"k": 20.0}},
                                      {"name": "temperature_softening", "params": {"alpha": 0.03, "t_ref": 24.0}}]})
    cal = store.load(SENSOR)
    session = load_session(env["session"])
    package = load_package(env["package"])
    temp = temperature_of(session)
    pipe = open_pipeline(package, cal, sensor_id=SENSOR)
    assert pipe.effects.enabled and pipe.correction.enabled
    from tensortouch.tools.sessions.writer import read_frames

    times = session.table("frames")[:, 0]
    published = []
    for i, img in read_frames(session):
        pipe.set_temperature(temp(times[i]))
        res = pipe.process(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), float(times[i]))
        published += [c.force_n for c in res.clusters]
    model = NetworkModel(package)
    passed = model.frame_pass(session, cal, None)
    out = replay(passed, package, cal, temp)
    assert len(published) == len(out["force"]) > 20
    raw = passed["cl_force_n"]
    assert not np.allclose(raw, published, atol=1e-3)             # effects + correction changed them
    np.testing.assert_allclose(out["force"], np.array(published), rtol=1e-9, atol=1e-9)


def test_compare_caches_the_network_and_reapplies_effects(env):
    store = CalibrationStore(env["store"])
    reg = Registry.default(entry_points=False)
    model = NetworkModel(load_package(env["package"]))
    first = run_compare(env["session"], SENSOR, store, model, reg)
    assert first.summary["network_pass"]["cached"] is False
    assert first.summary["position_error"]["n"] > 0 and first.summary["detected_fraction"] > 0.2
    again = run_compare(env["session"], SENSOR, store, NetworkModel(load_package(env["package"])), reg)
    assert again.summary["network_pass"] == dict(first.summary["network_pass"], cached=True, seconds=0.0)
    np.testing.assert_array_equal(again.pred, first.pred)
    store.derive(SENSOR, {"effects": [{"name": "strain_stiffening", "params": {"k": 30.0}}]})
    after = run_compare(env["session"], SENSOR, store, NetworkModel(load_package(env["package"])), reg)
    assert after.summary["network_pass"]["key"] == first.summary["network_pass"]["key"]
    assert after.summary["network_pass"]["cached"] is True
    c = after.table.cols
    factor = 1.0 + 30.0 * (c["depth"] / c["gel_height"]) ** 2      # runtime covariates of the matched clusters
    hit = c["matched"] > 0
    assert hit.sum() > 10 and np.any(factor[hit] > 1.01)
    np.testing.assert_allclose(after.pred[hit], first.pred[hit] * factor[hit, None], rtol=1e-9, atol=1e-12)
    assert after.summary["batch_vs_runtime_max_n"] < 1e-9


def test_cli_model_choice(env, capsys):
    parser = argparse.ArgumentParser(prog="tensortouch")
    cli.register(parser.add_subparsers(dest="command", required=True))
    base = ["compare", str(env["session"]), "--sensor", SENSOR, "--store", str(env["store"]), "--no-pictures"]
    args = parser.parse_args(base + ["--out", str(env["tmp"] / "net"), "--model", str(env["package"])])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "network pass" in out and "position error (mm)" in out
    # the contact law stays available explicitly; without a fitted law the message says how to get one
    args = parser.parse_args(base + ["--out", str(env["tmp"] / "law"), "--model", "contact-law"])
    with pytest.raises(TensorTouchError, match="--model-from"):
        args.func(args)
    args = parser.parse_args(base + ["--out", str(env["tmp"] / "law"), "--model-from", str(env["session"])])
    assert args.func(args) == 0
    assert "position error" not in capsys.readouterr().out
    # default: the installed package, when the calibration is made for its size
    models = env["tmp"] / "models"
    shutil.copytree(env["package"], models / "difference-32")
    env["monkeypatch"].setenv("TENSORTOUCH_MODELS", str(models))
    args = parser.parse_args(base + ["--out", str(env["tmp"] / "dflt")])
    assert args.func(args) == 0
    assert "network pass" in capsys.readouterr().out
    # ... and the contact law (said so) when it is not
    env["monkeypatch"].setenv("TENSORTOUCH_MODELS", str(Path(__file__).resolve().parents[1] / "exported_models"))
    from tensortouch.runtime.stages.model import installed_packages

    if installed_packages():
        assert args.func(args) == 0
        assert "note: model = the nominal contact law" in capsys.readouterr().out


def test_nominal_correction_is_fitted_on_a_calibration_session_and_used(env, capsys):
    pytest.importorskip("sklearn")
    from tensortouch.tools.workbench.nominal import NominalConfig, fit_and_store_correction

    store = CalibrationStore(env["store"])
    reg = Registry.default(entry_points=False)
    model = NetworkModel(load_package(env["package"]))
    before = run_compare(env["session"], SENSOR, store, model, reg)
    version, text = fit_and_store_correction(env["session"], SENSOR, store, model, reg,
                                             cfg=NominalConfig(min_force_n=0.02, min_frames=10, min_samples_leaf=2, max_depth=4))
    assert store.load(SENSOR).version == version and "nominal correction" in text
    after = run_compare(env["session"], SENSOR, store, model, reg)
    assert after.post is not None and after.summary["network_pass"]["cached"] is True
    hit = after.table.cols["matched"] > 0
    e0 = np.abs(np.linalg.norm(before.pred[hit], axis=1) - np.linalg.norm(before.table.meas[hit], axis=1)).mean()
    e1 = np.abs(np.linalg.norm(after.pred[hit], axis=1) - np.linalg.norm(after.table.meas[hit], axis=1)).mean()
    assert e1 < 0.8 * e0
    assert after.summary["batch_vs_runtime_max_n"] < 1e-9
