"""`tensortouch bench fe`: seconds per keypoint frame and per 5-keypoint trajectory on the standard gel.

The standard gel (tools.fe.scenario.standard_dome) at the shipped mesh size (0.7 mm top / 2 mm
inside), rigid sphere R 5 mm pressed 2 mm then slid 1 mm (5 keypoints, mu = 2.2). `--quick` uses
a coarser mesh (1.2 mm top) and says so in its output; `--order 2` times the locking-free quadratic
u/p/J tets (top 1.4 mm / inside 3 mm, similar node count); `--frictionless` sets mu = 0 (the
symmetric solver path).

By default the solver's engines run side by side on the same mesh in one process, alternating
(reference "superlu" = felupe assembly + scipy SuperLU, then the default engine, `--repeat` times;
`--engines a,b,c` picks the list, the reference first),
so the ratio holds on a shared machine; the output gives both wall and process-CPU times, the
ratio of their medians, and how far the final forces of the two engines are apart.
`--engine NAME` times one engine only.
"""
from __future__ import annotations

import json
import logging
import os
import platform
import statistics
import time

from .linsolve import ENGINES

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
    parser.add_argument("--frictionless", action="store_true", help="mu = 0 (symmetric tangent) instead of 2.2")
    parser.add_argument("--engine", choices=ENGINES, default=None,
                        help="time one engine only (default: the reference superlu and the default side by side)")
    parser.add_argument("--engines", default=None,
                        help="comma-separated engines to time side by side, the reference first "
                             f"(e.g. superlu,pardiso,pardiso-reuse; choices {', '.join(ENGINES)})")
    parser.add_argument("--repeat", type=int, default=1, help="alternating runs per engine (default 1)")
    parser.add_argument("--threads", type=int, default=None,
                        help="PARDISO threads per factorisation (default: TENSORTOUCH_FE_THREADS, else 1); "
                             "the results are the same bits for any count; 2 only pays on an idle machine")
    parser.add_argument("--json", action="store_true", help="print one JSON object as the last line")


REFERENCE_ENGINE = "superlu"


def _time_one(scenario, mesh, engine: str, quiet: bool) -> dict:
    from .solver import solve

    t1, c1 = time.perf_counter(), time.process_time()
    result = solve(scenario, mesh=mesh, engine=engine,
                   progress=None if quiet else lambda j, n, msg: print(f"  [{engine}] {msg}", flush=True))
    wall, cpu = time.perf_counter() - t1, time.process_time() - c1
    info = json.loads(result.solver_info)
    per = 5 / result.n_frames
    return {"engine": engine, "seconds_per_trajectory": round(wall * per, 3),
            "cpu_seconds_per_trajectory": round(cpu * per, 3), "seconds_per_frame": round(wall / result.n_frames, 3),
            "increments": info["increments"], "newton_iterations": info["iterations"],
            "factorizations": info.get("factorizations"), "symbolic_analyses": info.get("symbolic_analyses"),
            "chord_steps": info.get("chord_steps", 0), "refinements": info.get("refinements", 0),
            "double_fallbacks": info.get("double_fallbacks", 0),
            "krylov_solves": info.get("krylov_solves", 0), "krylov_iterations": info.get("krylov_iterations", 0),
            "krylov_failures": info.get("krylov_failures", 0),
            "final_force_N": [round(float(v), 5) for v in result.RF[-1, 0]],
            "equilibrium_error_max": float(f"{_equilibrium_error(result):.2e}"),
            "load_average_1min": round(os.getloadavg()[0], 2), "_rf": result.RF}


