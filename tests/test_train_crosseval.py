"""Cross-evaluation (tools/train/crosseval.py): recipe keys, the sealed set scored whole and alone, the
shipped demo."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _cli(*args, cwd=None):
    r = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", *args], capture_output=True, text=True, cwd=cwd, timeout=300)
    return r.returncode, [ln for ln in r.stdout.splitlines() + r.stderr.splitlines() if ln.strip()]


def test_crosseval_sealed_refuses_partial_or_mixed(tmp_path):
    pkg = ROOT / "exported_models" / "hiera-qup-128"
    rc, lines = _cli("train", "crosseval", "--package", str(pkg), "--units", "sealed", "--units-root", str(tmp_path))
    assert rc == 2 and len(lines) == 1 and "scored whole" in lines[0], lines
    rc, lines = _cli("train", "crosseval", "--package", str(pkg), "--units", "sealed", "--recipe", "tiny")
    assert rc == 2 and len(lines) == 1 and "scored alone" in lines[0], lines


def test_recipe_key_ignores_fit_seed_only():
    from types import SimpleNamespace

    from tensortouch.tools.train.crosseval import recipe_key

    def pkg(build):
        return SimpleNamespace(manifest={"training": {"recipe": {"doc": {"name": "r", "build": build}}}})

    assert recipe_key(pkg({"epochs": 3, "fit_seed": 1})) == recipe_key(pkg({"epochs": 3, "fit_seed": 2}))
    assert recipe_key(pkg({"epochs": 3})) != recipe_key(pkg({"epochs": 4}))
    assert recipe_key(SimpleNamespace(manifest={"training": {}})) is None


def test_crosseval_scorecard_on_the_shipped_demo(tmp_path):
    """End to end on real parts: the shipped int8 package through the runtime on the shipped demo, twice
    (a copy counts as a second fit of the same recipe): per-session lines, the scorecard with CIs and
    breakdowns, the fit-seed spread (flagged: fewer than three), the JSON file."""
    from tensortouch.contracts.paths import ROOT as REPO

    model, demo, store = REPO / "exported_models" / "hiera-qup-128", REPO / "runtime" / "demo", REPO / "calibration_store"
    if not (model / "manifest.json").is_file() or not (demo / "session.json").is_file():
        pytest.skip("no shipped model or demo in this checkout")
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(model, copy)
    out = tmp_path / "card.json"
    rc, lines = _cli("train", "crosseval", "--package", str(model), "--package", str(copy), "--session", str(demo),
                     "--store", str(store), "--boot", "200", "--json", str(out))
    assert rc == 0, lines[-5:]
    assert any(ln.startswith("scorecard") for ln in lines) and any("fewer than 3" in ln for ln in lines), lines
    doc = json.loads(out.read_text())
    card = doc["scorecards"][str(model)]
    o = card["overall"]
    assert card["units"] == 1 and card["pokes"] >= 2 and o["contacts"] >= 20
    assert 0.0 <= o["miss_rate"]["mean"] <= 0.2 and o["force_mae_n"]["ci"][0] <= o["force_mae_n"]["mean"] <= o["force_mae_n"]["ci"][1]
    assert 0.0 < o["direction_error_deg"]["mean"] < 45.0 and o["phantom_rate"]["n"] > 0
    # the field split at the measured tips is scored on every contact, and reads like the clusters there
    assert o["split_force_mae_n"]["n"] == o["contacts"] and 0.0 < o["split_force_mae_n"]["mean"] < 1.0
    assert any("field split at the tips" in ln for ln in lines)
    assert set(card["by indenter"]) <= {"cylinder3", "flat4"} and card["by indenter"]
    assert sum(b["contacts"] for b in card["by force"].values()) == o["contacts"]
    assert sum(b["contacts"] for b in card["by contacts"].values()) == o["contacts"]
    assert doc["scorecards"][str(copy)]["overall"]["force_mae_n"] == o["force_mae_n"]
    (spread,) = doc["fit_seeds"].values()
    assert spread["force_mae_n"]["n"] == 2 and spread["force_mae_n"]["sd"] == 0.0
