"""The package's contact threshold (tools/train/threshold.py) and its use by the runtime."""
import json
from types import SimpleNamespace

import numpy as np
import pytest
from tensortouch.runtime.pipeline import PipelineConfig
from tensortouch.runtime.stages.contacts import ContactConfig
from tensortouch.tools.train.threshold import ThresholdConfig, _has_core, budget_rule, choose, record, rest_frames


def sweep(rest_fp, hit, n_rest=100, n_contact=50, name="S"):
    return {"session": f"/x/{name}", "rest_frames": n_rest, "contact_frames": n_contact,
            "rest_with_core": list(rest_fp), "contact_with_core": list(hit)}


def test_has_core_needs_min_pixels_above_the_threshold():
    mag = np.zeros((16, 16))
    mag[4, 4] = mag[4, 5] = 0.01                     # a 2-pixel speck
    assert not _has_core(mag, 0.002, 3)
    mag[5, 5] = 0.01                                 # 8-connected third pixel
    assert _has_core(mag, 0.002, 3) and not _has_core(mag, 0.01, 3)


def test_choose_takes_the_lowest_clean_grid_value_over_all_sessions():
    cfg = ThresholdConfig(grid=(0.001, 0.0015, 0.002, 0.0025))
    a = sweep([9, 2, 0, 0], [50, 50, 50, 40], name="A")
    b = sweep([4, 0, 0, 0], [50, 49, 45, 30], name="B")
    out = choose([a, b], cfg)
    assert out["threshold_n"] == pytest.approx(0.002 * 4 / 3, abs=1e-5)
    m = out["measured"]
    assert m["rest_frames_with_core"] == [13, 2, 0, 0] and m["sessions"] == ["A", "B"]
    assert m["detected_at_n"] == 0.0025 and m["contact_detected_fraction"] == pytest.approx(70 / 100)
    dirty = choose([sweep([3, 2, 1, 1], [1, 1, 1, 1])], cfg)
    assert dirty["threshold_n"] is None and dirty["measured"]["rest_frames_with_core"] == [3, 2, 1, 1]


def test_release_and_approach_frames_are_not_rest_but_ft_noise_is():
    """A frame read below rest_n just after a release still holds a real touch; an F/T noise spike
    between rest_n and rest_touch_n drops only itself."""
    cfg = ThresholdConfig()                                  # rest 0.05 N, touch 0.1 N, guard 0.1 s
    t = np.arange(60) / 30.0
    f = np.full(60, 0.03)
    f[20:30] = 1.0                                           # a poke
    f[30] = 0.034                                            # the release frame (TWIN-T66's case)
    f[45] = 0.07                                             # a noise spike at rest
    rest = rest_frames(t, f, cfg)
    assert not rest[30] and not rest[17] and not rest[32]    # within 0.1 s of the poke
    assert rest[16] and rest[33] and rest[44] and rest[46] and not rest[45]
    assert not rest[20:30].any() and rest[:16].all() and rest[50:].all()
    assert rest_frames(t, np.full(60, 0.03), cfg).all()      # never touched: all at rest
    loose = ThresholdConfig(rest_guard_s=0.0)
    assert rest_frames(t, f, loose)[30]                      # without the guard: the old rule


def test_the_runtime_takes_the_threshold_from_the_manifest(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"name": "m", "files": {}}))
    record(tmp_path, {"threshold_n": 0.00275, "measured": {"rule": "test"}})
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert man["files"] == {} and man["runtime"]["contacts"]["threshold_n"] == 0.00275
    assert PipelineConfig.for_package(SimpleNamespace(manifest=man)).contacts.threshold_n == 0.00275
    for old in ({"name": "old"}, {"runtime": {"contacts": {"threshold_n": None}}}):
        assert PipelineConfig.for_package(SimpleNamespace(manifest=old)).contacts.threshold_n == ContactConfig().threshold_n


