"""Stage shells of `tensortouch train all` (tools/train/build.py): each reads the build folder, writes its
outputs there and returns a small dict stored in its stamp. Twin sessions are read through
runtime.session; the twin's plan and FE results are reconstructed from the same RecordConfig the
sessions stage used (so the FE scenario hash is checked against truth/truth.json)."""
from __future__ import annotations

import json
import logging
import shlex
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from runtime.files import atomic_write, atomic_write_json

log = logging.getLogger(__name__)


def recorder(b, spec):
    """The twin Recorder of a session spec (not run): plan, unit, modules, physics config."""
    from tools.twin.record import Recorder

    return Recorder(spec.record_config(b.cfg.physics, b.cfg.size), b.session(spec))


def fe_results(b, spec) -> list:
    """Twin mode (`--fe twin`): the FE results (tools.fe.FEResult) of every poke of a session: the very
    solves the twin recorded with (truth/truth.json `fe_scenarios`, loaded from the FE cache), so labels,
    images and F/T come from one physics even if tools/fe changed since; a solve missing from the cache is
    redone with the current FE (its hash then differs and a warning says so). With hertz-fallback physics
    (smoke tests only) the twin's PokeSolve stands in."""
    from tools.fe import load_result
    from tools.twin.record import make_physics

    rec = recorder(b, spec)
    physics = make_physics(rec.cfg, rec.unit)
    if b.cfg.physics != "fe":
        return [_fallback_result(physics.solve(p)) for p in rec.plan]
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
    from tools.train.resolve_stage import resolved_sources

    return resolved_sources(b, spec)


def _fallback_result(ps):
    """A PokeSolve of the analytic fallback shaped like an FEResult (no stress, contact forces from the
    reaction spread over the touched nodes) — only so the smoke test can run the chain without FE."""
    J, N = ps.U.shape[:2]
    K = ps.RF.shape[1]
    from tools.twin.geometry import GelSurface

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

    from tools.train.fields import _disc, surface_angles

    tris = Delaunay(_disc(*surface_angles(ps.nodes))).simplices
    return SimpleNamespace(nodes=ps.nodes, surface_nodes=np.arange(N), surface_tris=tris, U=ps.U,
                           S=np.zeros((J, N, 6)), CNORMF=cn, CSHEAR=np.zeros_like(cn), contact_owner=owner,
                           RF=ps.RF, pose_position=np.zeros((J, K, 3)), scenario_hash=ps.key)


def unit_meta(b, serial: str) -> dict:
    """The unit's current calibration metadata (gel design geometry `gel`, camera) — what a real rig's
    calibration store holds before any training stage runs."""
    from runtime.calibration import CalibrationStore

    return CalibrationStore(b.store_root).load(serial).meta


def unit_calibration(b, serial: str):
    """The calibration the dataset and evaluation use for a unit (stage 3's choice)."""
    from runtime.calibration import CalibrationStore

    info = json.loads((b.root / "correspondence" / f"{serial}.json").read_text())
    return CalibrationStore(b.store_root).load(serial, info["version"])


# ------------------------------------------------------------------------------------------- stages

RATIO_WARN = 1.3       # stage 4: warn when a sim-to-real force ratio is beyond ×/÷ this

# hertz-fallback twin physics (smoke tests only) gives ~5x smaller forces than FE: scaled contact thresholds
FALLBACK_CONTACT_N = (0.3, 0.22)


