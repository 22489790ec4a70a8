"""The evaluation protocol: unit sets (one set per unit, disjoint seed ranges, recipes against them, the
sealed score log) and the scorecard's pure core, on hand-made values."""
from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from tensortouch.tools.train import protocol as P
from tensortouch.tools.train import scorecard as S

ROOT = Path(__file__).resolve().parents[1]


def _doc(**sets):
    doc = tomllib.loads(P.PROTOCOL_FILE.read_text())
    for k, v in sets.items():
        doc["sets"][k] = v
    return doc


def _cli(*args, cwd=None):
    r = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", *args], capture_output=True, text=True, cwd=cwd, timeout=300)
    return r.returncode, [ln for ln in r.stdout.splitlines() + r.stderr.splitlines() if ln.strip()]


# ----- unit sets ------------------------------------------------------------------------------------
def test_shipped_protocol_sets_and_distribution():
    p = P.load_protocol()
    n = {k: len(v) for k, v in p.units.items()}
    assert n["sealed"] >= 10 and sum(u.pokes for u in p.units["sealed"]) >= 80
    serials = [u.serial for us in p.units.values() for u in us]
    assert len(serials) == len(set(serials))
    # one distribution: every session of every set has the same ranges, only the indenter pair differs
    for name in P.SET_NAMES:
        specs = p.sessions(name)
        base = {k: v for k, v in specs[0]["trajectory"].items() if k != "indenters"}
        assert all({k: v for k, v in s["trajectory"].items() if k != "indenters"} == base for s in specs)
        # six units in a row hold the six pairs of the four indenters: each indenter on three of them
        pairs = [tuple(s["trajectory"]["indenters"]) for s in specs[:6]]
        assert len(set(pairs)) == 6
        for ind in ("sphere5", "sphere3", "flat4", "cylinder3"):
            assert sum(ind in pr for pr in pairs) == 3
    assert p.sessions("validation")[0]["trajectory"]["p_two"] == 0.35
    # what a recipe's session takes, and what the twin records from it
    from tensortouch.tools.train.build import config_from_dict
    from tensortouch.tools.train.units import set_sessions

    spec = set_sessions(p, "validation", first=1, pokes=3)[0]
    assert spec.pokes == 3 and spec.world == "rig"
    rc = spec.record_config("hertz-fallback", 64)
    assert rc.trajectory.p_two == 0.35 and rc.trajectory.indenters == ("sphere5", "sphere3")
    config_from_dict({"heldout": p.sessions("validation", first=2)}, "r.toml")


def test_a_unit_in_two_sets_is_refused():
    doc = _doc(validation={"seeds": [200, 299], "units": [{"serial": "TWIN-T03", "seed": 250, "pokes": 8}]})
    with pytest.raises(P.ProtocolError, match="unit TWIN-T03 is in set 'train' and in set 'validation'"):
        P.parse_protocol(doc, "p.toml")


def test_seed_ranges_and_seeds():
    with pytest.raises(P.ProtocolError, match="overlap"):
        P.parse_protocol(_doc(sealed={"seeds": [150, 160], "units": [{"serial": "TWIN-Q01", "seed": 300, "pokes": 8}]}),
                         "p.toml")
    with pytest.raises(P.ProtocolError, match="outside the set's seed range"):
        P.parse_protocol(_doc(sealed={"seeds": [7000, 7999], "units": [{"serial": "TWIN-Q01", "seed": 8000, "pokes": 8}]}),
                         "p.toml")
    with pytest.raises(P.ProtocolError, match="seed 7100 is used by TWIN-Q01 and by TWIN-Q02"):
        P.parse_protocol(_doc(sealed={"seeds": [7000, 7999], "units": [
            {"serial": "TWIN-Q01", "seed": 7100, "pokes": 8}, {"serial": "TWIN-Q02", "seed": 7100, "pokes": 8}]}), "p.toml")
    with pytest.raises(P.ProtocolError, match="serial"):
        P.parse_protocol(_doc(sealed={"seeds": [7000, 7999], "units": [{"serial": "../up", "seed": 7100, "pokes": 8}]}),
                         "p.toml")
    doc = _doc()
    doc["distribution"]["indenters"] = ["sphere5", "spoon"]
    with pytest.raises(P.ProtocolError, match="distribution.indenters"):
        P.parse_protocol(doc, "p.toml")