def test_choose_weak_takes_the_rest_maximum_times_the_margin_and_the_best_light_detection():
    cfg = ThresholdConfig(grid=(0.001, 0.002), weak_grid=(0.0005, 0.001), weak_margin=1.5)
    a = dict(sweep([1, 0], [10, 10], name="A"), rest_weak_max=[0.2, 0.05],
             light={"core": [[1, 0], [1, 1], [0, 0]], "weak": [[0.5, 0.2], [0.1, 0.05], [0.25, 0.08]]})
    b = dict(sweep([0, 0], [10, 10], name="B"), rest_weak_max=[0.1, 0.02], light={"core": [], "weak": []})
    out = choose([a, b], cfg)
    # strong threshold: grid[1] = 0.002 -> ×4/3; the light frames detected at it: frame 2 only
    assert out["threshold_n"] == pytest.approx(0.002 * 4 / 3, abs=1e-5)
    m = out["measured"]
    assert m["weak_min_total_n"] == pytest.approx([0.3, 0.075]) and m["light_frames"] == 3
    # w=0.0005 (F_min 0.3): frames 1 (0.5) + 2 -> 2/3; w=0.001 (F_min 0.075): frames 1, 2, 3 -> 3/3
    assert m["light_detected_by_weak_n"] == pytest.approx([2 / 3, 1.0], abs=1e-4)
    assert out["weak_threshold_n"] == 0.001 and out["min_total_n"] == pytest.approx(0.075)
    assert m["light_detected_strong_only"] == pytest.approx(1 / 3)
    # old sweeps without light frames: the rule stays off
    old = choose([sweep([1, 0], [10, 10])], cfg)
    assert old["weak_threshold_n"] is None and old["min_total_n"] is None


def test_the_runtime_takes_the_light_touch_rule_from_the_manifest():
    man = {"runtime": {"contacts": {"threshold_n": 0.002, "weak_threshold_n": 0.0012, "min_total_n": 0.04}}}
    c = PipelineConfig.for_package(SimpleNamespace(manifest=man)).contacts
    assert (c.threshold_n, c.weak_threshold_n, c.min_total_n) == (0.002, 0.0012, 0.04)
    off = {"runtime": {"contacts": {"threshold_n": 0.002, "weak_threshold_n": None, "min_total_n": None}}}
    assert PipelineConfig.for_package(SimpleNamespace(manifest=off)).contacts.min_total_n == 0.0


def budget_frames():
    """10 rest frames (one with a core at the lower strong threshold; weak-component totals 0.5, 0.03, 0.02,
    0.01 N, the rest 0) and 4 touch frames, on grid (0.001, 0.002) N and one weak threshold 0.0005 N."""
    rc = np.zeros((10, 2), bool)
    rc[0, 0] = True
    rw = np.zeros((10, 1))
    rw[:4, 0] = 0.5, 0.03, 0.02, 0.01
    tc = np.array([[1, 1], [1, 0], [0, 0], [0, 0]], bool)
    tw = np.array([[0.5], [0.2], [0.04], [0.01]])
    return rc, rw, tc, tw


def test_budget_rule_hand_worked():
    rc, rw, tc, tw = budget_frames()
    # one phantom in 10 allowed, half of it (none) to the strong threshold: 0.001 N holds a core on frame 0, so the
    # strong threshold is 0.002 N. The weak rule may then keep one rest frame (0.5 N) and must stay above the next,
    # 0.03 N: the 0.2 and 0.04 N touches join the 0.5 N one, 3 of 4.
    best = budget_rule(rc, rw, tc, tw, (0.001, 0.002), (0.0005,), 0.1, 0.02)
    assert (best["threshold_n"], best["weak_threshold_n"]) == (0.002, 0.0005)
    assert best["min_total_n"] == pytest.approx(0.03001)
    assert best["detected_fraction"] == 0.75 and best["rest_fraction"] == pytest.approx(0.1)
    # no phantom allowed: 0.001 N is out (frame 0); at 0.002 N the weak rule could only sit above 0.5 N and adds
    # nothing, so the rule stays off (the stricter of equals)
    best = budget_rule(rc, rw, tc, tw, (0.001, 0.002), (0.0005,), 0.0, 0.02)
    assert (best["threshold_n"], best["weak_threshold_n"], best["min_total_n"]) == (0.002, None, None)
    assert best["detected_fraction"] == 0.25 and best["rest_fraction"] == 0.0
    # the floor: min_total_n never below it
    best = budget_rule(rc, np.zeros_like(rw), tc, tw, (0.002,) * 2, (0.0005,), 0.0, 0.05)
    assert best["min_total_n"] == 0.05 and best["detected_fraction"] == 0.5      # 0.2 N reaches it, 0.04 N does not
    # a weak threshold at or above the strong one is no rule
    assert budget_rule(rc, rw, tc, tw, (0.0005, 0.0005), (0.0005,), 0.1, 0.02)["weak_threshold_n"] is None