def stage_keypoints(b) -> dict:
    """Stage 1 on every session (measured F/T + mocap) → keypoints/<session>.json."""
    from runtime.session import load_session
    from tools.train.keypoints import KeypointConfig, extract_keypoints, keypoints_doc

    kcfg = KeypointConfig(contact_force_n=b.cfg.contact_force_n, detach_force_n=b.cfg.detach_force_n)
    if b.cfg.physics != "fe":
        kcfg = KeypointConfig(contact_force_n=FALLBACK_CONTACT_N[0], detach_force_n=FALLBACK_CONTACT_N[1])
    out = {}
    for spec in b.all_sessions():
        path = b.root / "keypoints" / f"{spec.name}.json"
        ses = load_session(b.session(spec), check_frames=False)
        kps = extract_keypoints(ses.table("poses"), ses.table("wrench"), ses.table("frames"), kcfg)
        doc = keypoints_doc(ses, kps, kcfg, str(b.session(spec).resolve()))
        atomic_write_json(path, doc)
        plan = recorder(b, spec).plan   # reported only (periods vs the twin's plan), never used downstream
        out[spec.name] = {"periods": len(doc["periods"]), "keypoints": sum(len(p["t"]) for p in doc["periods"]),
                          "planned_pokes": len(plan), "planned_keypoints": int(sum(len(p.times) for p in plan))}
    return {"sessions": out}


def stage_fe(b) -> dict:
    """Stage 2. resolve (default): FE scenarios from the stage-1 keypoints of the measured streams,
    solved by tools.fe's batch runner (tools/train/resolve_stage.py). twin: the twin's cached solves of
    the session's plan (re-solved when missing from the cache); lists any poke whose solve was redone."""
    if fe_mode(b) != "twin":
        from tools.train.resolve_stage import stage_fe_resolve

        return stage_fe_resolve(b)
    out = {}
    for spec in b.all_sessions():
        truth = json.loads((b.session(spec) / "truth" / "truth.json").read_text())
        res = fe_results(b, spec)
        hashes = [str(r.scenario_hash) for r in res]
        doc = {"session": spec.name, "mode": "twin", "scenarios": hashes, "frames": [int(r.U.shape[0]) for r in res],
               "recorded_scenarios": truth.get("fe_scenarios", []),
               "resolved": [h for h in hashes if h not in truth.get("fe_scenarios", [])]}
        atomic_write_json(b.root / "fe" / f"{spec.name}.json", doc)
        out[spec.name] = doc["frames"]
    return {"fe_frames": out}


def stage_correspondence(b) -> dict:
    from tools.train.correspondence import build_unit_calibrations

    return build_unit_calibrations(b)


def stage_simreal(b) -> dict:
    """Stage 4: sim-to-real ratios per session and indenter → simreal/<session>.json."""
    from runtime.session import load_session
    from tools.train.simreal import session_ratios

    out = {}
    for spec in b.all_sessions():
        rec = recorder(b, spec)
        src = label_sources(b, spec)
        r = session_ratios(load_session(b.session(spec), check_frames=False), src,
                           [x.slots for x in src], [x.result.RF for x in src])
        doc = {"session": spec.name, "fe": fe_mode(b), "ratios": {str(k): v for k, v in r.items()},
               "twin_stiffness_scale": rec.unit.params.stiffness_scale}
        atomic_write_json(b.root / "simreal" / f"{spec.name}.json", doc)
        far = {k: round(v["magnitude"], 2) for k, v in r.items() if abs(np.log(v["magnitude"])) > np.log(RATIO_WARN)}
        if far:
            log.warning("sim-to-real %s: force ratios %s far from 1: the FE (tools.fe settings, material) and the "
                        "recorded gel disagree that much; labels get the ratios, but displacement/stress fields "
                        "keep the FE's shape (twin sessions recorded with an older tools.fe show this)", spec.name, far)
        out[spec.name] = {"magnitude": {k: round(v["magnitude"], 4) for k, v in doc["ratios"].items()},
                          "twin_stiffness_scale": round(rec.unit.params.stiffness_scale, 4)}
    return {"ratios": out}