def test_recipes_against_the_protocol():
    p = P.load_protocol()
    sealed = p.units["sealed"][0].serial          # named only by the protocol file
    ok = {"train": [{"serial": "TWIN-T01", "seed": 101}], "heldout": [{"serial": "TWIN-H01", "seed": 201},
                                                                       {"serial": "TWIN-S02", "seed": 12}]}
    P.check_recipe_sessions(p, ok, "r.toml")
    bad = [({"train": [{"serial": "TWIN-H02", "seed": 210}]}, "TWIN-H02 is a validation unit"),
           ({"heldout": [{"serial": "TWIN-T05", "seed": 108}]}, "TWIN-T05 is a train unit"),
           ({"heldout": [{"serial": sealed, "seed": 250}]}, f"{sealed} is a sealed unit"),
           ({"train": [{"serial": "TWIN-S01", "seed": 7500}]}, "in the sealed set's range")]
    for sessions, want in bad:
        with pytest.raises(P.ProtocolError, match=want.replace("[", r"\[").replace("]", r"\]")):
            P.check_recipe_sessions(p, sessions, "r.toml")


def test_recipe_naming_a_sealed_unit_exits_2_one_line(tmp_path):
    u = P.load_protocol().units["sealed"][2]
    r = tmp_path / "r.toml"
    r.write_text(f'name = "n"\n[sessions]\ntrain = [{{serial = "{u.serial}", seed = 150, pokes = 5}}]\n')
    rc, lines = _cli("train", "all", "--recipe", str(r), "--root", str(tmp_path / "b"))
    assert rc == 2 and len(lines) == 1 and u.serial in lines[0] and "sealed unit" in lines[0], lines


def test_units_check_cli():
    rc, lines = _cli("train", "units", "check")
    assert rc == 0 and "recipe(s) agree" in lines[-1], lines


def test_sealed_units_are_named_nowhere_else():
    """No recipe, test, doc or code names a sealed serial: only the protocol file holds them."""
    p = P.load_protocol()
    names = [u.serial for u in p.units["sealed"]]
    for folder in ("tests", "docs", "tools", "runtime", "contracts"):
        for f in (ROOT / folder).rglob("*"):
            if f.suffix in (".py", ".md", ".toml", ".json") and f != P.PROTOCOL_FILE:
                text = f.read_text(errors="ignore")
                assert not any(n in text for n in names), f


def test_sealed_log_once_per_package(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "manifest.json").write_text(json.dumps({"files": {"model.int8.onnx": {"sha256": "ab" * 32}}}))
    assert P.check_not_scored(pkg) == P.package_id({"files": {"model.int8.onnx": {"sha256": "ab" * 32}}})
    e = P.log_sealed_score(pkg, "h", ["TWIN-X-s1"], {"force_mae_n": 0.2})
    log = json.loads((pkg / P.SEALED_LOG).read_text())
    assert log == [e] and e["units"] == ["TWIN-X-s1"]
    with pytest.raises(P.ProtocolError, match="already scored on the sealed set"):
        P.check_not_scored(pkg)
    with pytest.raises(P.ProtocolError, match="once per package"):
        P.log_sealed_score(pkg, "h", [], {})
    # other weights: another package
    (pkg / "manifest.json").write_text(json.dumps({"files": {"model.int8.onnx": {"sha256": "cd" * 32}}}))
    P.check_not_scored(pkg)


def test_crosseval_sealed_refuses_partial_or_mixed(tmp_path):
    pkg = ROOT / "exported_models" / "hiera-qup-128"
    rc, lines = _cli("train", "crosseval", "--package", str(pkg), "--units", "sealed", "--units-root", str(tmp_path))
    assert rc == 2 and len(lines) == 1 and "scored whole" in lines[0], lines
    rc, lines = _cli("train", "crosseval", "--package", str(pkg), "--units", "sealed", "--recipe", "tiny")
    assert rc == 2 and len(lines) == 1 and "scored alone" in lines[0], lines