def test_budget_rule_refuses_and_gives_up():
    rc, rw, tc, tw = budget_frames()
    rc[:, :] = True                                   # every rest frame has a core at every grid value
    assert budget_rule(rc, rw, tc, tw, (0.001, 0.002), (0.0005,), 0.1, 0.02) is None
    with pytest.raises(ValueError, match="rest_weak .* expected \\(frames, 1\\)"):
        budget_rule(rc, np.zeros((10, 2)), tc, tw, (0.001, 0.002), (0.0005,), 0.1, 0.02)
    with pytest.raises(ValueError, match="budget 1.0"):
        budget_rule(rc, rw, tc, tw, (0.001, 0.002), (0.0005,), 1.0, 0.02)


def test_choose_with_a_rest_budget_reads_the_sweeps_frames():
    rc, rw, tc, tw = budget_frames()
    a = dict(sweep([1, 0], [3, 1], n_rest=10, n_contact=4, name="V1"), rest_core=rc, rest_weak=rw, touch_core=tc,
             touch_weak=tw)
    cfg = ThresholdConfig(grid=(0.001, 0.002), weak_grid=(0.0005,), rest_budget=0.1, min_total_floor_n=0.02)
    out = choose([a], cfg)
    assert (out["threshold_n"], out["weak_threshold_n"]) == (0.002, 0.0005)
    assert out["min_total_n"] == pytest.approx(0.03001)
    m = out["measured"]
    assert m["rest_frames"] == 10 and m["touch_frames"] == 4 and m["sessions"] == ["V1"]
    assert m["touch_detected_fraction"] == 0.75 and m["rest_with_core_fraction"] == pytest.approx(0.1)
    assert m["contact_detected_fraction"] == 0.25 and "0.2 N" in m["rule"]


