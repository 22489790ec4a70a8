"""Stage 2 shell (real-rig path, `--fe resolve`, the default): stage-1 keypoints → FE scenarios →
tools.fe batch runner (shared on-disk cache keyed by scenario hash, resume, progress) → fe/<session>.json.

Inputs per session — all things a real rig has, none of the twin's truth: the measured `poses` and
`wrench` streams, the stage-1 keypoint file, the mounted indenters' names (`streams.poses.indenters`)
looked up in the indenter catalog (the FE indenter set of tools.twin.trajectory.INDENTER_SET: shape and
size per name), and the unit's gel design geometry from its calibration (`meta.gel`).

fe/<session>.json (`tensortouch.train_fe` v2, mode "resolve"): per contact period the scenario file
and hash, its FE frame times, which are stage-1 keypoints, the initial-pose time, the indenter ids,
and the status (solved / failed / skipped with the reason). Results live in `<cache>/fe/<hash>.npz`
(tools.fe.batch default folder), shared by every build: a rebuild with the same sessions solves nothing.
With hertz-fallback physics (smoke test only) the analytic twin solver stands in for tools.fe.
"""
from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from .build import unit_meta
from .sources import fe_cache_dir, gel_of, label_solver

log = logging.getLogger(__name__)

SCHEMA = "tensortouch.train_fe"




def session_scenarios(session_dir: Path, keypoint_file: Path, calibration_meta: dict, catalog=None, cfg=None,
                      solver=None):
    """[(period index, PeriodScenario | None, error str)] of one session; `solver`: tools.fe SolverSettings
    of the label solves (None: the default)."""
    from ...contracts.session import load_session
    from ..twin.trajectory import INDENTER_SET
    from .resolve import PoseTrack, ResolveConfig, ResolveError, period_scenario

    cfg = cfg or ResolveConfig()
    catalog = catalog or INDENTER_SET
    ses = load_session(session_dir, check_frames=False)
    names = {int(k): v for k, v in ses.streams["poses"].get("indenters", {}).items()}
    poses = ses.table("poses")
    doc = json.loads(Path(keypoint_file).read_text())
    gel, surf = gel_of(calibration_meta)
    out = []
    for i, per in enumerate(doc["periods"]):
        slots = [int(k) for k in per["indenters"]]
        try:
            missing = [k for k in slots if k not in names]
            if missing:
                raise ResolveError(f"{session_dir}/session.json: streams.poses.indenters names no indenter {missing}")
            tracks = [PoseTrack.from_table(poses, k) for k in slots]
            ps = period_scenario(tracks, slots, [names[k] for k in slots], np.asarray(per["t"], float), catalog,
                                 gel, surf, cfg, solver=solver)
            out.append((i, ps, ""))
        except ResolveError as exc:
            log.warning("%s period %d: no FE scenario (%s)", Path(session_dir).name, i, exc)
            out.append((i, None, str(exc)))
    return out



def stage_fe_resolve(b, cfg=None) -> dict:
    """Stage 2 (resolve) over every session of the build; returns counts for the stamp."""
    from ...contracts.files import atomic_write_json
    from ..fe import save_scenario
    from ..fe.batch import run_batch
    from .resolve import ResolveConfig

    cfg = cfg or ResolveConfig()
    docs, jobs = {}, []
    solver = label_solver(b)
    for spec in b.all_sessions():
        meta = unit_meta(b, spec.serial)
        items = session_scenarios(b.session(spec), b.root / "keypoints" / f"{spec.name}.json", meta, cfg=cfg,
                                  solver=solver)
        periods = []
        for i, ps, err in items:
            if ps is None:
                periods.append({"period": i, "status": "skipped", "error": err})
                continue
            f = b.root / "fe" / "scenarios" / spec.name / f"p{i:02d}.json"
            save_scenario(ps.scenario, f)
            periods.append({"period": i, "status": "pending", "file": str(f), "scenario": ps.scenario.hash(),
                            "indenters": ps.slots, "names": ps.names, "t_init": ps.t_init,
                            "times": [round(float(x), 6) for x in ps.times],
                            "is_keypoint": [bool(x) for x in ps.is_keypoint],
                            "frames": len(ps.times), "keypoints": int(np.sum(ps.is_keypoint))})
            jobs.append((spec.name, len(periods) - 1, f, ps))
        docs[spec.name] = {"schema": SCHEMA, "schema_version": 2, "session": spec.name, "mode": "resolve",
                           "physics": b.cfg.physics, "cache": str(fe_cache_dir()), "periods": periods}
    if b.cfg.physics == "fe" and jobs:
        cache = fe_cache_dir()
        log.info("stage fe: %d period scenarios over %d sessions → tools.fe batch (cache %s, %d worker(s))",
                 len(jobs), len(docs), cache, cfg.workers)
        cluster = b.cfg.fe_cluster or None
        run_batch([str(f) for _, _, f, _ in jobs], cache, workers=cfg.workers, cluster=cluster)
        retry = []
        for name, j, _f, _ps in jobs:
            h = ps.scenario.hash()
            if not (cache / f"{h}.npz").is_file():   # one retry with smaller increments (new hash)
                sc = ps.scenario
                sv = sc.solver
                sc2 = replace(sc, solver=replace(sv, max_increment_mm=sv.max_increment_mm * cfg.retry_increment_factor,
                                                 max_increment_rad=sv.max_increment_rad * cfg.retry_increment_factor))
                f2 = f.with_name(f.stem + "-retry.json")
                save_scenario(sc2, f2)
                retry.append((name, j, f2, sc2.hash(), h))
        if retry:
            log.warning("stage fe: %d scenario(s) failed; retrying with smaller increments", len(retry))
            run_batch([str(f2) for _, _, f2, _, _ in retry], cache, workers=cfg.workers, cluster=cluster)
        fixed = {(n, j): (f2, h2, h) for n, j, f2, h2, h in retry}
        for name, j, _f, _ps in jobs:
            per = docs[name]["periods"][j]
            if (name, j) in fixed:
                f2, h2, h = fixed[(name, j)]
                if (cache / f"{h2}.npz").is_file():
                    per.update(file=str(f2), scenario=h2, retried_from=h)
                else:
                    failed = cache / f"{h2}.failed.json"
                    per.update(status="failed", error=json.loads(failed.read_text()).get("error", "") if failed.is_file() else "no result")
                    continue
            per["status"] = "solved"
    else:
        for name, j, _f, _ps in jobs:
            docs[name]["periods"][j]["status"] = "solved"
    out = {}
    for name, doc in docs.items():
        atomic_write_json(b.root / "fe" / f"{name}.json", doc)
        st = [p["status"] for p in doc["periods"]]
        out[name] = {"periods": len(st), "solved": st.count("solved"), "failed": st.count("failed"),
                     "skipped": st.count("skipped"),
                     "fe_frames": sum(p.get("frames", 0) for p in doc["periods"] if p["status"] == "solved")}
    return {"mode": "resolve", "sessions": out}


