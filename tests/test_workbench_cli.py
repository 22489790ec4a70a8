"""compare -> diagnose -> effects add -> compare on real twin sessions, through the CLI.

Twin sessions are recorded once into the cache (tools.workbench.scenarios; analytic physics, few
frames) and reused. The calibration store and every output live in tmp_path."""
import argparse
import json

import numpy as np
import pytest
from tensortouch.contracts.session import rewrite_in_units
from tensortouch.contracts.store import CalibrationStore
from tensortouch.tools.accept.alter import copy_without_truth
from tensortouch.tools.workbench import cli
from tensortouch.tools.workbench.scenarios import Scenario, fresh_store, record

pytest.importorskip("tensortouch.tools.twin.record")
SENSOR = "TWIN-WB01"


def run(argv, capsys):
    parser = argparse.ArgumentParser(prog="tensortouch")
    cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    code = args.func(args)
    return code, capsys.readouterr().out


@pytest.fixture(scope="module")
def sessions():
    calib = record(Scenario(100, pokes=30))
    hidden = record(Scenario(40, pokes=14, effects=(("strain_stiffening", {"k": 15.0}),)))
    return calib, hidden


@pytest.fixture
def env(tmp_path, monkeypatch, sessions):
    monkeypatch.setenv("TENSORTOUCH_CACHE", str(tmp_path / "cache"))
    store = fresh_store(tmp_path / "store")
    return sessions, store, tmp_path


