"""`tensortouch accept workbench-synthetic-generality`: the diagnosis on hidden effects of forms not in
the library, on synthetic sessions with the nominal law as the model (tools/workbench/generality.py).

    tensortouch accept workbench-synthetic-generality [--draws 3] [--sizes 0.3 1 3] [--nulls 10] [--out FILE]
"""
from __future__ import annotations

import argparse
import json


def add_arguments(g: argparse.ArgumentParser) -> None:
    from ..workbench.generality import EXPECTED

    g.add_argument("--draws", type=int, default=3, help="random draws per effect and size")
    g.add_argument("--sizes", type=float, nargs="+", default=[0.3, 1.0, 3.0], help="effect sizes (× the floor)")
    g.add_argument("--nulls", type=int, default=10, help="sessions with no hidden effect")
    g.add_argument("--effects", nargs="+", choices=sorted(EXPECTED), help="hide only these effects (default all)")
    g.add_argument("--out", help="write every row as JSON here")


def run(args: argparse.Namespace) -> int:
    from ...contracts.files import atomic_write_json
    from ..workbench.generality import run as run_generality

    out = run_generality(args.draws, tuple(args.sizes), args.nulls, effects=args.effects,
                         progress=lambda r: print(json.dumps(r, default=float), flush=True))
    print(json.dumps(out["summary"], indent=1))
    if args.out:
        atomic_write_json(args.out, out, default=float)
    return 0
