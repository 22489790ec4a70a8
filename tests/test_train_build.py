"""`tensortouch train all` (tools/train/build.py): stage keys and stamps, resume, and the whole chain on a
tiny configuration (hertz-fallback twin physics, 64² model, one short session: ~35 s on an idle
machine, ~2 min under load — so it runs by default, as CI's smoke test).

Everything is written under pytest's tmp folders; nothing goes to exported_models/ or calibration_store/."""
import argparse
import json
import time

import numpy as np
import pytest
from tensortouch.tools.train.build import STAGES, Build, BuildConfig, stage_keys, tiny_config
from tensortouch.tools.train.runner import run_build


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
    e = stage_keys(BuildConfig(max_bulk_ratio=6.0))                   # the label solves' locking cap: FE onwards
    assert [s for s in STAGES if a[s] != e[s]] == list(STAGES[STAGES.index("fe"):])
    assert stage_keys(BuildConfig(max_bulk_ratio=5)) == a             # the default stays out of older keys


def test_set_reaches_the_build_config():
    from tensortouch.tools.train.build import config_from_dict
    from tensortouch.tools.train.recipe import load_recipe

    r = load_recipe("hiera-qup-128", ["contact_force_n=1.5", "build.detach_force_n=1.1", "quantization_pick=first"])
    cfg = config_from_dict(r.config(r.steps()[0]), r.source)
    assert (cfg.contact_force_n, cfg.detach_force_n, cfg.quantization_pick) == (1.5, 1.1, "first")
    assert r.hash != load_recipe("hiera-qup-128").hash                  # a --set is part of the recipe
    plain = load_recipe("hiera-qup-128")
    a, b = stage_keys(cfg), stage_keys(config_from_dict(plain.config(plain.steps()[0]), plain.source))
    assert a["sessions"] == b["sessions"] and a["keypoints"] != b["keypoints"]


def test_the_shipped_recipe_uses_only_what_a_rig_has():
    from tensortouch.tools.train.build import config_from_dict
    from tensortouch.tools.train.recipe import load_recipe

    r = load_recipe("hiera-qup-128")
    for step in r.steps():
        cfg = config_from_dict(r.config(step), r.source)
        assert (cfg.fe, cfg.tables, cfg.physics) == ("resolve", "gpr", "fe") and not cfg.init_from
    held = {s["serial"] for s in r.doc["sessions"]["heldout"]}
    assert held and not held & {s["serial"] for s in r.doc["sessions"]["train"]}


@pytest.mark.parametrize("text, sets, match", [
    ('name = "x"\nbogus = 1\n', [], "unknown top-level key"),
    ('about = "no name"\n', [], "'name'"),
    ('name = "x"\n[[steps]]\nname = "b"\nafter = "a"\n', [], "names no earlier step"),
    ('name = "x"\n[[steps]]\nname = "a"\n[[steps]]\nname = "a"\n', [], "used twice"),
    ('name = "x"\n', ["epochs"], "expected key=value"),
    ('name = "x"\n', ["steps.nope.lr=1"], "no step 'nope'"),
    ('name = "x"\n[sessions]\ntrain = 3\n', [], "list of tables"),
    ('name = "x"\n[build\n', [], "not a readable recipe"),
])
def test_a_bad_recipe_is_one_line_naming_the_place(tmp_path, text, sets, match):
    from tensortouch.tools.train.recipe import RecipeError, load_recipe

    f = tmp_path / "r.toml"
    f.write_text(text)
    with pytest.raises(RecipeError, match=match):
        load_recipe(f, sets)


def test_unknown_build_fields_and_session_entries_are_refused(tmp_path):
    from tensortouch.tools.train.build import config_from_dict
    from tensortouch.tools.train.recipe import RecipeError, load_recipe

    f = tmp_path / "r.toml"
    f.write_text('name = "x"\n[build]\nepochz = 3\n')
    r = load_recipe(f)
    with pytest.raises(RecipeError, match="unknown build field.*epochz"):
        config_from_dict(r.config(r.steps()[0]), r.source)
    f.write_text('name = "x"\n[sessions]\ntrain = [ { serial = "A", seed = 1 } ]\n')
    r = load_recipe(f)
    with pytest.raises(RecipeError, match=r"sessions.train\[0\] needs serial, seed, pokes"):
        config_from_dict(r.config(r.steps()[0]), r.source)
    f.write_text('name = "x"\n[build]\nlabel_frames = "between"\n')
    r = load_recipe(f)
    with pytest.raises(RecipeError, match="label_frames = 'between'; expected one of interpolated, checked, fe, keypoint"):
        config_from_dict(r.config(r.steps()[0]), r.source)
    for bad in ("-1", '"six"', "true"):
        f.write_text(f'name = "x"\n[build]\nmax_bulk_ratio = {bad}\n')
        r = load_recipe(f)
        with pytest.raises(RecipeError, match=r"max_bulk_ratio is .*expected a number in \[0, 1000\]"):
            config_from_dict(r.config(r.steps()[0]), r.source)


def test_set_values_are_read_as_toml():
    from tensortouch.tools.train.recipe import parse_value

    assert parse_value("1e-4") == 1e-4 and parse_value("true") is True and parse_value("[1, 2]") == [1, 2]
    assert parse_value('"a b"') == "a b" and parse_value("gpr") == "gpr"


def test_a_manifest_not_built_from_a_recipe_says_so(tmp_path):
    from tensortouch.tools.train.recipe import RecipeError, load_recipe

    (tmp_path / "manifest.json").write_text('{"training": {"command": "old"}}')
    with pytest.raises(RecipeError, match="without training.recipe"):
        load_recipe(tmp_path / "manifest.json")


