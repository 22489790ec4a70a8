"""The evaluation protocol: unit sets (one set per unit, disjoint seed ranges, recipes against them, the
sealed score log), on hand-made values."""
from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import tomllib
from pathlib import Path

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
    assert P.check_not_scored(pkg, "h") == P.package_id({"files": {"model.int8.onnx": {"sha256": "ab" * 32}}})
    e = P.log_sealed_score(pkg, "h", ["TWIN-X-s1"], {"force_mae_n": 0.2})
    log = json.loads((pkg / P.SEALED_LOG).read_text())
    assert log == [e] and e["units"] == ["TWIN-X-s1"]
    with pytest.raises(P.ProtocolError, match="already scored on the sealed set"):
        P.check_not_scored(pkg, "h")
    with pytest.raises(P.ProtocolError, match="once per package"):
        P.log_sealed_score(pkg, "h", [], {})
    # a sealed set recorded anew (another protocol hash): scored once more, both entries kept
    e2 = P.log_sealed_score(pkg, "h2", ["TWIN-X-s2"], {"force_mae_n": 0.3})
    assert json.loads((pkg / P.SEALED_LOG).read_text()) == [e, e2]
    with pytest.raises(P.ProtocolError, match="once per package"):
        P.log_sealed_score(pkg, "h2", [], {})
    # a fixed scorer re-measures: once more per scorer version; entries of before the versions count as 1
    old = json.loads((pkg / P.SEALED_LOG).read_text())
    (pkg / P.SEALED_LOG).write_text(json.dumps([{k: v for k, v in x.items() if k != "scorer"} for x in old]))
    with pytest.raises(P.ProtocolError, match="scorer 1"):
        P.check_not_scored(pkg, "h", scorer=1)
    e3 = P.log_sealed_score(pkg, "h", ["TWIN-X-s1"], {"force_mae_n": 0.25}, scorer=2)
    assert e3["scorer"] == 2 and len(json.loads((pkg / P.SEALED_LOG).read_text())) == 3
    with pytest.raises(P.ProtocolError, match="scorer 2"):
        P.check_not_scored(pkg, "h", scorer=2)
    # other weights: another package
    (pkg / "manifest.json").write_text(json.dumps({"files": {"model.int8.onnx": {"sha256": "cd" * 32}}}))
    P.check_not_scored(pkg, "h")


def test_a_replaced_package_keeps_its_sealed_log(tmp_path):
    from tensortouch.tools.train.package import write_package

    model = tmp_path / "m.onnx"
    for i, payload in enumerate((b"first weights", b"other weights")):
        model.write_bytes(payload)
        man = {"files": {"model.int8.onnx": {"sha256": hashlib.sha256(payload).hexdigest()}}}
        pkg = write_package(tmp_path / "models", "p", {"model.int8.onnx": model}, man)
        if i == 0:
            first = P.log_sealed_score(pkg, "h", ["TWIN-X-s1"], {"force_mae_n": 0.2})
    assert json.loads((pkg / P.SEALED_LOG).read_text()) == [first]     # carried over, not lost
    assert (pkg / "model.int8.onnx").read_bytes() == b"other weights"
    P.check_not_scored(pkg, "h")                                         # the new weights are another package


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
    pkg = tmp_path / "pkg"   # the shipped model files, without the shipped package's own sealed score log
    shutil.copytree(model, pkg, ignore=shutil.ignore_patterns("sealed_scores.json", ".sealed_scores.json.lock"))
    args = ("train", "crosseval", "--package", str(pkg), "--units", "sealed", "--protocol", str(proto),
            "--units-root", str(root), "--boot", "50")
    rc, lines = _cli(*args)
    assert rc == 0 and any("sealed score logged" in ln for ln in lines), lines[-5:]
    (entry,) = json.loads((pkg / P.SEALED_LOG).read_text())
    assert entry["units"] == ["TWIN-QS1-s7001"] and entry["protocol"] == P.load_protocol(proto).hash
    assert set(entry["headline"]) == set(S.HEADLINE)
    rc, lines = _cli(*args)
    assert rc == 2 and len(lines) == 1 and "already scored on the sealed set" in lines[0], lines


