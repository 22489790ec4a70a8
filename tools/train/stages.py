"""Stage shells of `tensortouch train all` (tools/train/build.py): each reads the build folder, writes its
outputs there and returns a small dict stored in its stamp. Twin sessions are read through
contracts.session; the twin's plan and FE results are reconstructed from the same RecordConfig the
sessions stage used (so the FE scenario hash is checked against truth/truth.json)."""
from __future__ import annotations

import json
import logging
import shlex
import shutil
import time
from pathlib import Path

import numpy as np

from ...contracts.files import atomic_write, atomic_write_json
from .build import fit_dir, pretrain_dir, unit_calibration
from .package import update_manifest
from .sources import fe_mode, fe_results, label_sources, recorder

log = logging.getLogger(__name__)









# ------------------------------------------------------------------------------------------- stages

RATIO_WARN = 1.3       # stage 4: warn when a sim-to-real force ratio is beyond ×/÷ this

# hertz-fallback twin physics (smoke tests only) gives ~5x smaller forces than FE: scaled contact thresholds
FALLBACK_CONTACT_N = (0.3, 0.22)

# the stamp of stages 1, 2 and 4 in a distilled build (BuildConfig.teacher): its targets need no FE labels
DISTILLED = {"skipped": "distilled: the targets are the teacher package's outputs (tools/train/distill.py)"}


def stage_sessions(b) -> dict:
    """Record the twin sessions (FE physics, cached per poke) and write each unit's TRUE calibration
    into the build's store (the twin truth the correspondence stage is checked against)."""
    from ..progress import stage_progress
    from ..twin.record import Recorder
    from ..twin.unit import write_true_calibration
    from .rig_estimate import prepare

    out = {}
    for i, spec in enumerate(b.all_sessions()):
        path = b.session(spec)
        rec = Recorder(spec.record_config(b.cfg.physics, b.cfg.size), path, progress=stage_progress(spec.name))
        version = write_true_calibration(rec.unit, b.store_root, b.cfg.size)
        if (path / "session.json").is_file():
            log.info("[sessions %d/%d] %s already recorded", i + 1, len(b.all_sessions()), spec.name)
        else:
            log.info("[sessions %d/%d] recording %s (unit %s, seed %d, %d pokes)", i + 1, len(b.all_sessions()),
                     spec.name, spec.serial, spec.seed, spec.pokes)
            rec.run()
        if spec.world == "rig":
            out[spec.name] = {"rig_estimate": prepare(path)}
        out[spec.name] = {**out.get(spec.name, {}), "path": str(path), "true_calibration": version}
    return {"sessions": out}


def stage_keypoints(b) -> dict:
    """Stage 1 on every session (measured F/T + mocap) → keypoints/<session>.json."""
    if b.cfg.teacher:
        return DISTILLED
    from ...contracts.session import load_session
    from .keypoints import KeypointConfig, extract_keypoints, keypoints_doc

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
    if b.cfg.teacher:
        return DISTILLED
    if fe_mode(b) != "twin":
        from .resolve_stage import stage_fe_resolve

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
    from .correspondence import build_unit_calibrations

    return build_unit_calibrations(b)


