"""Generality check of the workbench (session 6): twin-truth effects at parameters no test uses,
fixed before the first run; every row is reported (docs/workbench.md, "Generality check").

    python -m tests.workbench_generality [--model exported_models/hiera-qup-128] [--out FILE]

Same unit, plan, nominal correction and network path as tests/workbench_acceptance.py.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import tests.workbench_acceptance as acc
from tools.workbench.scenarios import net_scenario, record

CASES = (("viscoelastic_relaxation", {"g1": 0.4, "tau": 3.0}),
         ("temperature_softening", {"alpha": 0.03, "t_ref": 22.0}),
         ("mullins_softening", {"r": 0.4, "m": 0.8}),
         ("strain_stiffening", {"k": 8.0}),
         ("rim_stiffening", {"a": 2.0, "w": 3.0}),
         ("ft_bias_drift", {"bx": 0.01, "by": 0.0, "bz": -0.01}),
         ("led_drift", {"c": 0.002}))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.workbench_generality")
    p.add_argument("--model", default="exported_models/hiera-qup-128")
    p.add_argument("--work", default="cache/workbench/generality")
    p.add_argument("--out", help="write the rows as JSON here")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    bench = acc.Bench(a.model, work)
    null = acc.null_session()
    rows = []
    for name, params in CASES:
        t0 = time.time()
        s = record(net_scenario(acc.NET_TEST_SEED, effects=((name, params),)))
        d = bench.diagnose(s)
        r = d.ranking[0]
        rows.append({"effect": name, "truth": params, "rank1": r.effect.name, "before": r.before, "after": r.after,
                     "reduction": r.reduction, "p": r.p_adjusted, "fitted": r.params, "seconds": time.time() - t0,
                     "verdict": d.verdict.effect.name if d.verdict else None,
                     "size_n": acc.effect_size(bench, s, null) if name != "led_drift" else float("nan")})
        print(json.dumps(rows[-1]), flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
