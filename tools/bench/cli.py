"""`tensortouch bench <area>`: benchmarks that print side-by-side ratios measured in one run.

Each area is a module exposing `add_arguments(parser)` and `run(args) -> int`, imported only when its
area is chosen; an area whose extra is not installed says which one to install.
"""
from __future__ import annotations

from ..command_group import lazy_group

# area -> (module, what it measures, the extra it needs beyond the base install)
AREAS = {
    "runtime": ("tensortouch.tools.bench.runtime_bench", "deploy frame loop: per-stage latency, int8 vs fp32",
                "train"),   # the fp32 graph is exported from the package's weights when it ships int8 only
    "contacts": ("tensortouch.tools.bench.contacts_bench", "contact clustering with vs without the light-touch rule", None),
    "hand": ("tensortouch.tools.bench.hand_bench", "N sensors in one process: frames/s per sensor, p99, soak drift", None),
    "fe": ("tensortouch.tools.fe.bench", "FE solver: seconds per keypoint frame / 5-keypoint trajectory", "train"),
    "twin": ("tensortouch.tools.twin.bench", "digital twin: seconds of recording per minute of compute", "train"),
    "workbench": ("tensortouch.tools.workbench.bench", "compare → diagnose → add → compare", "train"),
    "recalib": ("tensortouch.tools.recalib.twin_bench", "field recalibration on twin units: held-out |F| error before/after",
                "train"),
    "recalib-synthetic": ("tensortouch.tools.recalib.bench", "field recalibration on synthetic force fields (no network)",
                          "train"),
    "cli": ("tensortouch.tools.bench.cli_bench", "`tensortouch --help` start-up: wall time and the modules it imports", None),
}


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks (" + ", ".join(AREAS) + ")",
                       description="Benchmarks that print side-by-side figures measured in one run (docs/BENCHMARKS.md).")
    lazy_group(p, "bench_area", "AREA", [(name, *row) for name, row in AREAS.items()])