def test_threshold_cli_refuses_the_sealed_set_and_bad_budgets(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    pkg = Path(__file__).resolve().parents[1] / "exported_models" / "hiera-qup-128"

    def cli(*args):
        r = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", "train", "threshold", "--package",
                            str(pkg), *args], capture_output=True, text=True, timeout=300)
        return r.returncode, [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
    rc, lines = cli("--units", "sealed", "--units-root", str(tmp_path))
    assert rc == 2 and len(lines) == 1 and "never used for a choice" in lines[0], lines
    rc, lines = cli("--units", "validation", "--rest-budget", "1.5")
    assert rc == 2 and len(lines) == 1 and "--rest-budget 1.5" in lines[0], lines
    rc, lines = cli()
    assert rc == 2 and len(lines) == 1 and "--units SET" in lines[0], lines


def test_fixed_support_keeps_the_builds_reach(tmp_path):
    from tensortouch.tools.train.threshold import fixed_support

    def pkg(contacts, rule):
        (tmp_path / "manifest.json").write_text(json.dumps({"runtime": {"contacts": contacts, "measured": {"support_rule": rule}}}))
        return tmp_path
    assert fixed_support(pkg({"support_radius_px": 20.0, "support_floor_n": 0.0}, "fixed by the build: 20 px, floor 0 N")) == 20.0
    assert fixed_support(pkg({"support_radius_px": 9.0, "support_floor_n": 0.004}, "measured on ...")) is None
    assert fixed_support(pkg({"support_radius_px": None, "support_floor_n": None}, "")) is None


def test_repeated_session_flags_are_all_kept():
    """`--session A --session B C` is three sessions (a repeated nargs flag used to keep only the last)."""
    import argparse

    from tensortouch.tools.train.threshold import add_arguments
    from tensortouch.tools.workbench.cli import _model_args

    ap = argparse.ArgumentParser()
    add_arguments(ap)
    args = ap.parse_args(["--package", "p", "--session", "a:s", "--session", "b:s", "c:s"])
    assert args.session == ["a:s", "b:s", "c:s"]
    assert ap.parse_args(["--package", "p"]).session == []
    wb = argparse.ArgumentParser()
    _model_args(wb)
    got = wb.parse_args(["--model-from", "c1", "--model-from", "c2", "--own-error-from", "o1", "--own-error-from", "o2"])
    assert got.model_from == ["c1", "c2"] and got.own_error_from == ["o1", "o2"]
    assert wb.parse_args([]).model_from is None


def test_split_only_writes_split_dip_and_leaves_the_other_settings(tmp_path):
    """`train threshold --split-only` on the shipped demo with a copy of the shipped package: the manifest
    gains runtime.contacts.split_dip (a candidate or null) and the split_* measurement; nothing else moves."""
    import shutil

    from tensortouch.contracts.paths import ROOT as REPO
    from tensortouch.contracts.store import CalibrationStore
    from tensortouch.tools.train.threshold import measure_split

    model, demo = REPO / "exported_models" / "hiera-qup-128", REPO / "runtime" / "demo"
    if not (model / "manifest.json").is_file() or not (demo / "session.json").is_file():
        pytest.skip("no shipped model or demo in this checkout")
    pkg = tmp_path / "pkg"
    shutil.copytree(model, pkg)
    before = json.loads((pkg / "manifest.json").read_text())
    cal = CalibrationStore(REPO / "calibration_store").load(json.loads((demo / "session.json").read_text())["sensor_id"])
    out = measure_split(pkg, [(demo, cal)], command="tensortouch train threshold --split-only")
    after = json.loads((pkg / "manifest.json").read_text())
    assert after["runtime"]["contacts"]["split_dip"] == out["split_dip"]
    assert out["split_dip"] is None or 0 < out["split_dip"] < 1
    m = after["runtime"]["measured"]
    assert m["split_candidates"][0] == 0.0 and len(m["split_two_apart_frames"]) == len(m["split_candidates"])
    assert m["split_command"].endswith("--split-only") and m["split_sessions"] == ["demo"]
    for k, v in before["runtime"]["contacts"].items():
        if k != "split_dip":
            assert after["runtime"]["contacts"][k] == v
    def rest(measured):
        return {k: v for k, v in measured.items() if not k.startswith("split")}
    assert rest(m) == rest(before["runtime"]["measured"])


def test_record_writes_the_tare_the_settings_were_measured_with(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"name": "m", "files": {}}))
    record(tmp_path, {"threshold_n": 0.001, "measured": {"rule": "test"}})
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert "tare" not in man["runtime"] and PipelineConfig.for_package(SimpleNamespace(manifest=man)).tare is False
    record(tmp_path, {"threshold_n": 0.001, "measured": {"rule": "test"}}, tare=True)
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert man["runtime"]["tare"] is True and PipelineConfig.for_package(SimpleNamespace(manifest=man)).tare is True


def test_split_only_with_the_tare_measures_on_tared_fields_and_records_it(tmp_path):
    """`--split-only --tare on` on the shipped demo with a copy of the runtime's default package: runtime.tare is written
    with split_dip; the package on disk is untouched until then (the sweep sets it in memory)."""
    import shutil

    from tensortouch.contracts.paths import ROOT as REPO
    from tensortouch.contracts.store import CalibrationStore
    from tensortouch.runtime.stages.model import ModelPackageError, find_package
    from tensortouch.tools.train.threshold import _load, measure_split

    try:
        model = find_package(root=REPO / "exported_models").folder
    except ModelPackageError:
        pytest.skip("no shipped package in this checkout")
    demo = REPO / "runtime" / "demo"
    if not (demo / "session.json").is_file():
        pytest.skip("no shipped demo in this checkout")
    pkg = tmp_path / "pkg"
    shutil.copytree(model, pkg)
    before = (json.loads((pkg / "manifest.json").read_text()).get("runtime") or {}).get("tare")
    assert PipelineConfig.for_package(_load(pkg, True)).tare is True
    assert PipelineConfig.for_package(_load(pkg, False)).tare is False
    assert (json.loads((pkg / "manifest.json").read_text()).get("runtime") or {}).get("tare") == before
    cal = CalibrationStore(REPO / "calibration_store").load(json.loads((demo / "session.json").read_text())["sensor_id"])
    out = measure_split(pkg, [(demo, cal)], tare=True)
    after = json.loads((pkg / "manifest.json").read_text())
    assert after["runtime"]["tare"] is True and after["runtime"]["contacts"]["split_dip"] == out["split_dip"]
