"""Acceptance of issue 6 on twin sessions (slow: records ~20 sessions on first run, cached after).

Model = nominal contact law fitted on a calibration session (no hidden effect); each test session
has effects switched on in the twin's truth (or measurements altered by tools/accept/alter.py,
an independent script). Diagnosis reads sample tables built from measured streams only.
"""
import pytest
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.stages.effects import EffectChain, Registry
from tensortouch.tools.accept.alter import alter_session
from tensortouch.tools.accept.workbench import PLUGINS  # the harness's plugin
from tensortouch.tools.workbench.compare import load_table
from tensortouch.tools.workbench.diagnose import add_to_chain, diagnose
from tensortouch.tools.workbench.models import ContactLaw
from tensortouch.tools.workbench.scenarios import Scenario, record, store_root

from tests.conftest import hidden_effects

pytestmark = pytest.mark.slow
HIDDEN = hidden_effects("twin")
SLIDES = {"friction_mismatch": ("slide", "press")}   # friction shows only while sliding


@pytest.fixture(scope="module")
def bench():
    cal = CalibrationStore(store_root()).load("TWIN-WB01")
    calib, _ = load_table(record(Scenario(100, pokes=30)), cal)
    law = ContactLaw.fit(calib)

    def table(session):
        t, _ = load_table(session, cal)
        return t.with_model(law.predict(t))

    return table, Registry.default(entry_points=False)


@pytest.mark.parametrize("name", list(HIDDEN))
def test_hidden_effect_ranked_first_and_error_halved(name, bench):
    table, reg = bench
    kinds = {"kinds": SLIDES[name]} if name in SLIDES else {}
    sc = Scenario(10 + list(HIDDEN).index(name), effects=((name, HIDDEN[name]),), **kinds)
    diag = diagnose(table(record(sc)), reg)
    assert diag.ranking[0].effect.name == name
    assert diag.verdict is not None and diag.verdict.effect.name == name
    assert diag.verdict.reduction >= 0.5


def test_null_sessions_no_significant_effect_in_9_of_10(bench):
    table, reg = bench
    verdicts = [diagnose(table(record(Scenario(s))), reg).verdict for s in range(1, 11)]
    assert sum(v is None for v in verdicts) >= 9, [v.effect.name for v in verdicts if v]


def test_two_hidden_effects_found_one_after_the_other(bench):
    table, reg = bench
    sc = Scenario(30, effects=(("viscoelastic_relaxation", {"g1": 0.3, "tau": 1.0}),
                               ("rim_stiffening", {"a": 2.0, "w": 4.0})))
    t = table(record(sc))
    first = diagnose(t, reg)
    chain = add_to_chain(EffectChain(), first.verdict)
    second = diagnose(t, reg, chain)
    assert {first.verdict.effect.name, second.verdict.effect.name} == {"viscoelastic_relaxation", "rim_stiffening"}
    third = diagnose(t, reg, add_to_chain(chain, second.verdict))
    assert third.verdict is None
    assert third.ranking and second.verdict.after < 0.5 * first.verdict.before


def test_independent_alteration_script_viscoelastic(bench, tmp_path):
    table, reg = bench
    altered = alter_session(record(Scenario(5)), tmp_path / "visco", "viscoelastic", {"g1": 0.35, "tau": 0.8})
    diag = diagnose(table(altered), reg)
    assert diag.verdict.effect.name == "viscoelastic_relaxation"
    assert diag.verdict.reduction >= 0.5
    assert diag.verdict.params["tau"] == pytest.approx(0.8, rel=0.25)


def test_unknown_effect_covariate_named_then_user_plugin_fixes_it(bench, tmp_path):
    table, reg = bench
    altered = alter_session(record(Scenario(6)), tmp_path / "azimuth", "azimuth", {"a": 0.35, "phi0": 0.5})
    t = table(altered)
    diag = diagnose(t, reg)
    assert diag.unexplained["covariate"] == "phi"
    with_plugin = diagnose(t, Registry.default(plugin_dirs=[PLUGINS], entry_points=False))
    assert with_plugin.verdict.effect.name == "azimuth_stiffness"
    assert with_plugin.verdict.reduction >= 0.5
