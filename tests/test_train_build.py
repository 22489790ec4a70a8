"""`tensortouch train all` (tools/train/build.py): stage keys and stamps, resume, and the whole chain on a
tiny configuration (hertz-fallback twin physics, 64² model, one short session: ~35 s on an idle
machine, ~2 min under load — so it runs by default, as CI's smoke test).

Everything is written under pytest's tmp folders; nothing goes to exported_models/ or calibration_store/."""
import argparse
import json
import time

import numpy as np
import pytest

from tools.train.build import STAGES, Build, BuildConfig, run_build, stage_keys, tiny_config


def test_stage_keys_change_only_downstream():
    a = stage_keys(BuildConfig())
    b = stage_keys(BuildConfig(epochs=BuildConfig().epochs + 1))
    changed = [s for s in STAGES if a[s] != b[s]]
    assert changed == ["fit", "export", "evaluate"]
    c = stage_keys(BuildConfig(contact_stride=3))
    assert [s for s in STAGES if a[s] != c[s]] == list(STAGES[STAGES.index("dataset"):])
    d = stage_keys(BuildConfig(contact_force_n=1.5, detach_force_n=1.1))  # stage-1 thresholds: all but sessions
    assert [s for s in STAGES if a[s] != d[s]] == list(STAGES[STAGES.index("keypoints"):])
    cfg = BuildConfig.from_dict(json.loads(json.dumps(BuildConfig().to_dict())))
    assert stage_keys(cfg) == a                                       # round trip through JSON


def test_contact_threshold_flags_reach_the_build_config():
    from tools.train.build import config_from_args
    from tools.train.cli import register

    p = argparse.ArgumentParser()
    register(p.add_subparsers(dest="command"))
    cfg = config_from_args(p.parse_args(["train", "all", "--contact-force", "1.5", "--detach-force", "1.1"]))
    assert (cfg.contact_force_n, cfg.detach_force_n) == (1.5, 1.1)
    assert (BuildConfig().contact_force_n, BuildConfig().detach_force_n) == (0.5, 0.37)


def test_int8_calibration_flags_reach_the_export_key():
    """Only the export is redone for another int8 calibration; the shipped package's older export
    (first 32 samples) is reproduced with --calibration-samples 32 --calibration-pick first."""
    from tools.train.build import config_from_args
    from tools.train.cli import register

    p = argparse.ArgumentParser()
    register(p.add_subparsers(dest="command"))
    old = config_from_args(p.parse_args(["train", "all", "--calibration-samples", "32", "--calibration-pick", "first"]))
    new = BuildConfig()
    assert (old.calibration_samples, old.calibration_pick) == (32, "first")
    assert (new.calibration_samples, new.calibration_pick) == (128, "spread")
    a, b = stage_keys(old), stage_keys(new)
    assert a["fit"] == b["fit"] and a["export"] != b["export"]


def test_a_recipe_includes_others_sessions_once(tmp_path):
    from tools.train.build import read_recipe

    a = {"serial": "TWIN-A", "seed": 1, "pokes": 5}
    b = {"serial": "TWIN-B", "seed": 2, "pokes": 8, "trajectory": {"kinds": ["slide"]}}
    (tmp_path / "one.json").write_text(json.dumps({"_about": "x", "train": [a], "epochs": 3}))
    (tmp_path / "two.json").write_text(json.dumps({"train": [a, b]}))
    (tmp_path / "both.json").write_text(json.dumps({"include": ["one.json", "two.json"], "lr": 1e-4}))
    d = read_recipe(tmp_path / "both.json")
    assert d == {"train": [a, b], "lr": 1e-4}                 # only the sessions come from included recipes
    assert [s.serial for s in BuildConfig.from_dict(d).train] == ["TWIN-A", "TWIN-B"]


def test_stamps_mark_done_only_for_the_same_config(tmp_path):
    b = Build(BuildConfig(), tmp_path)
    assert not b.done("keypoints")
    b.stamp("keypoints", {"n": 1}, 0.5)
    assert b.done("keypoints") and b.read_stamp("keypoints")["n"] == 1
    assert not Build(BuildConfig(train=[]), tmp_path).done("keypoints")   # other sessions: redo