def run(args) -> int:
    import numpy as np

    from .scenario import standard_dome
    from .solver import DEFAULT_ENGINE, build_mesh

    if args.repeat < 1:
        print(f"--repeat: expected >= 1, got {args.repeat}")
        return 2
    from . import linsolve

    if args.threads is not None:
        if args.threads < 1:
            print(f"--threads: expected >= 1, got {args.threads}")
            return 2
        linsolve.THREADS = args.threads
    if args.engines:
        engines = [e.strip() for e in args.engines.split(",") if e.strip()]
        bad = [e for e in engines if e not in ENGINES]
        if bad or len(set(engines)) != len(engines):
            print(f"--engines: expected distinct names from {', '.join(ENGINES)}, got {args.engines!r}")
            return 2
    else:
        engines = [args.engine] if args.engine else [REFERENCE_ENGINE, DEFAULT_ENGINE]
    mesh_kw = {"size_top": QUICK_SIZE_TOP} if args.quick else {}
    if args.order == 2:
        mesh_kw.update(order=2, size_top=max(mesh_kw.get("size_top", 0.7), 1.4), size_inside=3.0)
    scenario = standard_dome(n_keypoints=args.keypoints, **mesh_kw)
    if args.frictionless:
        scenario.friction = 0.0
    from .assembly import compile_kernels

    compile_kernels()  # numba compiles (or loads its cache) before anything is timed
    t0 = time.perf_counter()
    mesh = build_mesh(scenario)
    t_mesh = time.perf_counter() - t0
    # the assembly pattern is built once per mesh (kept on it, as a batch worker or a twin recording
    # keeps it for all its pokes): timed here, apart, like the mesh
    from .solver import GelModel

    t0 = time.perf_counter()
    GelModel(scenario, mesh, engines[-1] if engines[-1] != REFERENCE_ENGINE else DEFAULT_ENGINE)
    t_pattern = time.perf_counter() - t0
    runs = {e: [] for e in engines}
    for _ in range(args.repeat):
        for e in engines:
            runs[e].append(_time_one(scenario, mesh, e, args.json))
    med = {e: {k: statistics.median(r[k] for r in rs) for k in ("seconds_per_trajectory", "cpu_seconds_per_trajectory")}
           for e, rs in runs.items()}
    new = engines[-1]
    last = runs[new][-1]
    out = {
        "bench": "fe",
        "scenario": "standard_dome" + (" (quick: coarser mesh)" if args.quick else "")
                    + (" (frictionless)" if args.frictionless else ""),
        "quick": bool(args.quick), "order": args.order, "friction": scenario.friction,
        "nodes": len(mesh.nodes), "tets": int(mesh.tets.shape[0]), "keypoints": args.keypoints,
        "seconds_mesh": round(t_mesh, 3), "seconds_pattern": round(t_pattern, 3), "engine": new, "repeat": args.repeat,
        "pardiso_threads": linsolve.thread_count(),
        "seconds_per_frame": last["seconds_per_frame"],
        "seconds_per_trajectory": med[new]["seconds_per_trajectory"],
        "cpu_seconds_per_trajectory": med[new]["cpu_seconds_per_trajectory"],
        "seconds_per_trajectory_with_mesh": round(med[new]["seconds_per_trajectory"] + t_mesh * 5 / args.keypoints, 3),
        "increments": last["increments"], "newton_iterations": last["newton_iterations"],
        "final_force_N": last["final_force_N"], "equilibrium_error_max": last["equilibrium_error_max"],
        "runs": [{k: v for k, v in r.items() if k != "_rf"} for e in engines for r in runs[e]],
        "load_average_1min": round(os.getloadavg()[0], 2),
        "cpu_count": os.cpu_count(), "machine": platform.machine(),
    }
    if len(engines) >= 2:
        ref = runs[engines[0]][-1]["_rf"]
        out["reference_engine"] = engines[0]
        out["versus_reference"] = {}
        for e in engines[1:]:
            d = np.linalg.norm(runs[e][-1]["_rf"] - ref, axis=2) / np.maximum(np.linalg.norm(ref, axis=2), 1e-12)
            out["versus_reference"][e] = {
                "speedup_wall": round(med[engines[0]]["seconds_per_trajectory"] / med[e]["seconds_per_trajectory"], 2),
                "speedup_cpu": round(med[engines[0]]["cpu_seconds_per_trajectory"] / med[e]["cpu_seconds_per_trajectory"], 2),
                "final_force_rel_diff": float(f"{d[-1].max():.2e}"),
                "force_rel_diff_max_all_frames": float(f"{d.max():.2e}")}
        out.update(out["versus_reference"][new])
    label = " (QUICK: coarser mesh than shipped)" if args.quick else ""
    if args.order == 2:
        label += " (order 2: quadratic u/p/J tets, top 1.4 mm)"
    print(f"FE bench{label}: standard dome, {out['nodes']} nodes, {out['tets']} tets, "
          f"{args.keypoints} keypoints, mu = {scenario.friction}; mesh {t_mesh:.2f} s, assembly pattern "
          f"{t_pattern:.2f} s (once per mesh, not in the times below); "
          f"PARDISO threads {linsolve.thread_count()}")
    for e in engines:
        r = runs[e][-1]
        print(f"  {e:8s}: {med[e]['seconds_per_trajectory']:.2f} s wall, {med[e]['cpu_seconds_per_trajectory']:.2f} s CPU "
              f"per 5-keypoint trajectory (median of {len(runs[e])}; {r['increments']} increments, "
              f"{r['newton_iterations']} Newton iterations, {r['factorizations']} factorisations, "
              f"{r['symbolic_analyses']} symbolic analyses, {r['chord_steps']} chord steps on a kept "
              f"factorisation" + (f", {r['krylov_solves']} Krylov solves on kept factors in {r['krylov_iterations']} "
                                  f"iterations, {r['krylov_failures']} failed" if r['krylov_solves'] or
                                  r['krylov_failures'] else "") + f"); RF = {r['final_force_N']} N")
    for e, v in out.get("versus_reference", {}).items():
        print(f"  {e} / {engines[0]}: {v['speedup_wall']:.2f}x faster (wall), {v['speedup_cpu']:.2f}x (CPU); "
              f"final forces differ by {v['final_force_rel_diff']:.1e} (relative), at most "
              f"{v['force_rel_diff_max_all_frames']:.1e} over all frames")
    print(f"  load average {out['load_average_1min']} on {os.cpu_count()} cores (wall time grows when the "
          f"machine is shared; the ratio is measured side by side); max |sum RF + base reaction| / |sum RF| = "
          f"{out['equilibrium_error_max']:.1e}")
    if args.json:
        print(json.dumps(out))
    return 0
