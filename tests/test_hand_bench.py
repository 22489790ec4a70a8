"""`tensortouch bench hand`: model choice (shipped package / named / synthetic) and an end-to-end run
(tiny sizes: checks the code path, not the numbers)."""
import argparse
import json
import os

import pytest

from tests.hand_util import make_package


def _args(argv):
    from tensortouch.tools.bench import hand_bench

    p = argparse.ArgumentParser()
    hand_bench.add_arguments(p)
    return p.parse_args(argv)


def test_model_default_is_newest_installed_package(tmp_path, monkeypatch):
    from tensortouch.contracts import paths
    from tensortouch.tools.bench.hand_bench import resolve_model

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
    from tensortouch.contracts.errors import ModelPackageError
    with pytest.raises(ModelPackageError, match="input size 32x32, but --size 64"):
        resolve_model("newer-32", 64, tmp_path / "work")
    with pytest.raises(ModelPackageError):
        resolve_model("no-such-model", None, tmp_path / "work")


def test_newest_package_is_the_latest_built_not_the_latest_checked_out(tmp_path):
    """A fresh clone gives every manifest the same file time: the manifest's `created` decides."""
    import json

    from tensortouch.runtime.stages.model import find_package

    models = tmp_path / "models"
    built = {"b-built-first-32": "2026-12-01T10:00:00Z", "a-built-last-32": "2026-12-06T23:00:00Z"}
    for name, created in built.items():
        make_package(models / name)
        man = models / name / "manifest.json"
        man.write_text(json.dumps({**json.loads(man.read_text()), "created": created}))
        os.utime(man, (1000, 1000))                                   # same file time, as after a clone
    assert find_package(None, root=models).folder.name == "a-built-last-32"
    os.utime(models / "b-built-first-32" / "manifest.json", (2000, 2000))     # a later touch does not matter
    assert find_package(None, root=models).folder.name == "a-built-last-32"


def test_model_synthetic_explicit_and_when_nothing_installed(tmp_path, monkeypatch):
    from tensortouch.contracts import paths
    from tensortouch.tools.bench.hand_bench import resolve_model

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
    assert a.source == "demo" and _args(["--source", "synthetic"]).source == "synthetic"
    assert a.fields_every == 1 and _args(["--fields-every", "3"]).fields_every == 3


def test_fields_every_below_1_is_refused():
    from tensortouch.contracts.errors import CommandError
    from tensortouch.tools.bench import hand_bench

    with pytest.raises(CommandError, match="--fields-every 0"):
        hand_bench.run(_args(["--fields-every", "0"]))


def test_setup_demo_source_replays_the_demo_through_each_sensors_copy_of_its_calibration(tmp_path):
    from tensortouch.contracts.store import CalibrationStore
    from tensortouch.tools.bench import hand_bench
    from tensortouch.tools.bench.runtime_bench import demo_size

    size = demo_size()
    pkg, synthetic, videos, serials = hand_bench._setup(tmp_path, 3, "synthetic", size, source="demo")
    assert synthetic and serials == ["bench-0", "bench-1", "bench-2"] and len(set(videos)) == 1
    assert videos[0].is_file()
    assert all(CalibrationStore(tmp_path / "store").load(s).model_size == (size, size) for s in serials)


@pytest.mark.slow
def test_hand_bench_small(capsys):
    from tensortouch.tools.bench import hand_bench

    args = _args(["--model", "synthetic", "--source", "synthetic", "--sensors", "2", "--size", "32", "--seconds", "1.5", "--warmup", "2",
                  "--soak", "3", "--log-every", "1", "--soak-fps", "10", "--json"])
    assert hand_bench.run(args) == 0
    out = capsys.readouterr().out
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["synthetic_weights"] and summary["size"] == 32
    assert set(summary["modes"]) == set(hand_bench.MODES)
    for r in summary["modes"].values():
        assert r["min_hz"] > 5 and len(r["fingers"]) == 2 and r["received_msgs_per_s"] > 0
        assert 0 < r["cpu_share"] <= (os.cpu_count() or 2) + 0.1 and r["cpu_ms_per_frame"] > 0
    soak = summary["soak"]
    assert soak["windows"] >= 2 and soak["rss_last_mb"] > 0 and soak["fps_target"] == 10
    assert set(soak["mean_hz"]) == {"f0", "f1"} and all(0 < v <= 11 for v in soak["mean_hz"].values())
    assert all(v >= 0 for v in soak["behind_frames"].values()) and soak["load1_median"] >= 0
    assert 0 < soak["cpu_share_total"] <= (os.cpu_count() or 2) + 0.1 and "whole soak" in out


def _rows(n=40, leak_mb_per_h=0.0, p99_ms=20.0):
    rows = []
    for i in range(1, n + 1):
        t = 30.0 * i
        rows.append({"t_s": t, "rss_mb": 250.0 + leak_mb_per_h * t / 3600, "load1": 2.0 + (i % 3), "cpu_share": 1.25,
                     "fingers": {f"f{k}": {"hz": 30.0, "p50_ms": 8.0, "p99_ms": p99_ms + k, "state": "running",
                                           "frames": int(30 * t) - 3 * k, "behind": float(3 * k)}
                                 for k in range(4)}})
    return rows


def test_soak_summary_measures_drift_rate_and_backlog():
    from tensortouch.tools.bench.hand_bench import summarize_soak

    flat = summarize_soak(_rows(), 30.0)
    assert flat["rss_slope_mb_per_h"] == pytest.approx(0.0, abs=1e-6)
    leak = summarize_soak(_rows(leak_mb_per_h=12.0), 30.0)
    assert leak["rss_slope_mb_per_h"] == pytest.approx(12.0, rel=1e-6)
    assert flat["mean_hz"]["f0"] == pytest.approx(30.0) and flat["mean_hz"]["f3"] < 30.0
    assert flat["behind_frames"] == {"f0": 0.0, "f1": 3.0, "f2": 6.0, "f3": 9.0}
    assert flat["p99_first_quarter_ms"] == pytest.approx(23.0) and flat["load1_median"] == pytest.approx(3.0)
    assert flat["duration_s"] == 1200.0 and flat["windows"] == 40 and flat["cpu_share_median"] == 1.25


def test_soak_plot_and_from_log(tmp_path, capsys):
    import cv2

    log = tmp_path / "soak.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in _rows(12, leak_mb_per_h=6.0)))
    png = tmp_path / "soak.png"
    from tensortouch.tools.bench import hand_bench

    assert hand_bench.run(_args(["--from-log", str(log), "--soak-fps", "30", "--plot", str(png), "--json"])) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["soak"]
    assert out["windows"] == 12 and out["rss_slope_mb_per_h"] == pytest.approx(6.0, rel=1e-6)
    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 200 and img.shape[1] > 300