# ----- scorecard pure core --------------------------------------------------------------------------
def test_direction_error_by_hand():
    d = S.direction_error_deg([[1, 0, 0], [0, 0, 2], [0, 1, 0], [0, 0, 0]], [[1, 1, 0], [0, 0, -1], [0, 3, 0], [1, 0, 0]])
    assert d[:3] == pytest.approx([45.0, 180.0, 0.0])
    assert np.isnan(d[3])


def test_poke_segments_by_hand():
    t = np.arange(12) * 0.1
    c = np.array([0, 0, 1, 1, 0, 1, 0, 0, 0, 0, 1, 0], bool)      # 0.2–0.5 (gap 0.2 s merged), 1.0
    assert S.poke_segments(t, c, merge_s=0.3).tolist() == [0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1]
    assert S.poke_segments(t, c, merge_s=0.15).tolist() == [0, 0, 0, 0, 1, 1, 2, 2, 2, 2, 2, 2]
    assert S.poke_segments(t, np.zeros(12, bool)).tolist() == [0] * 12


def test_ratio_stats_by_hand():
    # clusters: unit A pokes a1 (rows 1, 3), a2 (row 5); unit B poke b1 (row 10)
    sums, counts = np.array([4.0, 5.0, 10.0]), np.array([2.0, 1.0, 1.0])
    W = np.array([[1, 1, 1],      # everything once: (4 + 5 + 10) / 4 = 4.75
                  [2, 0, 0],      # a1 twice: 8 / 4 = 2
                  [0, 0, 2],      # b1 twice: 10
                  [0, 0, 0]])     # nothing drawn: left out
    s = S.ratio_stats(W.astype(float), sums, counts, level=0.5)
    assert s["n"] == 4 and s["mean"] == pytest.approx(4.75)
    assert s["ci"] == pytest.approx(list(np.percentile([4.75, 2.0, 10.0], [25, 75])))


def test_bootstrap_ci_fixed_seed_two_units():
    """Two units of one poke each, values 0 and 1: replicates are 0, 0.5, 1 with p = 1/4, 1/2, 1/4, so
    the 95 % interval is [0, 1] and about half the replicates sit at 0.5."""
    W = S.resample_counts([1, 1], 4000, np.random.default_rng(3))
    assert W.shape == (4000, 2) and (W.sum(1) == 2).all()
    reps = (W @ np.array([0.0, 1.0])) / (W @ np.ones(2))
    assert set(np.unique(reps)) == {0.0, 0.5, 1.0}
    assert abs((reps == 0.5).mean() - 0.5) < 0.03
    s = S.ratio_stats(W, np.array([0.0, 1.0]), np.ones(2))
    assert s["mean"] == 0.5 and s["ci"] == [0.0, 1.0]
    # pokes are redrawn inside a drawn unit only: one unit, three pokes → every replicate draws 3
    W = S.resample_counts([3, 0], 500, np.random.default_rng(0))
    assert (W.sum(1) % 3 == 0).all()


def _table():
    """Unit A: poke 0 sphere3 single 1.0 N read 0.8 N, poke 1 sphere3 + flat4 (multi) 2.0 N read 2.5 N and 0.6 N
    missed; unit B: poke 0 flat4 single 0.3 N read 0.3 N at 90°; rest frames: A 1 phantom of 2, B 0 of 2."""
    contacts = {"unit": ["A", "A", "A", "B"], "poke": [0, 1, 1, 0],
                "indenter": ["sphere3", "sphere3", "flat4", "flat4"], "n_contact": [1, 2, 2, 1],
                "meas": [[0, 0, 1.0], [0, 0, 2.0], [0, 0, 0.6], [0, 0.3, 0]], "pred": [[0, 0, 0.8], [0, 0, 2.5], [0, 0, 0], [0.3, 0, 0]],
                "miss": [False, False, True, False]}
    rest = {"unit": ["A", "A", "B", "B"], "poke": [0, 1, 0, 0], "phantom": [True, False, False, False]}
    return contacts, rest


