"""Generality check of the field recalibration: twin units drawn at random from a fixed
seed (gel x0.75-1.30, optical centre +-7 px, focal +-4 %), variation the bench's six units do not
have; every unit is reported (docs/BENCHMARKS.md § Recalibration).

    tensortouch accept recalib-generality --model exported_models/hiera-qup-128 [--units 4] [--seed 20261122]
        [--calibration nominal|true] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..recalib.twin_bench import BenchUnit, TwinBenchConfig, markdown, run_bench, summary


def random_units(n: int, seed: int) -> tuple:
    rng = np.random.default_rng(seed)
    return tuple(BenchUnit(f"TWIN-G{k:03d}", round(float(rng.uniform(0.75, 1.30)), 3),
                           (round(float(rng.uniform(-7, 7)), 1), round(float(rng.uniform(-7, 7)), 1)),
                           round(float(rng.uniform(0.96, 1.04)), 3)) for k in range(1, n + 1))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", default="exported_models/hiera-qup-128", help="model package folder")
    p.add_argument("--units", type=int, default=4, help="how many random twin units")
    p.add_argument("--seed", type=int, default=20261122, help="seed of the unit draw")
    p.add_argument("--calibration", choices=("nominal", "true"), default="nominal",
                   help="start from the nominal store or each unit's own (factory) calibration")
    p.add_argument("--json", help="write all numbers here")


def run(a: argparse.Namespace) -> int:
    units = random_units(a.units, a.seed)
    res = run_bench(TwinBenchConfig(units=units, nominal=None, model=a.model, variants=(), calibration=a.calibration,
                                    runtime_check=False), say=lambda m: print(m, flush=True))
    print(markdown(res, "probe"))
    print(summary(res, "probe"))
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1, default=float))
    return 0

