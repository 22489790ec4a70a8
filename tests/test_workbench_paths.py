"""Model paths (issue 45): the contact law fitted on several sessions and its refusal, the model's
own error told apart from new physics, and the paths' floors side by side."""
from __future__ import annotations

import numpy as np
import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.runtime.stages.effects import Registry
from tensortouch.tools.workbench.diagnose import DiagnoseConfig, blocks_of, diagnose
from tensortouch.tools.workbench.generality import session
from tensortouch.tools.workbench.models import ContactLaw, pool_tables
from tensortouch.tools.workbench.own_error import OwnError
from tensortouch.tools.workbench.table import SampleTable


def _law_table(seed: int, names: dict, stiffness: dict) -> SampleTable:
    """A synthetic session whose series press with the named indenters; F = k d^1.5 along the normal."""
    s = session(seed, n_pokes=12)
    c = dict(s["cols"])
    n = len(c["time"])
    series = (np.arange(n) * len(names) // n).astype(float)     # the session in len(names) parts, one per indenter
    c["series"] = series
    k = np.array([stiffness[names[str(int(i))]] for i in series])
    normal = -s["normal"]
    meas = (k * c["depth"] ** 1.5)[:, None] * normal
    vec = {"normal": normal, "slip_vec": np.zeros((n, 3))}
    return SampleTable(c, meas, np.zeros_like(meas), vec, {"indenters": names})


def test_contact_law_from_sessions_covers_every_indenter_and_refuses_an_unseen_one():
    stiff = {"sphere5": 0.4, "flat4": 0.9, "sphere3": 0.25, "cone": 1.3}
    a = _law_table(1, {"0": "sphere5", "1": "flat4"}, stiff)
    b = _law_table(2, {"0": "sphere3"}, stiff)
    law = ContactLaw.fit_sessions([a, b], ["A", "B"])
    assert sorted(law.laws) == ["flat4", "sphere3", "sphere5"]
    test = _law_table(3, {"0": "sphere3", "1": "flat4"}, stiff)
    pred = law.predict(test)
    on = test.cols["depth"] > 0.3
    rel = np.linalg.norm(pred[on] - test.meas[on], axis=1) / np.linalg.norm(test.meas[on], axis=1)
    assert np.median(rel) < 0.05                          # each indenter's own curve, not the others'
    assert law.covers(test) == []
    unseen = _law_table(4, {"0": "cone"}, stiff)
    assert law.covers(unseen) == ["cone"]
    with pytest.raises(TensorTouchError) as exc:
        law.predict(unseen)
    text = str(exc.value)
    assert "'cone'" in text and "A, B" in text and "\n" not in text
    with pytest.raises(TensorTouchError):
        ContactLaw.fit(b).predict(test)                   # one session only: flat4 was never seen
    pooled = pool_tables([a, b])
    assert len(pooled) == len(a) + len(b)


def _brightness_session(seed: int, gain: float):
    """A synthetic session whose model has its OWN structured error: a gain that depends on the frame
    brightness, which is darker near the rim (so a rim stiffening could imitate it)."""
    s = session(seed)
    c = dict(s["cols"])
    rng = np.random.default_rng(seed + 77)
    bright = 1.0 - 0.08 * np.exp(-c["rim_distance"] / 8.0) + rng.normal(0.0, 0.002, len(c["time"]))
    c["brightness"] = bright
    own = 1.0 + gain * (1.0 - bright) / 0.08              # the network reads too much force where it is dark
    model = s["model"] * own[:, None]
    return SampleTable(c, s["meas"], model, {"normal": s["normal"]}, {})


# the force-stage families a brightness-dependent gain can imitate (the whole library, pairs included,
# takes minutes per diagnosis on a shared CPU; the test is about what the model's own error absorbs)
FAMILIES = ["rim_stiffening", "strain_stiffening", "temperature_softening", "ft_bias_drift"]
QUICK = DiagnoseConfig(pairs=False)


def _parts(tables):
    cfg = DiagnoseConfig()
    return [(t.cov(), t.model, t.meas, blocks_of(t, cfg)[0]) for t in tables]


def test_own_error_on_clean_sessions_is_not_reported_as_physics():
    reg = Registry.default(entry_points=False)
    calib = [_brightness_session(s, -0.5) for s in (11, 12)]
    test = _brightness_session(13, -0.5)                  # no hidden effect: only the model's own error
    alone = diagnose(test, reg, cfg=QUICK, candidates=FAMILIES)
    assert alone.verdict is not None                      # without the model of its own error: a false verdict
    own = OwnError.fit(_parts(calib))
    assert any(g[0] in ("brightness", "rim_distance", "theta") for g in own.groups)
    assert own.heldout["rms_after"] < 0.7 * own.heldout["rms_before"]
    against = diagnose(test, reg, cfg=QUICK, candidates=FAMILIES, post=own.post(test.cov()))
    assert against.verdict is None, [s.to_json() for s in against.ranking[:2]]


def test_new_physics_is_still_found_against_the_own_error():
    reg = Registry.default(entry_points=False)
    calib = [_brightness_session(s, -0.5) for s in (11, 12)]
    own = OwnError.fit(_parts(calib))
    test = _brightness_session(14, -0.5)
    T = test.cols["temperature"]
    hidden = test.meas * (1.0 - 0.012 * (T - 22.0))[:, None]     # a softening with temperature, hidden
    t = SampleTable(test.cols, hidden, test.model, test.vec, {})
    d = diagnose(t, reg, cfg=QUICK, candidates=FAMILIES, post=own.post(t.cov()))
    assert d.verdict is not None and (d.verdict.effect.family or d.verdict.effect.name) == "temperature_softening"


def test_own_error_fits_nothing_on_structureless_residuals():
    rng = np.random.default_rng(0)
    tables = []
    for seed in (21, 22):
        s = session(seed)
        meas = s["model"] + rng.normal(0.0, 0.02, s["model"].shape)
        tables.append(SampleTable(dict(s["cols"]), meas, s["model"], {"normal": s["normal"]}, {}))
    own = OwnError.fit(_parts(tables))
    assert own.groups == [] or own.heldout["rms_after"] > 0.97 * own.heldout["rms_before"]
    back = OwnError.from_json(own.to_json())
    x = tables[0].model
    assert np.allclose(back.apply(x, tables[0].cov()), own.apply(x, tables[0].cov()))


def test_floors_of_two_paths_side_by_side():
    """Two model paths of one session: the one with the larger error has the larger floor and MDE, and
    the table names both with their numbers."""
    from tensortouch.runtime.stages.effects import EffectChain
    from tensortouch.tools.workbench.compare import compare_table
    from tensortouch.tools.workbench.model_paths import PathResult, floors_lines

    reg = Registry.default(entry_points=False)
    s = session(31)
    rng = np.random.default_rng(3)
    out = []
    for name, sd in (("contact-law", 0.0), ("output", 0.15)):
        model = s["model"] * (1.0 + rng.normal(0.0, sd, len(s["model"])))[:, None]
        t = SampleTable(dict(s["cols"]), s["meas"], model, {"normal": s["normal"]}, {})
        comp = compare_table(t, EffectChain())
        comp.summary["model"] = {"name": name}
        d = diagnose(t, reg, cfg=QUICK, candidates=FAMILIES)
        out.append(PathResult(name, comp, d))
    lines = floors_lines(out)
    law, net = out
    assert law.floor() < net.floor() and law.mde() < net.mde()
    assert any(line.strip().startswith("contact-law") and f"{law.floor():.4f}" in line for line in lines)
    assert any(line.strip().startswith("output") and f"{net.mde():.4f}" in line for line in lines)
    assert "the contact-law path sees the smallest" in lines[-1]
    assert net.to_json()["floor"] == pytest.approx(net.floor())


def test_effect_added_from_a_path_diagnosis_reaches_the_runtime_effects_stage(tmp_path, capsys):
    """`effects add --from-diagnosis FILE --path P` -> a calibration version the runtime's pipeline
    applies: the published cluster forces are the effect's forward of the plain ones (end to end:
    CLI, store, SensorPipeline)."""
    import argparse
    import json

    from tensortouch.contracts.store import CalibrationStore
    from tensortouch.runtime.pipeline import SensorPipeline
    from tensortouch.runtime.stages.effects import EffectChain
    from tensortouch.runtime.stages.model import FieldModel, load_package
    from tensortouch.tools.bench.models import write_difference_package
    from tensortouch.tools.workbench import cli

    from tests.conftest import dome_calibration
    from tests.test_e2e_runtime import SENSOR, SIZE, H, W
    from tests.test_effect_stage import frames

    store = CalibrationStore(tmp_path / "calib")
    dome_calibration(store.root, SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    plain = store.load(SENSOR)
    params = {"alpha": 0.02, "t_ref": 20.0}
    other = {"effect": "ft_bias_drift", "params": {"b_x": 0.1, "b_y": 0.0, "b_z": 0.0,
                                                   "d_x": 0.0, "d_y": 0.0, "d_z": 0.0}}
    per = {"contact-law": {"path": "contact-law", "ranking": [{"effect": "temperature_softening", "params": params}]},
           "output": {"path": "output", "ranking": [other]}}
    diag = tmp_path / "diag.json"
    diag.write_text(json.dumps({**per["output"], "paths": per}))
    parser = argparse.ArgumentParser(prog="tensortouch")
    cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["effects", "add", "temperature_softening", "--sensor", SENSOR, "--store", str(store.root),
                              "--from-diagnosis", str(diag), "--path", "contact-law"])
    assert args.func(args) == 0
    assert "on the contact-law path" in capsys.readouterr().out
    cal = store.load(SENSOR)
    assert [e["name"] for e in cal.effects] == ["temperature_softening"]
    assert cal.effects[0]["params"] == pytest.approx(params)

    pkg = load_package(write_difference_package(tmp_path / "m" / "d", SIZE))

    def last(calibration, temperature):
        pipe = SensorPipeline(SENSOR, FieldModel(pkg, "fp32"), calibration)
        pipe.set_temperature(temperature)
        return [pipe.process(f, k / 30.0) for k, f in enumerate(frames())][-1]

    f0 = np.array([c.force_n for c in last(plain, 35.0).clusters])
    f1 = np.array([c.force_n for c in last(cal, 35.0).clusters])
    expect = EffectChain.from_list(cal.effects).apply(f0, {"temperature": np.full(len(f0), 35.0)})
    assert len(f0) and np.allclose(f1, expect, rtol=1e-6) and not np.allclose(f1, f0)


def test_a_refit_uses_the_model_of_the_path_the_effect_was_found_on():
    from tensortouch.tools.workbench.effects_cli import model_of_diagnosis

    assert model_of_diagnosis({"path": "contact-law", "model_source": ""}) == "contact-law"
    assert model_of_diagnosis({"path": "output", "model_source": "/pkgs/hiera-qup-128"}) == "/pkgs/hiera-qup-128"
    assert model_of_diagnosis({"path": "output"}) is None       # older diagnoses: the default model


def test_harness_scores_only_gains_a_gel_could_have():
    """accept workbench-paths: a case whose hidden gain leaves [0.5, 4] on the loaded rows is out of
    the physical range; an additive form (no gain range) is in it."""
    from tensortouch.tools.accept.workbench_paths import physical

    assert physical({"gain_range": [0.6, 3.9]}) and physical({"gain_range": None}) and physical({})
    assert not physical({"gain_range": [0.9, 11.9]}) and not physical({"gain_range": [0.36, 1.0]})


def test_harness_markdown_counts_hand_made_rows():
    """accept workbench-paths --summarize --markdown: one table line per world and path, counted by hand
    from three rows (a right 1x case with its removal, a missed 3x one, a null with a verdict)."""
    from tensortouch.tools.accept.workbench_paths import markdown

    case = {"path": "output", "form": "cubic_stiffening", "set": "scored", "unit": "U", "size_floor": 1.0,
            "floor": 0.1, "size_n": 0.2, "mde": 0.15, "verdict": "strain_stiffening", "p": 0.01, "right": True,
            "removed": 0.8, "removed_of_removable": 0.9, "gain_range": [1.0, 1.5]}
    miss = {**case, "size_floor": 3.0, "size_n": 0.3, "mde": 0.5, "verdict": None, "right": False, "best": "x",
            "best_p": 0.4, "floor": 0.3}
    for k in ("removed", "removed_of_removable"):
        miss.pop(k)
    null = {"path": "output", "null": "n", "floor": 0.2, "mde": 0.12, "verdict": "led_drift",
            "without_own_error": {"verdict": "led_drift"}}
    out = markdown([case, miss, null]).splitlines()
    assert out[0] == ("| analytic | output | 0.100–0.300 | 0.120–0.120 | 1 / 1 | 0 / 1 | 1 / 1 | 1 / 1 (1 / 1) "
                      "| 1 / 1 | 1 / 1 |")
    assert out[2].startswith("- analytic, output, cubic_stiffening 1× (0.200 N, MDE 0.150 N, U, gain 1.00–1.50): "
                             "strain_stiffening p = 0.01, removed 80 % (90 %")
    assert out[3].endswith("none (best x, p = 0.4) — wrong/missed")


def test_harness_pools_sessions_as_the_diagnosis_asks():
    """accept workbench-paths --mde-target: the statistical bar falls as 1/sqrt(presses), so an MDE of
    2x the floor on one session needs 1 * 2^2 = 4 sessions for 1x; nothing when the MDE is already low
    enough, when the practical bar (not lowered by more presses) is above the target, or off. Only a
    diagnosis that found nothing asks for more."""
    from types import SimpleNamespace

    from tensortouch.tools.accept.workbench_paths import markdown, pooled, sessions_needed, summarize

    m = {"mde": 0.2, "statistical": 0.2, "practical": 0.03, "floor": 0.1}
    assert sessions_needed(m, 1, 1.0) == 4
    assert sessions_needed(m, 1, 1.0, max_n=3) == 3
    assert sessions_needed(m, 1, 0.5) == 8                      # 16, capped at MAX_SESSIONS
    assert sessions_needed({**m, "mde": 0.09, "statistical": 0.09}, 1, 1.0) is None
    assert sessions_needed({**m, "practical": 0.12, "mde": 0.2}, 1, 1.0) is None
    assert sessions_needed(m, 1, None) is None and sessions_needed(None, 1, 1.0) is None
    assert sessions_needed(m, 8, 1.0) is None                   # already at the most

    asked = []

    def diagnosed(n, found_at=4):
        asked.append(n)
        mde = 0.2 / np.sqrt(n) if n < 4 else 0.09
        return SimpleNamespace(verdict="x" if n >= found_at else None, p=0.01, mde={
            "mde": mde, "statistical": mde, "practical": 0.03, "floor": 0.1})

    import tensortouch.tools.accept.workbench_paths as wp

    real = wp._diag
    wp._diag = lambda d: {"verdict": d.verdict, "p": d.p, "mde": d.mde["mde"], "diag_floor": 0.1}
    try:
        d, n, first = pooled(diagnosed, 1.0)
        assert (asked, n, d.verdict, first["first"]["sessions"]) == ([1, 4], 4, "x", 1)
        asked.clear()
        d, n, first = pooled(lambda k: diagnosed(k, found_at=1), 1.0)     # found alone: no more sessions
        assert (asked, n, first) == ([1], 1, {})
    finally:
        wp._diag = real
    row = {"path": "output", "form": "cubic_stiffening", "set": "scored", "unit": "U", "size_floor": 1.0,
           "floor": 0.1, "size_n": 0.1, "mde": 0.09, "verdict": "strain_stiffening", "p": 0.01, "right": True,
           "sessions": 4, "mde_target": 1.0, "model": "m",
           "first": {"sessions": 1, "verdict": None, "p": None, "mde": 0.2, "diag_floor": 0.1}}
    out = markdown([row]).splitlines()
    assert "output (m), sessions pooled to MDE ≤ 1× floor" in out[0]
    assert out[2].endswith("; 4 sessions together (one alone: MDE 0.200 N, no verdict)")
    assert list(summarize([row])) == ["output [sessions pooled to an MDE of 1× the floor] [m]"]


def _softened(seed: int, a: float) -> SampleTable:
    """A synthetic 12-poke session whose measured force softens by a per °C above 22 °C (hidden)."""
    s = session(seed, n_pokes=12)
    c = dict(s["cols"])
    c["series"] = np.zeros(len(c["time"]))
    meas = s["meas"] * (1.0 - a * (c["temperature"] - 22.0))[:, None]
    return SampleTable(c, meas, s["model"], {"normal": s["normal"]}, {})


def test_sessions_diagnosed_together_see_what_one_cannot():
    """`diagnose SESSION --with ...` pools sessions (pool_tables): a softening of 0.6 %/°C is missed on
    one 12-poke session and found on four together, whose MDE is about half; four clean sessions
    together give no verdict."""
    reg = Registry.default(entry_points=False)
    one = diagnose(_softened(41, 0.006), reg, cfg=QUICK, candidates=FAMILIES)
    four = diagnose(pool_tables([_softened(41 + k, 0.006) for k in range(4)]), reg, cfg=QUICK, candidates=FAMILIES)
    assert one.verdict is None
    assert four.verdict is not None and four.verdict.effect.name == "temperature_softening"
    assert four.mde["mde"] < 0.6 * one.mde["mde"]
    clean = diagnose(pool_tables([_softened(41 + k, 0.0) for k in range(4)]), reg, cfg=QUICK, candidates=FAMILIES)
    assert clean.verdict is None


def test_pooled_correction_runs_each_sessions_own_on_its_rows():
    from tensortouch.tools.workbench.models import pool_posts

    post = pool_posts([lambda x: 2 * x, None, lambda x: x + 1], [2, 1, 2])
    x = np.arange(15, dtype=float).reshape(5, 3)
    assert np.array_equal(post(x), np.concatenate([2 * x[:2], x[2:3], x[3:] + 1]))
    assert pool_posts([None, None], [3, 4]) is None


def test_diagnose_with_pools_each_sessions_correction_on_its_own_rows(monkeypatch):
    """`diagnose --with` (cli.pooled_comparison): the pooled table's correction runs the first session's
    on its rows and the second's on its own, whatever the tables' sizes (comparisons stubbed: the test
    is about the bookkeeping)."""
    from types import SimpleNamespace

    from tensortouch.tools.workbench import cli

    def comp_of(seed, k):
        t = _softened(seed, 0.0)
        return SimpleNamespace(table=t, pred=np.zeros((len(t), 3)), post=lambda x, k=k: k * x,
                               summary={"sensor_id": "S"})

    first, second = comp_of(41, 2.0), comp_of(42, 3.0)
    n1, n2 = len(first.table), len(second.table)
    monkeypatch.setattr(cli, "compare_session", lambda sub: second)
    args = SimpleNamespace(session="A", with_sessions=["B"], model_from=None, correction_from=None)
    pooled = cli.pooled_comparison(args, first)
    assert len(pooled.table) == n1 + n2 and pooled.pred.shape == (n1 + n2, 3)
    out = pooled.post(np.ones((n1 + n2, 3)))
    assert np.all(out[:n1] == 2.0) and np.all(out[n1:] == 3.0)
    second.summary = {"sensor_id": "other"}
    with pytest.raises(TensorTouchError, match="pools sessions of one sensor"):
        cli.pooled_comparison(args, comp_of(43, 1.0))
