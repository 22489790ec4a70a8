"""`tensortouch accept <harness>`: the acceptance harnesses behind docs/BENCHMARKS.md.

Each harness module exposes `add_arguments(parser)` and `run(args) -> int`, as the bench areas do, and
is imported only when its harness is chosen.
"""
from __future__ import annotations

from ..command_group import lazy_group

HARNESSES = {
    "workbench": ("tensortouch.tools.accept.workbench",
                  "the workbench loop on twin sessions with hidden effects, nulls, two effects and a plugin"),
    "workbench-generality": ("tensortouch.tools.accept.workbench_generality",
                             "twin-truth effects at parameters no acceptance case uses"),
    "workbench-synthetic-generality": ("tensortouch.tools.accept.synthetic_generality",
                                       ("the diagnosis on hidden effects of forms not in the library (synthetic "
                                       "sessions, the nominal law as the model)")),
    "workbench-twin-generality": ("tensortouch.tools.accept.twin_generality",
                                  "diagnosis on twin units with hidden effects in forms not in the library"),
    "workbench-paths": ("tensortouch.tools.accept.workbench_paths",
                        "diagnosis on each model path (network output, contact law, FE at keypoints) with its floor"),
    "recalib-generality": ("tensortouch.tools.accept.recalib_generality",
                           "field recalibration on randomly drawn twin units"),
}


def register(sub) -> None:
    p = sub.add_parser("accept", help="acceptance harnesses (" + ", ".join(HARNESSES) + ")",
                       description="The acceptance harnesses behind docs/BENCHMARKS.md.")
    p.set_defaults(extra="train")
    lazy_group(p, "accept_harness", "HARNESS", [(name, module, text) for name, (module, text) in HARNESSES.items()])
