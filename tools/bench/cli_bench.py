"""`tensortouch bench cli`: how fast `tensortouch --help` starts, and which heavy modules building the
whole command tree imports (none should: they are imported when a command runs).

Each run is a fresh process (`python -m tensortouch.runtime.shells.cli --help`, the console script's
own code) timed from outside; the median and range of the wall time are printed.
"""
from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time

# what registering the commands must not import (each costs 0.1-3 s at start-up)
HEAVY = ("torch", "scipy", "zenoh", "onnxruntime", "cv2", "onnx", "sklearn", "matplotlib", "tqdm", "felupe",
         "gmsh", "trimesh", "mujoco", "pinocchio", "foxglove", "rerun", "mcap", "rosbags", "dask", "lerobot")

PROBE = ("import sys\nfrom tensortouch.runtime.shells.cli import build_parser\nbuild_parser()\n"
         "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))\n")


def heavy_imports() -> list[str]:
    """The HEAVY modules a fresh process has imported after building the `tensortouch` parser."""
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True).stdout
    loaded = set(out.split())
    return [m for m in HEAVY if m in loaded]


def add_arguments(p) -> None:
    p.add_argument("--runs", type=int, default=7, help="timed `tensortouch --help` processes (default 7)")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")


def run(args) -> int:
    cmd = [sys.executable, "-m", "tensortouch.runtime.shells.cli", "--help"]
    subprocess.run(cmd, capture_output=True, check=True)          # warm the file cache once
    walls = []
    for _ in range(max(1, args.runs)):
        t0 = time.perf_counter()
        subprocess.run(cmd, capture_output=True, check=True)
        walls.append(time.perf_counter() - t0)
    res = {"runs": len(walls), "wall_s_median": round(statistics.median(walls), 3),
           "wall_s_min": round(min(walls), 3), "wall_s_max": round(max(walls), 3), "heavy_imports": heavy_imports()}
    print(f"tensortouch --help: median {res['wall_s_median']:.3f} s (min {res['wall_s_min']:.3f}, max "
          f"{res['wall_s_max']:.3f}) over {res['runs']} runs; heavy modules imported: "
          f"{', '.join(res['heavy_imports']) or 'none'}")
    if args.json:
        print(json.dumps(res))
    return 0