def test_scorecard_means_and_breakdown_counts():
    card = S.scorecard(*_table(), S.ScoreConfig(n_boot=200))
    o = card["overall"]
    assert card["units"] == 2 and card["pokes"] == 3 and o["contacts"] == 4
    assert o["miss_rate"]["mean"] == pytest.approx(0.25)
    assert o["force_mae_n"]["mean"] == pytest.approx((0.2 + 0.5 + 0.0) / 3)
    assert o["force_mae_with_misses_n"]["mean"] == pytest.approx((0.2 + 0.5 + 0.6 + 0.0) / 4)
    assert o["direction_error_deg"]["mean"] == pytest.approx(30.0)
    assert o["phantom_rate"]["mean"] == pytest.approx(0.25) and o["phantom_rate"]["n"] == 4
    for s in (o["miss_rate"], o["force_mae_n"], o["phantom_rate"]):
        assert s["ci"][0] <= s["mean"] <= s["ci"][1]
    assert {k: v["contacts"] for k, v in card["by indenter"].items()} == {"flat4": 2, "sphere3": 2}
    assert card["by indenter"]["flat4"]["miss_rate"]["mean"] == 0.5
    assert card["by contacts"]["single"]["contacts"] == 2 and card["by contacts"]["multi"]["contacts"] == 2
    assert card["by contacts"]["multi"]["pokes"] == 1 and card["by contacts"]["single"]["units"] == 2
    assert {k: v["contacts"] for k, v in card["by force"].items()} == {"0.2-0.5 N": 1, "0.5-1.5 N": 2, "1.5-3 N": 1}
    # below the contact threshold a row is not scored
    card = S.scorecard(*_table(), S.ScoreConfig(n_boot=50, contact_n=0.5))
    assert card["overall"]["contacts"] == 3


def test_session_table_from_evaluation_rows():
    frames = [{"frame": i, "t": 0.1 * i, "fields": True, "meas_mags": m, "cluster_forces": c}
              for i, (m, c) in enumerate([([0.0, 0.0], [0.08]), ([1.0, 0.0], [0.9]), ([1.0, 0.5], [0.9]),
                                          ([0.1, 0.0], []), ([0.0, 0.0], []), ([0.0, 0.0], [0.01]),
                                          ([0.0, 0.4], [0.5])])]
    rows = [{"frame": 1, "indenter": 0, "meas_force": [0, 0, 1.0], "pred_force": [0, 0, 0.9], "miss": False},
            {"frame": 2, "indenter": 0, "meas_force": [0, 0, 1.0], "pred_force": [0, 0, 0.9], "miss": False},
            {"frame": 2, "indenter": 1, "meas_force": [0, 0, 0.5], "pred_force": [0, 0, 0], "miss": True},
            {"frame": 6, "indenter": 1, "meas_force": [0, 0.4, 0], "pred_force": [0, 0.5, 0], "miss": False}]
    c, r = S.session_table("U", {"frames": frames, "rows": rows}, {0: "sphere3", 1: "flat4"})
    assert c["poke"] == [0, 0, 0, 1] and c["n_contact"] == [1, 2, 2, 1]
    assert c["indenter"] == ["sphere3", "sphere3", "flat4", "flat4"]
    assert r["poke"] == [0, 1, 1] and r["phantom"] == [True, False, False]      # frame 3 (0.1 N) is no rest frame


def test_fit_seed_spread_by_hand():
    hs = [{"force_mae_n": v, "miss_rate": 0.1} for v in (0.2, 0.3, 0.4)]
    s = S.fit_seed_spread(hs)
    assert s["force_mae_n"]["mean"] == pytest.approx(0.3) and s["force_mae_n"]["sd"] == pytest.approx(0.1)
    assert s["force_mae_n"]["min"] == 0.2 and s["force_mae_n"]["max"] == 0.4 and s["miss_rate"]["sd"] == pytest.approx(0.0)


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
    assert set(card["by indenter"]) <= {"cylinder3", "flat4"} and card["by indenter"]
    assert sum(b["contacts"] for b in card["by force"].values()) == o["contacts"]
    assert sum(b["contacts"] for b in card["by contacts"].values()) == o["contacts"]
    assert doc["scorecards"][str(copy)]["overall"]["force_mae_n"] == o["force_mae_n"]
    (spread,) = doc["fit_seeds"].values()
    assert spread["force_mae_n"]["n"] == 2 and spread["force_mae_n"]["sd"] == 0.0