def stage_dataset(b) -> dict:
    """Stage 5 + sample selection: training sessions → dataset/ (per-session parts cached in .work/)."""
    from tools.train.dataset import DatasetConfig, session_samples, split_pokes, write_dataset

    work = b.dataset / ".work" / b.keys["dataset"]   # per configuration: a changed label source starts anew
    work.mkdir(parents=True, exist_ok=True)
    dcfg = DatasetConfig(size=b.cfg.size, contact_stride=b.cfg.contact_stride, rest_fraction=b.cfg.rest_fraction)
    parts = []
    for si, spec in enumerate(b.cfg.train):
        part = work / f"{spec.name}-{_inputs_hash(b, spec)}.npz"
        if not part.is_file():
            t0 = time.monotonic()
            rec = recorder(b, spec)
            ratios = json.loads((b.root / "simreal" / f"{spec.name}.json").read_text())["ratios"]
            last = [0.0]

            def prog(i, n, name=spec.name):
                if time.monotonic() - last[0] > 10 or i == n:
                    last[0] = time.monotonic()
                    log.info("dataset %s: %d/%d samples", name, i, n)
            rat = {int(k): v for k, v in ratios.items()}
            if fe_mode(b) == "twin":
                d = session_samples(b.session(spec), unit_calibration(b, spec.serial), rec.plan, fe_results(b, spec),
                                    [p.slots for p in rec.plan], rat, dcfg, prog)
            else:
                from tools.train.labels import session_samples_measured

                d = session_samples_measured(b.session(spec), unit_calibration(b, spec.serial),
                                             label_sources(b, spec), rat, dcfg, progress=prog)
            atomic_write(part, lambda fh: np.savez(fh, **d))
            log.info("dataset %s: %d samples in %.0f s", spec.name, len(d["frame"]), time.monotonic() - t0)
        with np.load(part) as z:
            d = {k: z[k] for k in z.files}
        n_src = spec.pokes if fe_mode(b) == "twin" else int(d["poke"].max() + 1) if len(d["poke"]) else 1
        val_pokes = split_pokes(n_src, si) if n_src > 1 else set()   # one contact only: keep it for training
        d["val"] = np.isin(d["poke"], list(val_pokes)) & (d["poke"] >= 0)
        parts.append(d)
    source = (f"twin sessions {[s.name for s in b.cfg.train]} (FE physics={b.cfg.physics}, labels fe={fe_mode(b)}, "
              f"tables={b.cfg.tables}); "
              f"tools.train.build {b.cfg.build}")
    area = np.mean([unit_calibration(b, spec.serial).pixel_area for spec in b.cfg.train], axis=0)
    h = write_dataset(b.dataset, parts, b.cfg.size, source, pixel_area=area)
    n = sum(len(p["frame"]) for p in parts)
    return {"data_hash": h, "samples": n, "val": int(sum(p["val"].sum() for p in parts)),
            "rest": int(sum((p["poke"] < 0).sum() for p in parts))}


def _inputs_hash(b, spec) -> str:
    """Hash of a session's stage 2/3/5 outputs: a dataset part is reused only for the same inputs."""
    import hashlib

    h = hashlib.sha256()
    for f in (b.root / "fe" / f"{spec.name}.json", b.root / "simreal" / f"{spec.name}.json",
              b.root / "correspondence" / f"{spec.serial}.json"):
        h.update(f.read_bytes() if f.is_file() else b"-")
    return h.hexdigest()[:10]


def pretrain_dir(b) -> Path:
    """Run folder of the MAE pretraining (one per configuration, so a changed budget starts anew)."""
    return b.root / "runs" / f"pretrain-{b.keys['pretrain']}"


def fit_dir(b) -> Path:
    return b.root / "runs" / f"fit-{b.keys['fit']}"


def stage_pretrain(b) -> dict:
    if b.cfg.pretrain_epochs <= 0:
        return {"skipped": True}
    from tools.train.model.train import PretrainConfig, pretrain

    res = pretrain(b.dataset, pretrain_dir(b),
                   PretrainConfig(epochs=b.cfg.pretrain_epochs, batch_size=b.cfg.batch, threads=b.cfg.threads,
                                  device=b.cfg.device))
    return {"samples_per_s": res.get("samples_per_s")}