def test_stamps_mark_done_only_for_the_same_config(tmp_path):
    b = Build(BuildConfig(), tmp_path)
    assert not b.done("keypoints")
    b.stamp("keypoints", {"n": 1}, 0.5)
    assert b.done("keypoints") and b.read_stamp("keypoints")["n"] == 1
    assert not Build(BuildConfig(train=[]), tmp_path).done("keypoints")   # other sessions: redo


def test_cli_registers_all_dataset_evaluate_with_a_short_help():
    from tensortouch.tools.train.cli import register

    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="command")
    register(sub)
    for argv in (["train", "all", "--recipe", "tiny", "--set", "epochs=2"], ["train", "dataset", "--recipe", "x"],
                 ["train", "evaluate", "--replace"]):
        args = p.parse_args(argv)
        assert callable(args.func)
    train = sub.choices["train"]._subparsers._group_actions[0].choices["all"]
    options = [a for a in train._actions if a.option_strings and a.dest != "help"]
    assert len(options) <= 12 and all(a.help for a in options)


@pytest.fixture(scope="module")
def tiny_build(tmp_path_factory):
    """The tiny chain up to the dataset (twin sessions → keypoints → FE → correspondence → ratios → fields)."""
    root = tmp_path_factory.mktemp("build")
    cfg = tiny_config()
    t0 = time.monotonic()
    b = run_build(cfg, list(STAGES[:STAGES.index("dataset") + 1]), root)
    return b, time.monotonic() - t0


def test_tiny_build_dataset_and_resume(tiny_build):
    from tensortouch.contracts.session import load_session
    from tensortouch.tools.train.model.data import load_split, read_index

    b, first = tiny_build
    for st in STAGES[:STAGES.index("dataset") + 1]:
        assert b.done(st), st
    for spec in b.all_sessions():
        assert load_session(b.session(spec)).sensor_id == spec.serial
    idx = read_index(b.dataset)
    assert idx["size"] == [64, 64] and len(idx["samples"]) == b.read_stamp("dataset")["samples"] > 10
    x, y = load_split(b.dataset)
    assert x.dtype == np.uint8 and x.shape[1:] == (6, 64, 64) and y.shape[1:] == (15, 64, 64)
    assert not (b.dataset / ".work").exists()                             # the resume parts go once it is written
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


def test_tiny_recipe_with_a_lineage_ships_a_package_that_names_and_rebuilds_its_recipe(tiny_build, tmp_path):
    """fit (step base) → fit from base's weights (step more) → export → evaluate on the tiny dataset; the
    package verifies and runs in the runtime; its manifest names the recipe and the lineage, and rebuilds."""
    from tensortouch.runtime.stages.model import FieldModel, load_package
    from tensortouch.tools.train.export import verify_package
    from tensortouch.tools.train.recipe import RecipeError, apply_set, load_recipe
    from tensortouch.tools.train.runner import run_recipe

    b, _ = tiny_build
    tiny = load_recipe("tiny")
    recipe = type(tiny)(tiny.name, tiny.source, {**tiny.doc, "steps": [
        {"name": "base"}, {"name": "more", "after": "base", "build": {"lr": 1e-4}}]})
    models = tmp_path / "models"
    b = run_recipe(recipe, ["fit", "export", "evaluate"], b.root, "tensortouch train all --recipe tiny",
                   overrides={"models_dir": str(models)})
    folder = models / recipe.name
    man = verify_package(folder)
    t = man["training"]
    assert t["command"] == "tensortouch train all --recipe tiny"
    assert t["data_hash"] == b.read_stamp("dataset")["data_hash"] and t["wall_time_s"] > 0
    assert t["recipe"]["name"] == "tiny-smoke" and t["recipe"]["hash"] == recipe.hash
    assert [s["step"] for s in t["lineage"]] == ["base", "more"] and t["lineage"][1]["after"] == "base"
    assert t["init_from"]["state_dict"].endswith(t["lineage"][0]["fit_run"] + "/best.pt")
    assert load_recipe(folder / "manifest.json").hash == recipe.hash           # the manifest rebuilds it
    # the export measured the package's contact threshold on training sessions (null = no clean value)
    assert man["runtime"]["measured"]["rest_frames"] > 0 and "threshold_n" in man["runtime"]["contacts"]
    m = FieldModel(load_package(folder))
    assert m(np.zeros((6, 64, 64), np.float32)).shape == (15, 64, 64)
    summ = json.loads((b.root / "eval" / "summary.json").read_text())
    assert set(summ) == {s.name for s in b.cfg.heldout}
    s = summ[b.cfg.heldout[0].name]
    assert s["contact_samples"] > 0 and "force_mag_mae_n" in s and s["rest_frames"] > 0
    other = apply_set(recipe, "steps.more.lr=2e-4")                           # another recipe, same package name
    with pytest.raises(RecipeError, match="give --replace"):
        run_recipe(other, ["export"], b.root, overrides={"models_dir": str(models)})


def test_manifest_paths_name_the_cache_as_a_checkout_has_it(tmp_path, monkeypatch):
    from tensortouch.contracts.paths import ROOT
    from tensortouch.tools.train.package import repo_relative

    monkeypatch.setenv("TENSORTOUCH_CACHE", str(tmp_path / "elsewhere"))
    assert repo_relative(tmp_path / "elsewhere" / "train" / "x" / "runs" / "fit-1") == "cache/train/x/runs/fit-1"
    assert repo_relative(ROOT / "tools" / "train" / "recipes" / "a.toml") == "tools/train/recipes/a.toml"
    assert repo_relative(tmp_path / "other") == str((tmp_path / "other").resolve())
