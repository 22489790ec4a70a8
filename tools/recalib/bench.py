"""Recalibration benchmark: held-out force error before/after 5–7 pokes, per unit.

    tensortouch bench recalib-synthetic [--repeats 10] [--seed 0] [--json OUT]

SYNTHETIC units (tools.recalib.synthetic): a known true force field vs a shipped model with a
position- and magnitude-dependent bias (gel stiffer/softer, shifted centre). Each session: the
guided spots (farthest-point suggestions, missed by ~1 px), gauge noise 2 % + 0.01 N; fit with
leave-one-out, store/refuse decision against the uncorrected model; then the error on 300 random
held-out contacts over the reachable gel. A refused session counts as "no correction" (its
reduction is 0). The twin-based numbers replace these once a trained model exists
(tests/test_recalib_twin.py).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import replace

import numpy as np

from .fit import FitConfig, chosen_inputs, columns, corrected_magnitude, decide, error_stats, fit_correction, fit_forest
from .synthetic import SyntheticUnit, random_units

log = logging.getLogger(__name__)

ACCEPTANCE_UNITS = {   # the example variation: gel 20 % stiffer, centre shifted; and neighbours
    "stiff+20%, shift (+.06,-.04)": SyntheticUnit(1.20, (0.06, -0.04), 0.25),
    "stiff+15%, shift (-.05,+.05)": SyntheticUnit(1.15, (-0.05, 0.05), 0.20),
    "soft-15%, shift (+.08,0)": SyntheticUnit(0.85, (0.08, 0.0), 0.30),
    "stiff+25%, shift (0,-.07)": SyntheticUnit(1.25, (0.0, -0.07), 0.15),
    "soft-20%, shift (-.04,-.04)": SyntheticUnit(0.80, (-0.04, -0.04), 0.35),
    "stiff+10%, shift (+.03,+.06)": SyntheticUnit(1.10, (0.03, 0.06), 0.40),
}


def one_session(unit: SyntheticUnit, n: int, rng: np.random.Generator, cfg: FitConfig = FitConfig()) -> dict:
    pokes = unit.guided_pokes(rng, n)
    fit = fit_correction(pokes, cfg)
    d = decide(fit.loo["after"], error_stats(pokes.pred_mag, pokes.ref_force))
    test = unit.held_out(rng, 300)
    before = error_stats(test.pred_mag, test.ref_force)["mae_n"]
    if d.store:
        chosen = replace(cfg, inputs=chosen_inputs(fit.spec), candidates=())   # what the fit stored
        g = fit_forest(pokes, chosen).predict(test.features(columns(chosen.inputs)))
        after = error_stats(corrected_magnitude(test.pred_mag, g, cfg), test.ref_force)["mae_n"]
    else:
        after = before
    return {"loo_before": fit.loo["before"]["mae_n"], "loo_after": fit.loo["after"]["mae_n"], "stored": d.store,
            "held_before": before, "held_after": after, "reduction": 1 - after / before}


def run_units(units: dict, pokes=(5, 6, 7), repeats: int = 10, seed: int = 0, progress=None) -> list[dict]:
    rows = []
    total = len(units) * len(pokes)
    for k, (name, unit) in enumerate(units.items()):
        for j, n in enumerate(pokes):
            rng = np.random.default_rng([seed, k, n])
            sessions = [one_session(unit, n, rng) for _ in range(repeats)]
            red = np.array([s["reduction"] for s in sessions])
            rows.append({"unit": name, "pokes": n, "repeats": repeats,
                         "held_before_mae_n": float(np.mean([s["held_before"] for s in sessions])),
                         "held_after_mae_n": float(np.mean([s["held_after"] for s in sessions])),
                         "reduction_median": float(np.median(red)), "reduction_min": float(red.min()),
                         "stored_fraction": float(np.mean([s["stored"] for s in sessions])),
                         "loo_reduction_median": float(np.median([1 - s["loo_after"] / s["loo_before"]
                                                                  for s in sessions]))})
            if progress:
                progress(f"[{k * len(pokes) + j + 1}/{total}] {name}, {n} pokes: held-out reduction median "
                         f"{rows[-1]['reduction_median']:.0%}, worst {rows[-1]['reduction_min']:.0%}")
    return rows


def markdown(rows: list[dict]) -> str:
    out = [("| unit (synthetic) | pokes | held-out MAE before → after (N) | reduction median (worst of runs) "
           "| LOO reduction median | stored |"), "|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['unit']} | {r['pokes']} | {r['held_before_mae_n']:.3f} → {r['held_after_mae_n']:.3f} | "
                   f"{r['reduction_median']:.0%} ({r['reduction_min']:.0%}) | {r['loo_reduction_median']:.0%} | "
                   f"{r['stored_fraction']:.0%} |")
    return "\n".join(out)


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--repeats", type=int, default=10, help="recalibration sessions per unit")
    ap.add_argument("--seed", type=int, default=0, help="random seed")
    ap.add_argument("--random-units", type=int, default=6, help="also N units of random manufacturing variation")
    ap.add_argument("--json", help="write all rows here")


def run(a: argparse.Namespace) -> int:
    say = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    t0 = time.time()
    rows = run_units(ACCEPTANCE_UNITS, repeats=a.repeats, seed=a.seed, progress=say)
    rnd = {f"random #{i} (s={u.stiffness_ratio:.2f}, r={u.radial_bias:.2f})": u
           for i, u in enumerate(random_units(np.random.default_rng(a.seed + 1000), a.random_units))}
    rows_rnd = run_units(rnd, repeats=a.repeats, seed=a.seed + 1, progress=say)
    print("### Acceptance-style units (stiffness ±10–25 %, centre shifted)\n")
    print(markdown(rows))
    print("\n### Random manufacturing variation (stiffness 0.8–1.3, shift ≤ 0.08, radial bias 0–0.4)\n")
    print(markdown(rows_rnd))
    say(f"done in {time.time() - t0:.0f} s")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"acceptance": rows, "random": rows_rnd, "seed": a.seed, "repeats": a.repeats}, fh, indent=2)
    return 0

