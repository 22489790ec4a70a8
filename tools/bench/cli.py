"""`tensortouch bench <area>`: benchmarks that print side-by-side ratios measured in one run.

Each area is a module exposing `add_arguments(parser)` and `run(args) -> int`; an area whose
module (or its dependencies) is not installed is listed as unavailable instead of failing.
"""
from __future__ import annotations

import importlib
import logging

log = logging.getLogger(__name__)

AREAS = {
    "runtime": ("tensortouch.tools.bench.runtime_bench", "deploy frame loop: per-stage latency, int8 vs fp32"),
    "contacts": ("tensortouch.tools.bench.contacts_bench", "contact clustering with vs without the light-touch rule"),
    "hand": ("tensortouch.tools.bench.hand_bench", "N sensors in one process: frames/s per sensor, p99, soak drift"),
    "fe": ("tensortouch.tools.fe.bench", "FE solver: seconds per keypoint frame / 5-keypoint trajectory"),
    "twin": ("tensortouch.tools.twin.bench", "digital twin: seconds of recording per minute of compute"),
    "workbench": ("tensortouch.tools.workbench.bench", "compare → diagnose → add → compare"),
    "recalib": ("tensortouch.tools.recalib.twin_bench", "field recalibration on twin units: held-out |F| error before/after"),
    "recalib-synthetic": ("tensortouch.tools.recalib.bench", "field recalibration on synthetic force fields (no network)"),
}


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks (" + ", ".join(AREAS) + ")")
    bsub = p.add_subparsers(dest="bench_area", metavar="AREA", required=True)
    for name, (module, helptext) in AREAS.items():
        try:
            mod = importlib.import_module(module)
        except ImportError as exc:
            log.warning("bench area %r unavailable: %s", name, exc)
            continue
        if not (callable(getattr(mod, "add_arguments", None)) and callable(getattr(mod, "run", None))):
            raise TypeError(f"bench area {name!r}: {module} must define add_arguments(parser) and run(args)")
        q = bsub.add_parser(name, help=helptext)
        mod.add_arguments(q)
        q.set_defaults(func=mod.run)