def test_units_cli_bad_input_one_line(tmp_path):
    for args, want in ((("record", "sealed", "--first", "2", "--root", str(tmp_path)), "recorded whole"),
                       (("record", "validation", "--pokes", "0", "--root", str(tmp_path)), "--pokes 0"),
                       (("list", "test"), "set 'test'")):
        rc, lines = _cli("train", "units", *args)
        assert rc == 2 and len(lines) == 1 and want in lines[0], (args, lines)
    bad = tmp_path / "p.toml"
    bad.write_text(P.PROTOCOL_FILE.read_text().replace("seeds = [200, 299]", "seeds = [150, 299]"))
    rc, lines = _cli("train", "units", "check", "--protocol", str(bad))
    assert rc == 2 and len(lines) == 1 and str(bad) in lines[0] and "overlap" in lines[0], lines


def test_sealed_set_scored_once_end_to_end(tmp_path):
    """A one-unit protocol (analytic twin physics, one poke): `units record sealed`, then `crosseval --units
    sealed` scores a copy of the shipped package and logs it in the package; the second score is refused."""
    import shutil

    from tensortouch.contracts.paths import ROOT as REPO

    model = REPO / "exported_models" / "hiera-qup-128"
    if not (model / "manifest.json").is_file():
        pytest.skip("no shipped model in this checkout")
    proto = tmp_path / "p.toml"
    proto.write_text('world = "label"\nframes = "png"\n[distribution]\nindenters = ["sphere5", "flat4"]\n'
                     '[sets.train]\nseeds = [100, 199]\nunits = [{serial = "TWIN-QT1", seed = 101, pokes = 1}]\n'
                     '[sets.validation]\nseeds = [200, 299]\nunits = [{serial = "TWIN-QV1", seed = 201, pokes = 1}]\n'
                     '[sets.sealed]\nseeds = [7000, 7999]\nunits = [{serial = "TWIN-QS1", seed = 7001, pokes = 1}]\n')
    root = tmp_path / "units"
    rc, lines = _cli("train", "units", "record", "sealed", "--protocol", str(proto), "--root", str(root),
                     "--physics", "hertz-fallback")
    assert rc == 0, lines[-3:]
    pkg = tmp_path / "pkg"
    shutil.copytree(model, pkg)
    args = ("train", "crosseval", "--package", str(pkg), "--units", "sealed", "--protocol", str(proto),
            "--units-root", str(root), "--boot", "50")
    rc, lines = _cli(*args)
    assert rc == 0 and any("sealed score logged" in ln for ln in lines), lines[-5:]
    (entry,) = json.loads((pkg / P.SEALED_LOG).read_text())
    assert entry["units"] == ["TWIN-QS1-s7001"] and entry["protocol"] == P.load_protocol(proto).hash
    assert set(entry["headline"]) == set(S.HEADLINE)
    rc, lines = _cli(*args)
    assert rc == 2 and len(lines) == 1 and "already scored on the sealed set" in lines[0], lines


def test_a_recipe_takes_sessions_by_set(tmp_path):
    from tensortouch.tools.train.recipe import RecipeError, load_recipe
    from tensortouch.tools.train.runner import step_configs

    h = P.load_protocol().hash
    r = tmp_path / "r.toml"
    r.write_text('name = "n"\n[sessions]\ntrain = { set = "train", first = 2, pokes = 3 }\n'
                 f'heldout = {{ set = "validation", first = 1, protocol = "{h}" }}\n[build]\nepochs = 2\n')
    (cfg,) = step_configs(load_recipe(r))
    assert [s.name for s in cfg.train] == ["TWIN-T01-s141", "TWIN-T02-s142"] and cfg.train[0].pokes == 3
    assert cfg.train[1].trajectory["indenters"] == ["sphere5", "flat4"] and cfg.train[1].world == "rig"
    assert [(s.serial, s.pokes) for s in cfg.heldout] == [("TWIN-H01", 8)]
    for text, want in (('heldout = { set = "sealed" }', "sessions.heldout takes the validation set"),
                       ('train = { set = "validation" }', "sessions.train takes the train set"),
                       ('train = { set = "train", first = 0 }', "sessions.train.first: expected a positive integer"),
                       ('train = { set = "train", protocol = "0000" }', "the unit sets changed"),
                       ('train = { units = "train" }', "takes set")):
        r.write_text(f'name = "n"\n[sessions]\n{text}\n')
        with pytest.raises(RecipeError, match=want):
            step_configs(load_recipe(r))
