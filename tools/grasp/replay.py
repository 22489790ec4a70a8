"""Recorded pulls replayed through the controller: how a decision rule (a `ControllerConfig`) names
the pulled object on frames recorded once, without rerunning the simulation.

`record` runs pull-only trials (`TrialConfig(pull_only=True)`: the pull lasts the whole decide
window, no path) with each object pulled in turn and writes each trial's frame log (phase, joint
angles, the contacts the controller received, what each gel felt) as JSON. `replay` feeds a log's
reference and pull frames to a fresh controller and returns the object it names. Which object that
is, is judged from the simulator's record of where each object touched each gel (the trial side's
truth; the controller never sees it).
"""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ...contracts.files import atomic_write_json
from .controller import ControllerConfig, SelectiveGraspController
from .graph import ContactGraph
from .sensor_mount import SensorMount

SENSORS = SelectiveGraspController.SENSORS


def record(bench, pairs: list[str], seeds: list[int], out: str | Path) -> list[Path]:
    """Pull-only trials on `bench` (a `trial.Bench` made with `TrialConfig(pull_only=True)`), both
    objects pulled for every pair and seed; one `<pair>_<seed>_<pulled>.json` per trial in `out`."""
    out = Path(out)
    written = []
    for seed in seeds:
        for pair in pairs:
            for pulled in (0, 1):
                log: list = []
                r = bench.trial(pair, seed, log_out=log, pulled=pulled)
                body = {"pair": pair, "seed": seed, "pulled": pulled, "start": bench.start,
                        "result": asdict(r), "log": log}
                written.append(atomic_write_json(out / f"{pair}_{seed}_{pulled}.json", body, indent=None))
    return written


def load(folder: str | Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(Path(folder).glob("*.json"))]


def _frame(contacts: list) -> SimpleNamespace:
    return SimpleNamespace(seq=0, contacts=[SimpleNamespace(position_mm=c[0], force_n=c[1], normal=c[2], area_mm2=c[3])
                                            for c in contacts])


def replay(rec: dict, graph: ContactGraph, cfg: ControllerConfig | None = None,
           mount: SensorMount | None = None) -> int | None:
    """The object (0 or 1) the controller with `cfg` names on recorded trial `rec`; None when it
    names none within the recorded pull."""
    mount = mount or SensorMount()
    ctrl = SelectiveGraspController(graph, rec["start"], mount, cfg or ControllerConfig())
    ctrl.watch()
    frames = [e for e in rec["log"] if e["phase"] in ("reference", "pull")]
    named = None
    for e in frames:
        for s in SENSORS:
            ctrl.on_contacts(s, _frame(e["contacts"][s]))
        named = ctrl.detect()
        if named is not None:
            break
    if named is None:
        return None
    moving = named[0]
    felt = [e for e in frames if e["phase"] == "reference"][-1]["felt"]
    where: dict[int, list] = {}
    for s in SENSORS:
        for k, p_gel, *_ in felt[s]:
            where.setdefault(int(k), []).append(ctrl._world(s, np.asarray(p_gel, float)))
    return min(where, key=lambda k: np.linalg.norm(np.mean(where[k], axis=0) - moving))


def tally(recs: list[dict], graph: ContactGraph, cfg: ControllerConfig | None = None) -> dict[str, dict[str, int]]:
    """Per pair and per pulled object: how many recorded pulls the rule named right, wrong, or not."""
    out: dict[str, dict[str, int]] = {}
    for rec in recs:
        named = replay(rec, graph, cfg)
        kind = "right" if named == rec["pulled"] else ("none" if named is None else "wrong")
        for key in (rec["pair"], f"object {rec['pulled']} pulled"):
            out.setdefault(key, {"right": 0, "wrong": 0, "none": 0})[kind] += 1
    return out
