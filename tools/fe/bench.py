"""`tensortouch bench fe`: seconds per keypoint frame and per 5-keypoint trajectory on the standard gel.

The standard gel (tools.fe.scenario.standard_dome) at the shipped mesh size (0.7 mm top / 2 mm
inside), rigid sphere R 5 mm pressed 2 mm then slid 1 mm (5 keypoints, mu = 2.2). `--quick` uses
a coarser mesh (1.2 mm top) and says so in its output; `--order 2` times the locking-free quadratic
u/p/J tets (top 1.4 mm / inside 3 mm, similar node count).
"""
from __future__ import annotations

import json
import logging
import os
import platform
import time

log = logging.getLogger(__name__)

QUICK_SIZE_TOP = 1.2


def _equilibrium_error(result) -> float:
    import numpy as np

    total = result.RF.sum(axis=1)
    err = np.linalg.norm(total + result.base_reaction, axis=1) / np.maximum(np.linalg.norm(total, axis=1), 1e-12)
    return float(err.max())


def add_arguments(parser) -> None:
    parser.add_argument("--quick", action="store_true",
                        help=f"smaller run: mesh {QUICK_SIZE_TOP} mm at the top instead of 0.7 mm")
    parser.add_argument("--keypoints", type=int, default=5, help="keypoints in the trajectory (default 5)")
    parser.add_argument("--order", type=int, choices=(1, 2), default=1,
                        help="1 = linear tets (shipped default), 2 = quadratic u/p/J tets (locking-free, slower)")
    parser.add_argument("--json", action="store_true", help="print one JSON object as the last line")


def run(args) -> int:
    from .scenario import standard_dome
    from .solver import build_mesh, solve

    mesh_kw = {"size_top": QUICK_SIZE_TOP} if args.quick else {}
    if args.order == 2:
        mesh_kw.update(order=2, size_top=max(mesh_kw.get("size_top", 0.7), 1.4), size_inside=3.0)
    scenario = standard_dome(n_keypoints=args.keypoints, **mesh_kw)
    t0 = time.perf_counter()
    mesh = build_mesh(scenario)
    t_mesh = time.perf_counter() - t0
    t1, c1 = time.perf_counter(), time.process_time()
    result = solve(scenario, mesh=mesh,
                   progress=lambda j, n, msg: None if args.json else print(f"  {msg}", flush=True))
    t_solve = time.perf_counter() - t1
    cpu_solve = time.process_time() - c1
    info = json.loads(result.solver_info)
    n_frames = result.n_frames
    out = {
        "bench": "fe",
        "scenario": "standard_dome" + (" (quick: coarser mesh)" if args.quick else ""),
        "quick": bool(args.quick),
        "order": args.order,
        "nodes": result.n_nodes,
        "tets": int(result.tets.shape[0]),
        "keypoints": n_frames,
        "seconds_mesh": round(t_mesh, 3),
        "seconds_per_frame": round(t_solve / n_frames, 3),
        "seconds_per_trajectory": round(t_solve * 5 / n_frames, 3),
        "seconds_per_trajectory_with_mesh": round((t_solve + t_mesh) * 5 / n_frames, 3),
        "cpu_seconds_per_trajectory": round(cpu_solve * 5 / n_frames, 3),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "increments": info["increments"], "newton_iterations": info["iterations"],
        "final_force_N": [round(float(v), 4) for v in result.RF[-1, 0]],
        "equilibrium_error_max": float(f"{_equilibrium_error(result):.2e}"),
        "cpu_count": os.cpu_count(), "machine": platform.machine(),
    }
    label = " (QUICK: coarser mesh than shipped)" if args.quick else ""
    if args.order == 2:
        label += " (order 2: quadratic u/p/J tets, top 1.4 mm)"
    print(f"FE bench{label}: standard dome, {out['nodes']} nodes, {out['tets']} tets, "
          f"{n_frames} keypoints, mu = 2.2")
    print(f"  mesh {t_mesh:.2f} s | {out['seconds_per_frame']:.2f} s per keypoint frame | "
          f"{out['seconds_per_trajectory']:.2f} s per 5-keypoint trajectory "
          f"({info['increments']} increments, {info['iterations']} Newton iterations)")
    print(f"  process CPU time {out['cpu_seconds_per_trajectory']:.2f} s per trajectory; load average "
          f"{out['load_average_1min']} on {os.cpu_count()} cores (wall time grows when the machine is shared)")
    print(f"  final reaction RF = {out['final_force_N']} N; max |sum RF + base reaction| / |sum RF| = "
          f"{out['equilibrium_error_max']:.1e}")
    if args.json:
        print(json.dumps(out))
    return 0