def stage_fit(b) -> dict:
    from tools.train.model.train import FitConfig, fit

    enc = pretrain_dir(b) / "encoder.pt"
    res = fit(b.dataset, fit_dir(b),
              FitConfig(arch=b.cfg.arch, epochs=b.cfg.epochs, batch_size=b.cfg.batch, lr=b.cfg.lr,
                        threads=b.cfg.threads, fg_weight=b.cfg.fg_weight, force_weight=b.cfg.force_weight,
                        light_weight=b.cfg.light_weight,
                        init_from=b.cfg.init_from, init_bounds=b.cfg.init_bounds, device=b.cfg.device),
              encoder_init=enc if (b.cfg.pretrain_epochs > 0 and enc.is_file() and b.cfg.arch == "hiera_qup") else None)
    return {"params": res["params"], "metrics": res["metrics"]["mean"], "samples_per_s": res.get("samples_per_s")}


def build_wall_time(b, extra: float = 0.0) -> float:
    from tools.train.build import STAGES

    return float(sum(b.read_stamp(s).get("seconds", 0.0) for s in STAGES) + extra)


def stage_export(b) -> dict:
    from runtime.paths import models_dir
    from tools.train.export import ExportConfig, export_run

    root = Path(b.cfg.models_dir) if b.cfg.models_dir else models_dir()
    t0 = time.monotonic()
    cmd = b.command or shlex.join(["tensortouch", "train", "all", "--name", b.cfg.name])
    man = export_run(fit_dir(b), b.dataset, b.cfg.name, root, cmd,
                     ExportConfig(quantization_samples=b.cfg.quantization_samples,
                                  quantization_pick=b.cfg.quantization_pick, latency_runs=b.cfg.latency_runs),
                     wall_time_s=build_wall_time(b, 0.0))
    m = man["metrics"]
    thr = package_threshold(b, root / b.cfg.name)
    if b.cfg.init_from:
        _record_init(root / b.cfg.name, Path(b.cfg.init_from))
    # the manifest's wall time is the whole build up to and including export: rewrite it once known
    total = build_wall_time(b, time.monotonic() - t0)
    _set_wall_time(root / b.cfg.name, total)
    return {"package": str(root / b.cfg.name), "psnr_fp32": m["fp32"]["psnr"], "psnr_int8": m["int8"]["psnr"],
            "latency_ms": {"fp32": m["latency_ms"]["fp32"], "int8": m["latency_ms"]["int8"]},
            "wall_time_s": total, "threshold_n": thr["threshold_n"]}


def package_threshold(b, package_dir: Path) -> dict:
    """The package's contact threshold from up to `threshold_sessions` training sessions spread over
    the list (tools/train/threshold.py), recorded in its manifest."""
    from tools.train.threshold import ThresholdConfig, measure

    specs = list(b.cfg.train)
    k = max(1, min(len(specs), b.cfg.threshold_sessions))
    pick = [specs[int(i)] for i in np.unique(np.linspace(0, len(specs) - 1, k).round().astype(int))]
    return measure(package_dir, [(b.session(s), unit_calibration(b, s.serial)) for s in pick],
                   ThresholdConfig(support_px=b.cfg.support_px or None))


def update_manifest(folder: Path, change) -> None:
    """Apply `change(manifest)` to a package's manifest.json and write it atomically (the manifest is
    not itself hashed, so export-time records such as wall time, threshold, init checkpoint go here)."""
    p = Path(folder) / "manifest.json"
    man = json.loads(p.read_text())
    change(man)
    atomic_write_json(p, man)


def _record_init(folder: Path, state: Path) -> None:
    """A fine-tuned package names the checkpoint it started from (path, SHA-256, that run's fit config)."""
    import hashlib

    run_cfg = state.parent / "config.json"
    init = {"state_dict": str(state), "sha256": hashlib.sha256(state.read_bytes()).hexdigest(),
            "fit_config": json.loads(run_cfg.read_text()) if run_cfg.is_file() else None}
    update_manifest(folder, lambda man: man["training"].update(init_from=init))


def _set_wall_time(folder: Path, seconds: float) -> None:
    """Record the build's wall time in the manifest."""
    update_manifest(folder, lambda man: man["training"].update(wall_time_s=round(float(seconds), 1)))


def stage_evaluate(b) -> dict:
    from tools.train.evaluate import evaluate_build

    return evaluate_build(b)
