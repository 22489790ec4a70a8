"""Generality check of the workbench: twin-truth effects at parameters no test uses,
fixed before the first run; every row is reported (docs/history/workbench.md, "Generality check").

    tensortouch accept workbench-generality [--model exported_models/hiera-qup-128] [--out FILE]

Same unit, plan, nominal correction and network path as tools/accept/workbench.py.
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from . import workbench as acc

CASES = (("viscoelastic_relaxation", {"g1": 0.4, "tau": 3.0}),
         ("temperature_softening", {"alpha": 0.03, "t_ref": 22.0}),
         ("mullins_softening", {"r": 0.4, "m": 0.8}),
         ("strain_stiffening", {"k": 8.0}),
         ("rim_stiffening", {"a": 2.0, "w": 3.0}),
         ("ft_bias_drift", {"bx": 0.01, "by": 0.0, "bz": -0.01}),
         ("led_drift", {"c": 0.002}))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", default="exported_models/hiera-qup-128", help="model package folder")
    p.add_argument("--work", default="cache/workbench/generality", help="folder for the recorded sessions and caches")
    p.add_argument("--out", help="write the rows as JSON here")


def run(a: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.WARNING)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    bench = acc.Bench(a.model, work)
    floor = next(s.before for s in bench.diagnose(acc.null_session()).ranking if s.channel == "force")
    rows = []
    for name, params in CASES:
        case = acc.Case(name, "truth", params)
        s = acc.case_session(case, work)
        size = acc.effect_size(bench, s, acc.base_of(case)) if name != "led_drift" else float("nan")
        rows.append(acc.row_of(bench.diagnose(s), name, params, size, floor))
        print(json.dumps(rows[-1], default=str), flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(rows, indent=1, default=str))
    return 0

