"""`tensortouch accept <harness>`: the acceptance harnesses behind docs/BENCHMARKS.md.

Each harness module exposes `add_arguments(parser)` and `run(args) -> int`, as the bench areas do.
"""
from __future__ import annotations

import importlib

HARNESSES = {
    "workbench": ("tensortouch.tools.accept.workbench",
                  "the workbench loop on twin sessions with hidden effects, nulls, two effects and a plugin"),
    "workbench-generality": ("tensortouch.tools.accept.workbench_generality",
                             "twin-truth effects at parameters no acceptance case uses"),
    "workbench-twin-generality": ("tensortouch.tools.accept.twin_generality",
                                  "diagnosis on twin units with hidden effects in forms not in the library"),
    "workbench-paths": ("tensortouch.tools.accept.workbench_paths",
                        "diagnosis on each model path (network output, contact law, FE at keypoints) with its floor"),
    "recalib-generality": ("tensortouch.tools.accept.recalib_generality",
                           "field recalibration on randomly drawn twin units"),
}


def register(sub) -> None:
    p = sub.add_parser("accept", help="acceptance harnesses (" + ", ".join(HARNESSES) + ")")
    asub = p.add_subparsers(dest="accept_harness", metavar="HARNESS", required=True)
    for name, (module, helptext) in HARNESSES.items():
        q = asub.add_parser(name, help=helptext, description=helptext)
        mod = importlib.import_module(module)
        mod.add_arguments(q)
        q.set_defaults(func=mod.run)