def stage_simreal(b) -> dict:
    """Stage 4: sim-to-real ratios per session and indenter → simreal/<session>.json."""
    if b.cfg.teacher:
        return DISTILLED
    from ...contracts.session import load_session
    from .simreal import session_ratios

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
    from .dataset import DatasetConfig, session_samples, split_pokes, write_dataset

    if b.cfg.teacher:
        return stage_dataset_distilled(b)
    if not b.cfg.train:   # a labels-only build (the label budget's recipes): held-out labels, nothing to train on
        log.info("dataset: no training sessions; the held-out sessions' labels are built, no dataset is written")
        return {"data_hash": "", "samples": 0, "val": 0, "rest": 0}
    work = parts_dir(b)
    dcfg = DatasetConfig(size=b.cfg.size, contact_stride=b.cfg.contact_stride, rest_fraction=b.cfg.rest_fraction)
    parts = []
    for si, spec in enumerate(b.cfg.train):
        part = work / f"{spec.name}-{_inputs_hash(b, spec)}.npz"
        if not part.is_file():
            t0 = time.monotonic()
            rec = recorder(b, spec)
            ratios = json.loads((b.root / "simreal" / f"{spec.name}.json").read_text())["ratios"]
            last = [0.0]

            def prog(i, n, name=spec.name, last=last):
                if time.monotonic() - last[0] > 10 or i == n:
                    last[0] = time.monotonic()
                    log.info("dataset %s: %d/%d samples", name, i, n)
            rat = {int(k): v for k, v in ratios.items()}
            if fe_mode(b) == "twin":
                d = session_samples(b.session(spec), unit_calibration(b, spec.serial), rec.plan, fe_results(b, spec),
                                    [p.slots for p in rec.plan], rat, dcfg, prog)
            else:
                from .labels import LabelConfig, session_samples_measured

                d = session_samples_measured(b.session(spec), unit_calibration(b, spec.serial),
                                             label_sources(b, spec), rat, dcfg,
                                             LabelConfig(frames=b.cfg.label_frames, sigma=b.cfg.label_sigma),
                                             progress=prog)
            atomic_write(part, lambda fh, d=d: np.savez(fh, **d))
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
    drop_parts(b)
    n = sum(len(p["frame"]) for p in parts)
    return {"data_hash": h, "samples": n, "val": int(sum(p["val"].sum() for p in parts)),
            "rest": int(sum((p["poke"] < 0).sum() for p in parts))}


def parts_dir(b) -> Path:
    """Stage 5's per-session parts, per configuration (a changed label source starts anew): they let an
    interrupted stage resume."""
    work = b.dataset / ".work" / b.keys["dataset"]
    work.mkdir(parents=True, exist_ok=True)
    return work


def drop_parts(b) -> None:
    """Remove every configuration's parts once the dataset is written: they are a second copy of every sample
    (11 GB for a 24-unit distilled set)."""
    shutil.rmtree(b.dataset / ".work", ignore_errors=True)


def teacher_package(b) -> Path:
    """The build's teacher package folder (a path relative to the repository root, or absolute)."""
    from ...contracts.errors import ModelPackageError
    from ...contracts.paths import ROOT

    path = Path(b.cfg.teacher)
    path = path if path.is_absolute() else ROOT / path
    if not (path / "manifest.json").is_file():
        raise ModelPackageError(f"teacher {b.cfg.teacher!r}: no model package there (expected {path / 'manifest.json'})")
    return path


