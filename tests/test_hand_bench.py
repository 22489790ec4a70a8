"""`tensortouch bench hand`: model choice (shipped package / named / synthetic) and an end-to-end run
(tiny sizes: checks the code path, not the numbers)."""
import argparse
import json
import os

import pytest

from tests.hand_util import make_package


def _args(argv):
    from tools.bench import hand_bench

    p = argparse.ArgumentParser()
    hand_bench.add_arguments(p)
    return p.parse_args(argv)


def test_model_default_is_newest_installed_package(tmp_path, monkeypatch):
    from runtime import paths
    from tools.bench.hand_bench import resolve_model

    models = tmp_path / "models"
    make_package(models / "older-32")
    newest = make_package(models / "newer-32")
    os.utime(models / "older-32" / "manifest.json", (1, 1))             # make the order explicit
    monkeypatch.setattr(paths, "models_dir", lambda: models)
    pkg, synthetic = resolve_model(None, None, tmp_path / "work")
    assert pkg.folder == newest and pkg.size == (32, 32)
    assert synthetic is True                          # the test package's manifest says "synthetic"
    pkg, _ = resolve_model("older-32", None, tmp_path / "work")           # by name
    assert pkg.folder == models / "older-32"
    pkg, _ = resolve_model(str(newest), 32, tmp_path / "work")           # by path, matching size
    assert pkg.folder == newest
    from runtime.errors import ModelPackageError
    with pytest.raises(ModelPackageError, match="input size 32x32, but --size 64"):
        resolve_model("newer-32", 64, tmp_path / "work")
    with pytest.raises(ModelPackageError):
        resolve_model("no-such-model", None, tmp_path / "work")


def test_model_synthetic_explicit_and_when_nothing_installed(tmp_path, monkeypatch):
    from runtime import paths
    from tools.bench.hand_bench import resolve_model

    make_package(tmp_path / "models" / "shipped-32")
    monkeypatch.setattr(paths, "models_dir", lambda: tmp_path / "models")
    pkg, synthetic = resolve_model("synthetic", 32, tmp_path / "w1")       # explicit, despite an installed one
    assert synthetic and pkg.size == (32, 32) and pkg.folder.parent == tmp_path / "w1"
    monkeypatch.setattr(paths, "models_dir", lambda: tmp_path / "empty")
    pkg, synthetic = resolve_model(None, 32, tmp_path / "w2")              # nothing installed
    assert synthetic and pkg.size == (32, 32)


def test_cli_arguments():
    a = _args([])
    assert a.model is None and a.size is None and a.soak_mode == "separate" and a.sensors == 4
    a = _args(["--model", "hiera-qup-128", "--soak", "60", "--soak-fps", "30", "--soak-mode", "shared"])
    assert a.model == "hiera-qup-128" and a.soak == 60 and a.soak_fps == 30 and a.soak_mode == "shared"


@pytest.mark.slow
def test_hand_bench_small(capsys):
    from tools.bench import hand_bench

    args = _args(["--model", "synthetic", "--sensors", "2", "--size", "32", "--seconds", "1.5", "--warmup", "2",
                  "--soak", "3", "--log-every", "1", "--soak-fps", "10", "--json"])
    assert hand_bench.run(args) == 0
    out = capsys.readouterr().out
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["synthetic_weights"] and summary["size"] == 32
    assert set(summary["modes"]) == set(hand_bench.MODES)
    for r in summary["modes"].values():
        assert r["min_hz"] > 5 and len(r["fingers"]) == 2 and r["received_msgs_per_s"] > 0
    soak = summary["soak"]
    assert soak["windows"] >= 2 and soak["rss_last_mb"] > 0 and soak["fps_target"] == 10
    assert set(soak["mean_hz"]) == {"f0", "f1"} and all(0 < v <= 11 for v in soak["mean_hz"].values())
    assert all(v >= 0 for v in soak["behind_frames"].values()) and soak["load1_median"] >= 0
