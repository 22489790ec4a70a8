"""Twin benchmarks (docs/BENCHMARKS.md, "Digital twin"): render rate, recording throughput
(seconds of recording per minute of compute, cold = FE solves included, warm = FE cached), and the
error of interpolating FE keypoint frames (linear in the motion phase) against a 4x denser solve.

    python -m tools.twin.bench [--pokes 3] [--cache DIR]
"""
from __future__ import annotations

import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def render_rate(n: int = 30) -> dict:
    from .physics import HertzFallbackPhysics
    from .trajectory import plan_session
    from .unit import TwinUnit

    unit = TwinUnit("TWIN-BENCH")
    r = unit.renderer
    out = {}
    t = time.perf_counter()
    for i in range(n):
        r.render(None, 1.0, np.random.default_rng(i))
    out["rest_ms"] = (time.perf_counter() - t) / n * 1e3
    phys = HertzFallbackPhysics(unit.gel)
    poke = plan_session(1, 0, unit.gel)[0]
    sol = phys.solve(poke)
    W = unit.gel.interpolator(sol.nodes, r.view.points[r.view.mask])
    u = np.zeros(r.view.points.shape)
    u[r.view.mask] = W @ sol.U[int(np.argmax(sol.depth[:, 0]))]
    t = time.perf_counter()
    for i in range(n):
        r.render(u, 1.0, np.random.default_rng(i))
    out["deformed_ms"] = (time.perf_counter() - t) / n * 1e3
    out["size"] = f"{unit.camera.width}x{unit.camera.height}"
    return out


def throughput(pokes: int, cache: Path, frames: str = "ffv1") -> dict:
    from .record import RecordConfig, Recorder

    res = {}
    for label in ("cold", "warm"):
        tmp = Path(tempfile.mkdtemp(prefix="twin-bench-"))
        cfg = RecordConfig(serial="TWIN-BENCH", pokes=pokes, seed=7, physics="fe", frame_format=frames)
        rec = Recorder(cfg, tmp / "s")
        from .record import make_physics

        rec.physics = make_physics(cfg, rec.unit)
        rec.physics.cache = cache
        t = time.perf_counter()
        rec.run()
        wall = time.perf_counter() - t
        from ...contracts.session import load_session

        dur = float(load_session(tmp / "s").table("frames")[-1, 0])
        res[label] = {"recorded_s": dur, "compute_s": wall, "rec_s_per_min": dur / wall * 60,
                      "physics_s": rec.timing["physics_s"], "render_s": rec.timing["render_s"],
                      "frames": rec.timing["frames_rendered"], "fe_solved": rec.physics.stats["solved"]}
        shutil.rmtree(tmp, ignore_errors=True)
    return res


def _densify(poke, factor: int):
    """The same poke with `factor` keypoints per original segment (positions linear in the phase)."""
    from .trajectory import Poke

    J = len(poke.times)
    s = np.linspace(0, J - 1, (J - 1) * factor + 1)
    j = np.minimum(s.astype(int), J - 2)
    f = (s - j)[None, :, None]
    tr = poke.translation[:, j] + f * (poke.translation[:, j + 1] - poke.translation[:, j])
    rv = poke.rotvec[:, j] + f * (poke.rotvec[:, j + 1] - poke.rotvec[:, j])
    # times: the phase s = k/factor inside a min-jerk segment is reached at the tau solving minjerk(tau) = s
    taus = np.linspace(0, 1, 2001)
    from .trajectory import minjerk

    tau = np.interp(s - j, minjerk(taus), taus)
    times = poke.times[j] + tau * (poke.times[j + 1] - poke.times[j])
    return Poke(poke.kind, poke.indenters, poke.slots, poke.position, poke.rotation, tr, rv, times,
                poke.t_approach, poke.t_retreat_end, poke.depth, dict(poke.extra))


def interpolation_error(cache: Path, factor: int = 4, kind: str = "slide") -> dict:
    from .physics import PokeSolve, interpolate
    from .record import RecordConfig, make_physics
    from .trajectory import TrajectoryConfig, plan_session
    from .unit import TwinUnit

    unit = TwinUnit("TWIN-BENCH")
    cfg = TrajectoryConfig(kinds=(kind,), p_two=0.0, indenters=("sphere5",))
    poke = plan_session(1, 3, unit.gel, cfg)[0]
    phys = make_physics(RecordConfig(), unit)
    phys.cache = cache
    coarse = phys.solve(poke)
    dense_poke = _densify(poke, factor)
    dense = phys.solve(dense_poke)
    between = np.arange(len(dense_poke.times)) % factor != 0
    t = dense_poke.times[between]
    # pure interpolation error: the dense solve's own every-factor-th keypoint, interpolated
    sub = PokeSolve(dense.nodes, dense.U[::factor], dense.RF[::factor], dense.RM[::factor],
                    dense.CAREA[::factor], dense.contact[::factor], dense.depth[::factor], dense.backend)
    U_d, RF_d = dense.U[between], dense.RF[between, 0]
    peak_u = float(np.linalg.norm(dense.U, axis=-1).max())
    peak_f = float(np.linalg.norm(dense.RF[:, 0], axis=-1).max())
    out = {"poke": kind, "depth_mm": float(poke.depth), "keypoints": len(poke.times),
           "dense_keypoints": len(dense_poke.times), "U_peak_mm": peak_u, "RF_peak_N": peak_f}
    for method in ("pchip", "linear"):
        du = np.linalg.norm(interpolate(sub, poke, t, "U", method=method) - U_d, axis=-1)
        drf = np.linalg.norm(interpolate(sub, poke, t, "RF", method=method)[:, 0] - RF_d, axis=-1)
        out[method] = {"U_max_mm": float(du.max()), "U_rms_mm": float(np.sqrt((du ** 2).mean())),
                       "RF_max_N": float(drf.max()), "RF_rms_N": float(np.sqrt((drf ** 2).mean()))}
    # FE increment dependence: same keypoints solved with 0.5 mm vs 0.125 mm keypoint steps
    dk = np.linalg.norm(coarse.RF[:, 0] - dense.RF[::factor, 0], axis=-1)
    out["fe_step_dependence_RF_max_N"] = float(dk.max())
    out["fe_step_dependence_U_max_mm"] = float(np.linalg.norm(coarse.U - dense.U[::factor], axis=-1).max())
    return out


def add_arguments(ap) -> None:
    ap.add_argument("--pokes", type=int, default=3, help="pokes in the recorded plan")
    ap.add_argument("--cache", help="FE cache for the benchmark (default: a fresh temp dir -> cold really cold)")
    ap.add_argument("--skip", nargs="*", default=[], choices=["render", "throughput", "interp"], help="parts of the benchmark to leave out")


def run(args) -> int:
    logging.basicConfig(level=logging.WARNING)
    cache = Path(args.cache) if args.cache else Path(tempfile.mkdtemp(prefix="twin-bench-fe-"))
    out = {}
    if "render" not in args.skip:
        out["render"] = render_rate()
        print(json.dumps({"render": out["render"]}), flush=True)
    if "throughput" not in args.skip:
        out["throughput"] = throughput(args.pokes, cache)
        print(json.dumps({"throughput": out["throughput"]}), flush=True)
    if "interp" not in args.skip:
        out["interp"] = [interpolation_error(cache, kind=k) for k in ("press", "slide")]
        print(json.dumps({"interp": out["interp"]}), flush=True)
    return 0