def stage_dataset_distilled(b) -> dict:
    """Stage 5 of a distilled build: training sessions' frames + the teacher's outputs → dataset/ (per-session
    parts cached in .work/)."""
    from ...runtime.stages.model import load_package
    from .dataset import DatasetConfig, split_pokes
    from .distill import DistillConfig, distill_session, teacher_bounds, write_distilled
    from .export import session

    teacher = teacher_package(b)
    pkg = load_package(teacher)
    if tuple(pkg.size) != (b.cfg.size, b.cfg.size):
        raise ValueError(f"teacher {teacher}: input {pkg.size}, the build's size is {b.cfg.size}")
    sess = session(pkg.file("int8"), threads=b.cfg.threads)      # what ships is what the student imitates
    name = sess.get_inputs()[0].name

    def run(x):
        return sess.run(None, {name: x})[0]
    work = parts_dir(b)
    dcfg = DatasetConfig(size=b.cfg.size, contact_stride=b.cfg.contact_stride, rest_fraction=b.cfg.rest_fraction)
    parts = []
    for si, spec in enumerate(b.cfg.train):
        part = work / f"{spec.name}.npz"
        if not part.is_file():
            t0 = time.monotonic()
            last = [0.0]

            def prog(i, n, name=spec.name, last=last):
                if time.monotonic() - last[0] > 10 or i == n:
                    last[0] = time.monotonic()
                    log.info("distill %s: %d/%d frames", name, i, n)
            kcfg = DistillConfig(copies=b.cfg.distill_copies, scale_jitter=b.cfg.crop_scale_jitter,
                                 center_jitter_px=b.cfg.crop_center_jitter_px, seed=si)
            d = distill_session(b.session(spec), unit_calibration(b, spec.serial), run, kcfg, dcfg, prog,
                                contacts=b.cfg.measured_force_split)
            atomic_write(part, lambda fh, d=d: np.savez(fh, **d))
            log.info("distill %s: %d samples in %.0f s", spec.name, len(d["frame"]), time.monotonic() - t0)
        with np.load(part) as z:
            d = {k: z[k] for k in z.files}
        val_pokes = split_pokes(spec.pokes, si) if spec.pokes > 1 else set()
        d["val"] = np.isin(d["poke"], list(val_pokes)) & (d["poke"] >= 0)
        parts.append(d)
    source = (f"distilled from {repo_relative_path(teacher)} on twin sessions {[s.name for s in b.cfg.train]} "
              f"(physics={b.cfg.physics}, {b.cfg.distill_copies} jittered crop(s) per frame); tools.train.build {b.cfg.build}")
    area = np.mean([unit_calibration(b, spec.serial).pixel_area for spec in b.cfg.train], axis=0)
    h = write_distilled(b.dataset, parts, teacher_bounds(teacher), b.cfg.size, source, pixel_area=area)
    drop_parts(b)
    n = sum(len(p["frame"]) for p in parts)
    return {"data_hash": h, "samples": n, "val": int(sum(p["val"].sum() for p in parts)),
            "rest": int(sum((p["poke"] < 0).sum() for p in parts)), "teacher": repo_relative_path(teacher),
            "teacher_int8_sha256": pkg.sha256("int8")}


def repo_relative_path(path: Path) -> str:
    from .package import repo_relative

    return repo_relative(path)


def _inputs_hash(b, spec) -> str:
    """Hash of a session's stage 2/3/5 outputs: a dataset part is reused only for the same inputs."""
    import hashlib

    h = hashlib.sha256()
    for f in (b.root / "fe" / f"{spec.name}.json", b.root / "simreal" / f"{spec.name}.json",
              b.root / "correspondence" / f"{spec.serial}.json"):
        h.update(f.read_bytes() if f.is_file() else b"-")
    return h.hexdigest()[:10]




def stage_pretrain(b) -> dict:
    if not b.cfg.train and not b.cfg.teacher:
        from ...contracts.errors import TensorTouchError

        raise TensorTouchError(f"recipe {b.cfg.name!r}: sessions.train is empty, a labels-only build; "
                               "`train dataset` and `train budget` run it, `train all` needs training sessions")
    if b.cfg.pretrain_epochs <= 0:
        return {"skipped": True}
    from .model.train import PretrainConfig, pretrain

    res = pretrain(b.dataset, pretrain_dir(b),
                   PretrainConfig(epochs=b.cfg.pretrain_epochs, batch_size=b.cfg.batch, threads=b.cfg.threads,
                                  device=b.cfg.device))
    return {"samples_per_s": res.get("samples_per_s")}