def test_cli_registers_all_dataset_evaluate():
    from tools.train.cli import register

    p = argparse.ArgumentParser()
    register(p.add_subparsers(dest="command"))
    for argv in (["train", "all", "--tiny", "--epochs", "2"], ["train", "dataset", "--build", "x"],
                 ["train", "evaluate", "--name", "m"]):
        args = p.parse_args(argv)
        assert callable(args.func)
    args = p.parse_args(["train", "all", "--tiny", "--epochs", "2", "--tables", "truth"])
    from tools.train.build import config_from_args

    cfg = config_from_args(args)
    assert cfg.epochs == 2 and cfg.physics == "hertz-fallback" and cfg.size == 64


@pytest.fixture(scope="module")
def tiny_build(tmp_path_factory):
    """The tiny chain up to the dataset (twin sessions → keypoints → FE → correspondence → ratios → fields)."""
    root = tmp_path_factory.mktemp("build")
    cfg = tiny_config()
    t0 = time.monotonic()
    b = run_build(cfg, list(STAGES[:STAGES.index("dataset") + 1]), root)
    return b, time.monotonic() - t0


def test_tiny_build_dataset_and_resume(tiny_build):
    from runtime.session import load_session
    from tools.train.model.data import load_split, read_index

    b, first = tiny_build
    for st in STAGES[:STAGES.index("dataset") + 1]:
        assert b.done(st), st
    for spec in b.all_sessions():
        assert load_session(b.session(spec)).sensor_id == spec.serial
    idx = read_index(b.dataset)
    assert idx["size"] == [64, 64] and len(idx["samples"]) == b.read_stamp("dataset")["samples"] > 10
    x, y = load_split(b.dataset)
    assert x.dtype == np.uint8 and x.shape[1:] == (6, 64, 64) and y.shape[1:] == (15, 64, 64)
    rest = b.read_stamp("dataset")["rest"]
    assert rest > 0                                                      # no-contact samples are in the data
    assert y.reshape(len(y), 15, -1).std(axis=2).max() > 0               # contact samples carry fields
    ratios = json.loads((b.root / "simreal" / f"{b.cfg.train[0].name}.json").read_text())
    assert ratios["ratios"] and set(ratios["ratios"]) <= {"0", "1"}
    assert all(0.5 <= r <= 2.0 for v in ratios["ratios"].values() for r in v["ratio"])
    stamps = {s: b.read_stamp(s)["finished"] for s in STAGES[:STAGES.index("dataset") + 1]}
    t0 = time.monotonic()
    again = run_build(b.cfg, list(stamps), b.root)                        # everything stamped: skipped
    assert time.monotonic() - t0 < max(5.0, 0.2 * first)
    assert {s: again.read_stamp(s)["finished"] for s in stamps} == stamps


def test_tiny_chain_ships_a_package_the_runtime_loads(tiny_build, tmp_path):
    """fit → export → evaluate on the tiny dataset; the package verifies and runs in the runtime."""
    from runtime.model import FieldModel, load_package
    from tools.train.export import verify_package

    b, _ = tiny_build
    b.cfg.models_dir = str(tmp_path / "models")
    b.command = "tensortouch train all --tiny"
    b = run_build(b.cfg, ["fit", "export", "evaluate"], b.root, b.command)
    folder = tmp_path / "models" / b.cfg.name
    man = verify_package(folder)
    assert man["training"]["command"] == "tensortouch train all --tiny"
    assert man["training"]["data_hash"] == b.read_stamp("dataset")["data_hash"]
    assert man["training"]["wall_time_s"] > 0
    # the export measured the package's contact threshold on training sessions (null = no clean value)
    assert man["runtime"]["measured"]["rest_frames"] > 0 and "contact_threshold_n" in man["runtime"]
    m = FieldModel(load_package(folder))
    assert m(np.zeros((6, 64, 64), np.float32)).shape == (15, 64, 64)
    summ = json.loads((b.root / "eval" / "summary.json").read_text())
    assert set(summ) == {s.name for s in b.cfg.heldout}
    s = summ[b.cfg.heldout[0].name]
    assert s["contact_samples"] > 0 and "force_mag_mae_n" in s and s["rest_frames"] > 0
