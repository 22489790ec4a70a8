"""Stage 8 — evaluation as seed §V-A on held-out twin sessions, through the runtime's own code path.

Every frame of a session goes through `runtime.pipeline.SensorPipeline` (preprocess, dynamic baseline,
the shipped int8 model, contact clustering) exactly as `tensortouch run` does. For frames where an
indenter's measured force (F/T rotated into the sensor frame) exceeds the seed's contact threshold,
the cluster nearest to that indenter's mocap tip is compared with it:
- position: cluster centroid (mm, sensor frame) − mocap tip position, per axis;
- force: cluster force − the force the indenter applies (= −F/T reading in the sensor frame), per
  axis and magnitude; a contact frame without any cluster counts as a miss (predicted force 0).
Rest frames (all measured |F| < `rest_n`) report the predicted total force (should be 0).

Pure core: `frame_errors`, `summarize`. Shells: `evaluate_session`, `evaluate_build`, figures.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvalConfig:
    contact_n: float = 1.5        # seed §III.C contact threshold on the measured force
    rest_n: float = 0.2           # all indenters below this: a rest frame
    precision: str = "int8"
    threads: int = 1


def measured_at(session, t: np.ndarray) -> dict[int, dict]:
    """Per indenter id: mocap tip (T, 3) and applied force (T, 3) = −F/T rotated to the sensor frame."""
    from tools.train.simreal import ft_to_sensor

    wr, po = session.table("wrench"), session.table("poses")
    rot = session.streams["wrench"]["ft_to_indenter"]["rotation_wxyz"]
    out = {}
    for k in sorted(set(wr[:, 1].astype(int))):
        w, p = wr[wr[:, 1] == k], po[po[:, 1] == k]
        f_ft = np.stack([np.interp(t, w[:, 0], w[:, 2 + c]) for c in range(3)], 1)
        near = np.clip(np.searchsorted(p[:, 0], t), 0, len(p) - 1)
        tip = np.stack([np.interp(t, p[:, 0], p[:, 2 + c]) for c in range(3)], 1)
        out[k] = {"tip": tip, "force": -ft_to_sensor(f_ft, p[near, 5:9], rot)}
    return out


def frame_errors(clusters: list, tips: np.ndarray, forces: np.ndarray, cfg: EvalConfig = EvalConfig()) -> list[dict]:
    """Match one frame's clusters (centroid_mm, force_n) to the indenters in contact (tips/forces (K, 3))
    by nearest centroid (each cluster used once); one row per indenter in contact."""
    rows, used = [], set()
    for k in np.argsort(-np.linalg.norm(forces, axis=1)):
        if np.linalg.norm(forces[k]) < cfg.contact_n:
            continue
        best, dist = None, np.inf
        for ci, c in enumerate(clusters):
            d = float(np.linalg.norm(np.asarray(c.centroid_mm) - tips[k]))
            if ci not in used and d < dist:
                best, dist = ci, d
        row = {"indenter": int(k), "meas_force": forces[k].tolist(), "tip": tips[k].tolist()}
        if best is None:
            row.update(miss=True, pred_force=[0.0, 0.0, 0.0], pred_pos=None)
        else:
            used.add(best)
            c = clusters[best]
            row.update(miss=False, pred_force=list(map(float, c.force_n)), pred_pos=list(map(float, c.centroid_mm)))
        rows.append(row)
    return rows


def summarize(rows: list[dict], rest_forces: list[float]) -> dict:
    """Seed §V-A style numbers from matched rows: mean absolute errors per axis and of |F|."""
    if not rows:
        return {"contact_samples": 0}
    mf = np.array([r["meas_force"] for r in rows])
    pf = np.array([r["pred_force"] for r in rows])
    hit = np.array([not r["miss"] for r in rows])
    out = {"contact_samples": len(rows), "detected_fraction": float(hit.mean()),
           "force_mae_n": dict(zip("xyz", np.abs(pf - mf).mean(0).round(4).tolist())),
           "force_mag_mae_n": float(np.abs(np.linalg.norm(pf, axis=1) - np.linalg.norm(mf, axis=1)).mean()),
           "force_mag_mean_meas_n": float(np.linalg.norm(mf, axis=1).mean()),
           "force_mag_bias_n": float((np.linalg.norm(pf, axis=1) - np.linalg.norm(mf, axis=1)).mean())}
    if hit.any():
        pp = np.array([r["pred_pos"] for r in rows if not r["miss"]])
        tp = np.array([r["tip"] for r in rows if not r["miss"]])
        out["position_mae_mm"] = dict(zip("xyz", np.abs(pp - tp).mean(0).round(4).tolist()))
        out["position_bias_mm"] = dict(zip("xyz", (pp - tp).mean(0).round(4).tolist()))
    rf = np.asarray(rest_forces, float)
    out["rest_frames"] = int(len(rf))
    if len(rf):
        out["rest_force_mean_n"] = float(rf.mean())
        out["rest_false_contact_fraction"] = float((rf > 0.0).mean())
    return out


def evaluate_session(session_dir, package, calibration, cfg: EvalConfig = EvalConfig(), keep_fields_at=None) -> dict:
    """Run the runtime pipeline over a session; returns rows, rest forces, per-frame traces."""
    import cv2

    from runtime.model import FieldModel
    from runtime.pipeline import SensorPipeline
    from runtime.session import load_session
    from tools.sessions.writer import read_frames

    ses = load_session(session_dir)
    frames = ses.table("frames")
    meas = measured_at(ses, frames[:, 0])
    ids = sorted(meas)
    pipe = SensorPipeline(ses.sensor_id, FieldModel(package, cfg.precision, cfg.threads), calibration)
    rows, rest, trace, kept = [], [], [], None
    for i, img in read_frames(ses):
        t = float(frames[i, 0])
        res = pipe.process(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), t)
        tips = np.array([meas[k]["tip"][i] for k in ids])
        forces = np.array([meas[k]["force"][i] for k in ids])
        trace.append({"t": t, "meas": forces.sum(0).tolist(), "pred": res.force_n.tolist(),
                      "state": res.state, "n_clusters": len(res.clusters)})
        if res.fields is None:
            continue
        if keep_fields_at is not None and i == keep_fields_at:
            kept = {"fields": res.fields.copy(), "frame": i, "image": img[:, :, ::-1].copy()}
        mags = np.linalg.norm(forces, axis=1)
        if np.all(mags < cfg.rest_n):
            rest.append(float(np.linalg.norm(res.force_n)))
        for r in frame_errors(res.clusters, tips, forces, cfg):
            r.update(t=t, frame=i)
            rows.append(r)
    return {"rows": rows, "rest": rest, "trace": trace, "kept": kept, "sensor": ses.sensor_id}


def evaluate_build(b) -> dict:
    """Stage 8 of a build: held-out sessions (+ the shipped demo) → eval/*.json, docs figures."""
    from runtime.calibration import CalibrationStore
    from runtime.model import load_package
    from runtime.paths import demo_dir, models_dir
    from tools.train.stages import unit_calibration

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
        s = summarize(r["rows"], r["rest"])
        summary[name] = s
        (b.root / "eval").mkdir(exist_ok=True)
        (b.root / "eval" / f"{name}.json").write_text(json.dumps({"summary": s, "rows": r["rows"],
                                                                  "trace": r["trace"]}, indent=0))
        log.info("evaluate %s: %s", name, json.dumps(s))
    (b.root / "eval" / "summary.json").write_text(json.dumps(summary, indent=1))
    if b.cfg.figures and b.cfg.heldout:
        from tools.train.figures import write_figures

        write_figures(b, package)
    return {"summary": summary}