def stage_fit(b) -> dict:
    from .model.train import FitConfig, fit

    enc = pretrain_dir(b) / "encoder.pt"
    scale_jitter = shift = 0.0
    if b.cfg.augment_crop:      # the centre jitter in px, as a share of the training units' mean crop radius
        radius = float(np.mean([unit_calibration(b, spec.serial).gel_radius_px for spec in b.cfg.train]))
        scale_jitter, shift = b.cfg.crop_scale_jitter, b.cfg.crop_center_jitter_px / radius
    res = fit(b.dataset, fit_dir(b),
              FitConfig(arch=b.cfg.arch, epochs=b.cfg.epochs, batch_size=b.cfg.batch, lr=b.cfg.lr,
                        threads=b.cfg.threads, fg_weight=b.cfg.fg_weight, force_weight=b.cfg.force_weight,
                        light_weight=b.cfg.light_weight, pixel_force_weight=b.cfg.pixel_force_weight,
                        measured_force_weight=b.cfg.measured_force_weight,
                        measured_force_split=b.cfg.measured_force_split, seed=b.cfg.fit_seed,
                        photometric=b.cfg.photometric, crop_scale_jitter=scale_jitter, crop_shift=shift,
                        init_from=b.cfg.init_from, init_bounds=b.cfg.init_bounds, device=b.cfg.device),
              encoder_init=enc if (b.cfg.pretrain_epochs > 0 and enc.is_file() and b.cfg.arch == "hiera_qup") else None)
    return {"params": res["params"], "metrics": res["metrics"]["mean"], "samples_per_s": res.get("samples_per_s")}


def build_wall_time(b, extra: float = 0.0) -> float:
    from .build import STAGES

    return float(sum(b.read_stamp(s).get("seconds", 0.0) for s in STAGES) + extra)


def stage_export(b) -> dict:
    from ...contracts.paths import models_dir
    from .export import ExportConfig, export_run

    root = Path(b.cfg.models_dir) if b.cfg.models_dir else models_dir()
    t0 = time.monotonic()
    cmd = b.command or shlex.join(["tensortouch", "train", "all", "--name", b.cfg.name])
    man = export_run(fit_dir(b), b.dataset, b.cfg.name, root, cmd,
                     ExportConfig(quantization_samples=b.cfg.quantization_samples,
                                  quantization_pick=b.cfg.quantization_pick, latency_runs=b.cfg.latency_runs,
                                  scheme=b.cfg.quantization_scheme),
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
    from .threshold import ThresholdConfig, measure

    specs = list(b.cfg.train)
    k = max(1, min(len(specs), b.cfg.threshold_sessions))
    pick = [specs[int(i)] for i in np.unique(np.linspace(0, len(specs) - 1, k).round().astype(int))]
    return measure(package_dir, [(b.session(s), unit_calibration(b, s.serial)) for s in pick],
                   ThresholdConfig(support_px=b.cfg.support_px or None))



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
    """Stage 8 of a build: held-out sessions (+ the shipped demo) → eval/*.json, docs figures."""
    from ...contracts.paths import demo_dir, models_dir
    from ...contracts.store import CalibrationStore
    from ...runtime.stages.model import load_package
    from .evaluate import EvalConfig, evaluate_session, summarize

    root = Path(b.cfg.models_dir) if b.cfg.models_dir else models_dir()
    package = load_package(root / b.cfg.name)
    targets = [(s.name, b.session(s), unit_calibration(b, s.serial)) for s in b.cfg.heldout]
    if b.cfg.eval_demo and (demo_dir() / "session.json").is_file():
        try:
            targets.append(("demo", demo_dir(), CalibrationStore().load("TWIN-DEMO")))
        except Exception as exc:  # noqa: BLE001 — the demo is optional for a build
            log.warning("demo evaluation skipped: %s", exc)
    summary = {}
    for name, path, cal in targets:
        if tuple(cal.model_size) != tuple(package.size):
            log.warning("%s: calibration size %s ≠ model %s; skipped", name, cal.model_size, package.size)
            continue
        r = evaluate_session(path, package, cal, EvalConfig(contact_n=b.cfg.eval_contact_n))
        s = summarize(r["rows"], r["rest"], r["phantoms"])
        summary[name] = s
        (b.root / "eval").mkdir(exist_ok=True)
        (b.root / "eval" / f"{name}.json").write_text(json.dumps({"summary": s, "rows": r["rows"],
                                                                  "trace": r["trace"]}, indent=0))
        log.info("evaluate %s: %s", name, json.dumps(s))
    (b.root / "eval" / "summary.json").write_text(json.dumps(summary, indent=1))
    if b.cfg.figures and b.cfg.heldout:
        from .figures import write_figures

        write_figures(b, package)
    return {"summary": summary}
