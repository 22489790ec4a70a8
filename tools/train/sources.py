"""Where a build's FE labels come from, read from the build folder: the twin's own solves of its plan
(`fe = "twin"`, evaluation only) or the stage-2 re-solves at the measured keypoints (`fe = "resolve"`),
and the analytic stand-in for tools.fe that the smoke test uses. Stages and evaluation read labels
through here; nothing here runs a stage."""
from __future__ import annotations

import json
import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from .build import unit_meta

log = logging.getLogger(__name__)


def recorder(b, spec):
    """The twin Recorder of a session spec (not run): plan, unit, modules, physics config."""
    from ..twin.record import Recorder

    return Recorder(spec.record_config(b.cfg.physics, b.cfg.size), b.session(spec))


def fe_results(b, spec) -> list:
    """Twin mode (`--fe twin`): the FE results (tools.fe.FEResult) of every poke of a session: the very
    solves the twin recorded with (truth/truth.json `fe_scenarios`, loaded from the FE cache), so labels,
    images and F/T come from one physics even if tools/fe changed since; a solve missing from the cache is
    redone with the current FE (its hash then differs and a warning says so). With hertz-fallback physics
    (smoke tests only) the twin's PokeSolve stands in."""
    from ..fe import load_result
    from ..twin.record import make_physics

    rec = recorder(b, spec)
    physics = make_physics(rec.cfg, rec.unit)
    if b.cfg.physics != "fe":
        return [fallback_result(physics.solve(p)) for p in rec.plan]
    truth = json.loads((b.session(spec) / "truth" / "truth.json").read_text())
    out = []
    for poke, key in zip(rec.plan, truth["fe_scenarios"]):
        path = physics.cache / f"{key}.npz"
        if path.is_file():
            out.append(load_result(path))
        else:
            res = physics.result(poke)
            log.warning("%s: FE result %s of the recording is not in the cache; re-solved as %s with the "
                        "current FE (labels may differ from the recorded physics)", spec.name, key, res.scenario_hash)
            out.append(res)
    return out


def fe_mode(b) -> str:
    return getattr(b.cfg, "fe", "twin")


def label_sources(b, spec) -> list:
    """The FE label sources of a session, one per poke (twin mode) or per resolved stage-1 contact
    period (resolve mode): SimpleNamespace(times (J,) s of the FE frames, slots (session indenter ids),
    result (FEResult-like), t_init, is_keypoint (J,), poke (twin Poke or None))."""
    if fe_mode(b) == "twin":
        rec = recorder(b, spec)
        return [SimpleNamespace(times=np.asarray(p.times, float), slots=list(p.slots), result=r, poke=p,
                                t_init=float(p.times[0]), is_keypoint=np.ones(len(p.times), bool))
                for p, r in zip(rec.plan, fe_results(b, spec))]
    return resolved_sources(b, spec)


def fallback_result(ps):
    """A PokeSolve of the analytic fallback shaped like an FEResult (no stress, contact forces from the
    reaction spread over the touched nodes) — only so the smoke test can run the chain without FE."""
    J, N = ps.U.shape[:2]
    K = ps.RF.shape[1]
    from ..twin.geometry import GelSurface

    n0 = GelSurface().normals(ps.nodes)
    cn = np.zeros((J, N, 3))
    owner = np.full((J, N), -1)
    for j in range(J):
        for k in range(K):
            depth = -np.sum(ps.U[j] * n0, 1)
            sel = (depth > 0.3 * ps.depth[j, k]) & (ps.depth[j, k] > 0)
            if np.isfinite(ps.contact[j, k]).all():
                sel &= np.linalg.norm(ps.nodes - ps.contact[j, k], axis=1) < 4.0
            if sel.any():
                cn[j, sel] += ps.RF[j, k] / sel.sum()
                owner[j, sel] = k
    from scipy.spatial import Delaunay

    from .fields import _disc, surface_angles

    tris = Delaunay(_disc(*surface_angles(ps.nodes))).simplices
    return SimpleNamespace(nodes=ps.nodes, surface_nodes=np.arange(N), surface_tris=tris, U=ps.U,
                           S=np.zeros((J, N, 6)), CNORMF=cn, CSHEAR=np.zeros_like(cn), contact_owner=owner,
                           RF=ps.RF, pose_position=np.zeros((J, K, 3)), scenario_hash=ps.key)