def test_compare_diagnose_add_compare_shows_the_error_falling(env, capsys):
    (calib, hidden), store, tmp = env
    common = ["--sensor", SENSOR, "--store", str(store)]
    out = tmp / "cmp"
    code, text = run(["compare", str(hidden), *common, "--out", str(out), "--model-from", str(calib)], capsys)
    assert code == 0
    for name in ("residuals.csv", "summary.json", "report.html", "residual_map.png", "residual_vs.png",
                 "timeline.png", "worst.jpg"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    header = (out / "residuals.csv").read_text().splitlines()[0].split(",")
    assert {"rx", "depth", "rate", "slip", "temperature", "time", "theta", "phi", "brightness"} <= set(header)
    before = summary["force_error"]["rms_vector"]

    code, text = run(["diagnose", str(hidden), *common, "--json"], capsys)
    assert code == 0
    result = json.loads(text.strip().splitlines()[-1])
    assert result["verdict"] == "strain_stiffening"
    assert result["ranking"][0]["significant"] and result["ranking"][0]["reduction"] >= 0.5
    assert "Missing physics" in text and "k = " in text

    code, text = run(["effects", "add", "strain_stiffening", "--from-diagnosis", *common], capsys)
    assert code == 0 and "calibration v0002" in text
    cal = CalibrationStore(store).load(SENSOR)
    assert cal.effects[0]["name"] == "strain_stiffening"
    assert cal.effects[0]["params"]["k"] == pytest.approx(15.0, rel=0.15)

    code, text = run(["compare", str(hidden), *common, "--out", str(out), "--before-after"], capsys)
    assert code == 0 and "before -> after" in text
    after = json.loads((out / "summary.json").read_text())
    assert after["force_error"]["rms_vector"] <= 0.5 * before
    assert after["before"]["force_error"]["rms_vector"] == pytest.approx(before)
    assert (out / "before_after.png").is_file()

    code, text = run(["diagnose", str(hidden), *common, "--json"], capsys)
    assert json.loads(text.strip().splitlines()[-1])["verdict"] is None

    code, text = run(["effects", "remove", "strain_stiffening", *common], capsys)
    assert code == 0 and CalibrationStore(store).load(SENSOR).effects == []


def diagnoses(env, capsys, *sessions) -> list[dict]:
    """`diagnose --json` of each session, the model fitted on the calibration session first."""
    (calib, _), store, tmp = env
    common = ["--sensor", SENSOR, "--store", str(store)]
    run(["compare", str(calib), *common, "--out", str(tmp / "c"), "--model-from", str(calib), "--no-pictures"], capsys)
    return [json.loads(run(["diagnose", str(s), *common, "--json"], capsys)[1].strip().splitlines()[-1])
            for s in sessions]


def test_diagnosis_sees_measurements_only(env, capsys):
    """Same answer on a copy without truth/, provenance or effect list."""
    (calib, hidden), store, tmp = env
    blind = copy_without_truth(hidden, tmp / "blind")
    assert not (blind / "truth").exists()
    assert "strain_stiffening" not in (blind / "session.json").read_text()
    a, b = diagnoses(env, capsys, hidden, blind)
    assert a["verdict"] == b["verdict"] == "strain_stiffening"
    assert [r["effect"] for r in a["ranking"]] == [r["effect"] for r in b["ranking"]]
    assert np.allclose([r["reduction"] for r in a["ranking"]], [r["reduction"] for r in b["ranking"]])


def test_session_in_other_units_gives_the_same_diagnosis(env, capsys):
    """The hidden session's streams rewritten in m, mN, N*m, ms, K: same verdict, errors still in N."""
    (calib, hidden), store, tmp = env
    foreign = copy_without_truth(hidden, tmp / "foreign")
    rewrite_in_units(foreign, {"length": "m", "force": "mN", "torque": "N*m", "time": "ms", "temperature": "K"})
    a, b = diagnoses(env, capsys, hidden, foreign)
    assert a["verdict"] == b["verdict"] == "strain_stiffening"
    assert [r["effect"] for r in a["ranking"]] == [r["effect"] for r in b["ranking"]]
    for ra, rb in zip(a["ranking"], b["ranking"]):
        assert rb["heldout_error_before"] == pytest.approx(ra["heldout_error_before"], rel=1e-3, abs=1e-6)
        assert rb["reduction"] == pytest.approx(ra["reduction"], rel=1e-2, abs=1e-3)


def test_clear_errors(env, capsys):
    (calib, hidden), store, tmp = env
    from tensortouch.contracts.errors import TensorTouchError

    with pytest.raises(TensorTouchError, match="no model for sensor"):
        run(["diagnose", str(hidden), "--sensor", SENSOR, "--store", str(store)], capsys)
    with pytest.raises(TensorTouchError, match="unknown effect"):
        run(["effects", "add", "warp_drive", "--sensor", SENSOR, "--store", str(store)], capsys)
    with pytest.raises(TensorTouchError, match="tau"):
        run(["effects", "add", "viscoelastic_relaxation", "--param", "tau=1000", "--sensor", SENSOR,
             "--store", str(store)], capsys)


def test_effect_parameters_given_with_a_unit(env, capsys):
    """--param tau=1500ms and t_ref=295.15K are stored in the parameters' own units (s, degC)."""
    (calib, hidden), store, tmp = env
    from tensortouch.contracts.errors import TensorTouchError

    common = ["--sensor", SENSOR, "--store", str(store)]
    code, _ = run(["effects", "add", "viscoelastic_relaxation", "--param", "tau=1500ms", "--param", "g1=0.2",
                   *common], capsys)
    assert code == 0
    code, _ = run(["effects", "add", "temperature_softening", "--param", "t_ref=295.15 K", *common], capsys)
    eff = {e["name"]: e["params"] for e in CalibrationStore(store).load(SENSOR).effects}
    assert eff["viscoelastic_relaxation"]["tau"] == pytest.approx(1.5)
    assert eff["temperature_softening"]["t_ref"] == pytest.approx(22.0)
    for bad, words in (("tau=2furlong", "'furlong' does not convert"), ("tau=fast", "expected P=V"),
                       ("spin=1", "has no parameter 'spin'"), ("tau=3N", "'N' does not convert")):
        with pytest.raises(TensorTouchError, match=words):
            run(["effects", "add", "viscoelastic_relaxation", "--param", bad, *common], capsys)


def test_diagnose_with_more_sessions_pools_their_rows(env, capsys):
    """`diagnose SESSION --with SESSION2`: one diagnosis of both sessions' rows (the second recorded
    with the same hidden stiffening); with --paths it is refused on one line."""
    (calib, hidden), store, tmp = env
    second = record(Scenario(41, pokes=14, effects=(("strain_stiffening", {"k": 15.0}),)))
    common = ["--sensor", SENSOR, "--store", str(store)]
    run(["compare", str(calib), *common, "--out", str(tmp / "c"), "--model-from", str(calib), "--no-pictures"], capsys)
    alone = json.loads(run(["diagnose", str(hidden), *common, "--json"], capsys)[1].strip().splitlines()[-1])
    code, text = run(["diagnose", str(hidden), *common, "--with", str(second), "--json"], capsys)
    both = json.loads(text.strip().splitlines()[-1])
    assert code == 0 and "diagnosing 2 sessions together" in text
    assert both["with"] == [str(second.resolve())] and both["verdict"] == "strain_stiffening"
    assert both["n_samples"] > 1.5 * alone["n_samples"]
    from tensortouch.contracts.errors import TensorTouchError

    with pytest.raises(TensorTouchError, match="--with pools sessions on one model path"):
        run(["diagnose", str(hidden), *common, "--with", str(second), "--paths", "output"], capsys)
