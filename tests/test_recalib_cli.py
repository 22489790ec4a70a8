"""`tensortouch recalibrate` end to end on a replayed synthetic recording (real replay camera, real
onnxruntime pipeline, real calibration store), plus rollback through `tensortouch calib`."""
import argparse
import json

import numpy as np
import pytest
from tensortouch.runtime.shells import commands
from tensortouch.tools.recalib import cli

from tests.recalib_util import SENSOR, setup_env, true_gain, write_recording


def parse(argv):
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    cli.register(sub)
    commands.register(sub)
    return parser.parse_args(argv)


@pytest.fixture
def env(tmp_path):
    package, store = setup_env(tmp_path)
    session, uvs, xyz = write_recording(tmp_path / "session", package, store)
    return tmp_path, package, store, session


def _recalibrate_6(tmp, package, store, session) -> tuple[dict, list[str]]:
    """`tensortouch recalibrate` on the replayed recording (6 pokes, fp32) → (its report, what it said)."""
    lines = []
    args = parse(["recalibrate", "--sensor", SENSOR, "--source", f"replay:{session}", "--store", str(store.root),
                  "--model", str(package.folder), "--precision", "fp32", "--pokes", "6",
                  "--report", str(tmp / "report.json")])
    assert cli.cmd_recalibrate(args, say=lines.append) == 0, "\n".join(lines)
    return json.loads((tmp / "report.json").read_text()), lines


def test_recalibrate_replay_stores_better_correction_and_rollback_restores(env):
    tmp, package, store, session = env
    v1 = store.current(SENSOR)
    v1_files = {p.name: p.read_bytes() for p in (store.root / SENSOR / "versions" / v1).iterdir()}
    report, lines = _recalibrate_6(tmp, package, store, session)
    assert len(report["accepted"]) == 6
    loo = report["loo"]
    # nested leave-one-out (input selection redone without the held-out poke): an honest, pessimistic estimate
    assert loo["after"]["mae_n"] < 0.65 * loo["before"]["mae_n"], loo
    # the recording's bias grows along u (a shifted centre): the selection takes position as an input
    assert "u" in store.load(SENSOR).meta["correction"]["inputs"], loo["selection"]
    assert loo["selection"]["fmag+theta+u+v"] < 0.85 * loo["selection"]["fmag"], loo["selection"]
    # the reference pairing recovered the bias the recording was made with
    ratios = [p["ref_force_n"] / np.linalg.norm(p["pred_force_n"]) for p in report["accepted"]]
    expect = [true_gain(np.array(p["uv_px"]) / 32) for p in report["accepted"]]
    assert np.allclose(ratios, expect, rtol=0.03)
    v2 = store.current(SENSOR)
    assert v2 != v1 and report["stored_version"] == v2
    cal2 = store.load(SENSOR)
    assert cal2.meta["correction"]["output"] == "gain" and cal2.meta["provenance"]["pokes"] == 6
    assert cal2.meta["provenance"]["base_version"] == v1
    assert any("poke 6 accepted" in line for line in lines)
    # rollback via the calib command: exact previous files, untouched
    rb = parse(["calib", "rollback", SENSOR, "--store", str(store.root)])
    assert rb.func(rb) == 0
    assert store.current(SENSOR) == v1
    after = {p.name: p.read_bytes() for p in (store.root / SENSOR / "versions" / v1).iterdir()}
    assert after == v1_files
    assert store.load(SENSOR).meta.get("correction") is None


def test_recalibrate_refuses_when_active_is_already_better(env):
    tmp, package, store, session = env
    base = ["recalibrate", "--sensor", SENSOR, "--source", f"replay:{session}", "--store", str(store.root),
            "--model", str(package.folder), "--precision", "fp32"]
    assert cli.cmd_recalibrate(parse(base + ["--pokes", "7"]), say=lambda m: None) == 0
    v2 = store.current(SENSOR)
    # same pokes again: the active v2 was fitted on all of them; 5 held-out pokes cannot beat it
    lines = []
    code = cli.cmd_recalibrate(parse(base + ["--pokes", "5"]), say=lines.append)
    assert code == 1 and store.current(SENSOR) == v2
    assert any("not stored (use --force" in line for line in lines), lines
    code = cli.cmd_recalibrate(parse(base + ["--pokes", "5", "--force"]), say=lines.append)
    assert code == 0 and store.current(SENSOR) != v2
    assert store.load(SENSOR).meta["provenance"]["forced"] is True


def test_recalibrate_recentres_a_shifted_crop_on_the_gel_rim_and_stores_it(env):
    tmp, package, store, session = env
    good = store.load(SENSOR).meta
    cx, cy = good["gel_center_px"]
    store.derive(SENSOR, {"gel_center_px": [cx + 3.0, cy - 2.0]})   # the stored crop is 3.6 px off the gel
    report, lines = _recalibrate_6(tmp, package, store, session)
    assert report["rim"]["shift_px"] == pytest.approx(np.hypot(3, 2), abs=0.7), report["rim"]
    new = store.load(SENSOR).meta
    assert new["gel_center_px"] == pytest.approx([cx, cy], abs=0.7)          # back on the gel
    assert new["provenance"]["crop"]["from"]["gel_center_px"] == [cx + 3.0, cy - 2.0]
    assert any("crop re-centred" in line for line in lines)
    ratios = [p["ref_force_n"] / np.linalg.norm(p["pred_force_n"]) for p in report["accepted"]]
    assert np.allclose(ratios, [true_gain(np.array(p["uv_px"]) / 32) for p in report["accepted"]], rtol=0.05)
    # the same pokes again: the active correction already fits them, so a new one is refused; a crop that
    # moved since is still stored (alone), the active correction kept
    corr = store.load(SENSOR).meta["correction"]
    store.derive(SENSOR, {"gel_center_px": [cx + 3.0, cy - 2.0]})
    lines = []
    again = parse(["recalibrate", "--sensor", SENSOR, "--source", f"replay:{session}", "--store", str(store.root),
                   "--model", str(package.folder), "--precision", "fp32", "--pokes", "5"])
    assert cli.cmd_recalibrate(again, say=lines.append) == 1, "\n".join(lines)
    meta = store.load(SENSOR).meta
    assert meta["gel_center_px"] == pytest.approx([cx, cy], abs=0.7) and meta["correction"] == corr
    assert meta["provenance"]["method"] == "recalibrate-rim"
    assert any("re-centred crop alone was stored" in line for line in lines), lines
    # --recentre off keeps the stored crop
    store.derive(SENSOR, {"gel_center_px": [cx + 3.0, cy - 2.0]})
    off = parse(["recalibrate", "--sensor", SENSOR, "--source", f"replay:{session}", "--store", str(store.root),
                 "--model", str(package.folder), "--precision", "fp32", "--recentre", "off", "--force"])
    assert cli.cmd_recalibrate(off, say=lambda m: None) == 0
    assert store.load(SENSOR).meta["gel_center_px"] == [cx + 3.0, cy - 2.0]