def fe_cache_dir() -> Path:
    from ..fe.batch import default_dir

    return default_dir()


def label_solver(b):
    """tools.fe SolverSettings of a build's label solves (stage 2 and the stage-3 pokes): the recipe's
    locking cap `max_bulk_ratio`, the rest at their defaults."""
    from ..fe import SolverSettings

    return SolverSettings(max_bulk_ratio=float(b.cfg.max_bulk_ratio))


def gel_of(calibration_meta: dict):
    """tools.fe GelGeometry + tools.twin GelSurface of the unit's gel design (calibration meta.gel)."""
    from ..fe import GelGeometry
    from ..twin.geometry import GelSurface

    g = calibration_meta.get("gel", {})
    shape = g.get("shape", "flattened_dome")
    base, cap, skirt = float(g.get("base_radius_mm", 12.0)), float(g.get("cap_height_mm", 6.0)), float(g.get("skirt_mm", 2.0))
    gel = GelGeometry(kind=shape, radius=base, cap_height=cap, skirt=skirt)
    return gel, GelSurface.from_fe(gel)


def fallback_solve(ps, gel_surface):
    """Analytic (hertz-fallback) stand-in for tools.fe on a period scenario — smoke tests only."""
    from ..twin.physics import HertzFallbackPhysics
    from ..twin.trajectory import Poke

    sc = ps.scenario
    K = len(sc.indenters)
    poke = Poke("resolved", list(ps.names), list(ps.slots),
                np.array([i.position for i in sc.indenters], float), np.array([i.rotation for i in sc.indenters], float),
                np.array([[k.translation for k in i.keypoints] for i in sc.indenters], float).reshape(K, -1, 3),
                np.array([[k.rotation for k in i.keypoints] for i in sc.indenters], float).reshape(K, -1, 3),
                np.asarray(ps.times, float), float(ps.t_init), float(ps.times[-1]))
    res = fallback_result(HertzFallbackPhysics(gel_surface).solve(poke))
    res.scenario_hash = sc.hash()
    res.pose_position = np.transpose(poke.position[:, None, :] + poke.translation, (1, 0, 2))
    return res


def resolved_sources(b, spec) -> list:
    """Label sources of a session from fe/<session>.json (resolve mode), solved periods only."""
    from ..fe import load_result, load_scenario

    doc = json.loads((b.root / "fe" / f"{spec.name}.json").read_text())
    if doc.get("mode") != "resolve":
        raise ValueError(f"{b.root / 'fe' / (spec.name + '.json')}: mode {doc.get('mode')!r}, expected 'resolve' "
                         "(rerun stage fe)")
    out = []
    surf = None
    for per in doc["periods"]:
        if per["status"] != "solved":
            continue
        if b.cfg.physics == "fe":
            res = load_result(fe_cache_dir() / f"{per['scenario']}.npz")
        else:
            if surf is None:
                surf = gel_of(unit_meta(b, spec.serial))[1]
            sc = load_scenario(per["file"])
            ps = SimpleNamespace(scenario=sc, names=per["names"], slots=per["indenters"], times=per["times"],
                                 t_init=per["t_init"])
            res = fallback_solve(ps, surf)
        out.append(SimpleNamespace(times=np.asarray(per["times"], float), slots=list(per["indenters"]), result=res,
                                   t_init=float(per["t_init"]), is_keypoint=np.asarray(per["is_keypoint"], bool),
                                   poke=None, period=int(per["period"]), scenario=per["scenario"]))
    return out
