"""Replaying recordings through the runtime once and re-applying corrections (twin recalibration bench).

`collect_frames` runs a recording through runtime.pipeline.SensorPipeline with the correction off and
keeps each frame's clusters (optionally cached as .npz, no pickle); `corrected_frames` applies a
calibration's correction to them exactly as the pipeline's correction stage does; `held_out_pokes`
pairs them with a reference force stream, one row per poke of the reference (as
tools.recalib.evaluate.measure_pokes).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def collect_frames(session_dir: Path, cal, package, precision: str, cache: Path | None = None) -> list:
    """(t, clusters) of every frame of a replayed recording, raw model force (correction off).
    With `cache`, the clusters are kept in an .npz per (session, model file, runtime sources, calibration
    tables and crop, the package's pipeline configuration: its measured contact threshold, rule, support
    and merging), so a rerun (other fits, other feature sets) does not run the model again."""
    from dataclasses import asdict

    from runtime.contacts import Cluster
    from runtime.pipeline import PipelineConfig

    key = None
    if cache is not None:
        import hashlib

        pipe_cfg = json.dumps(asdict(PipelineConfig.for_package(package)), sort_keys=True)
        h = hashlib.sha256(f"{Path(session_dir).name}|{package.sha256(precision)}|{runtime_sources_hash()}|{pipe_cfg}".encode())
        for name in ("theta", "phi", "surface_xyz", "pixel_area", "mask"):
            h.update(np.ascontiguousarray(getattr(cal, name)).tobytes())
        h.update(json.dumps([*cal.gel_center_px, cal.gel_radius_px]).encode())
        key = Path(cache) / f"{Path(session_dir).name}-{h.hexdigest()[:12]}.npz"
        if key.is_file():
            z = np.load(key, allow_pickle=False)
            frames = [(float(t), []) for t in z["t"]]
            for row in z["clusters"]:
                i = int(row[0])
                frames[i][1].append(Cluster(id=int(row[1]), centroid_px=(row[2], row[3]),
                                            centroid_mm=(row[4], row[5], row[6]), normal=(0.0, 0.0, 1.0),
                                            area_mm2=float(row[7]), force_n=(row[8], row[9], row[10]),
                                            force_mag_n=float(row[11]), pixels=0, perimeter_px=0.0, circularity=0.0))
            return frames
    frames = _run_pipeline(session_dir, cal, package, precision)
    if key is not None:
        rows = [[i, c.id, *c.centroid_px, *c.centroid_mm, c.area_mm2, *c.force_n, c.force_mag_n]
                for i, (_, cl) in enumerate(frames) for c in cl]
        key.parent.mkdir(parents=True, exist_ok=True)
        tmp = key.with_name(key.name + ".tmp.npz")
        np.savez(tmp, t=np.array([t for t, _ in frames]), clusters=np.array(rows, float).reshape(-1, 12))
        tmp.replace(key)
    return frames


def runtime_sources_hash() -> str:
    """sha256 of the runtime package's sources: cached clusters are stale when the pipeline changes
    (e.g. a new contact threshold), not only when the model or the calibration does."""
    import hashlib

    import runtime

    h = hashlib.sha256()
    for f in sorted(Path(runtime.__file__).parent.glob("*.py")):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _run_pipeline(session_dir: Path, cal, package, precision: str) -> list:
    from drivers.camera import camera_from_uri
    from drivers.camera.camera import EndOfStream
    from runtime.correction import ForceCorrection
    from runtime.model import FieldModel
    from runtime.pipeline import SensorPipeline

    pipe = SensorPipeline(cal.sensor_id, FieldModel(package, precision), cal, correction=ForceCorrection(None, None))
    out = []
    with camera_from_uri(f"replay:{session_dir}", realtime=False) as cam:
        while True:
            try:
                frame = cam.read()
            except EndOfStream:
                return out
            out.append((frame.t, pipe.process(frame.image, frame.t).clusters))


def mae(m: dict) -> float:
    return float(np.mean(np.abs(m["pred"] - m["ref"]))) if len(m["ref"]) else float("nan")


def corrected_frames(frames: list, cal, corr=None) -> list:
    """The runtime's correction stage (runtime.correction.ForceCorrection of `cal`, features exactly as
    SensorPipeline computes them) applied to recorded raw-model clusters; frames are copied."""
    from dataclasses import replace as dc_replace

    from runtime.correction import ForceCorrection
    from runtime.geometry import sample_bilinear

    corr = corr if corr is not None else ForceCorrection.from_calibration(cal)
    h, w = cal.model_size
    out = []
    for t, clusters in frames:
        if clusters and corr.enabled:
            forces = np.array([c.force_n for c in clusters])
            uv = np.array([c.centroid_px for c in clusters]) / np.array([w, h])
            tp = np.array([[sample_bilinear(cal.theta, u - 0.5, v - 0.5), sample_bilinear(cal.phi, u - 0.5, v - 0.5)]
                           for u, v in (c.centroid_px for c in clusters)])
            f = corr(forces, uv, tp)
            clusters = [dc_replace(c, force_n=tuple(map(float, fi)), force_mag_n=float(np.linalg.norm(fi)))
                        for c, fi in zip(clusters, f)]
        out.append((t, clusters))
    return out


def held_out_pokes(frames: list, reference, rules, by: str = "gauge") -> dict:
    """The reference's pokes with the sensor's force in them (tools.recalib.evaluate.gauge_pokes), or
    with by="detected" the single-contact pokes the sensor detected (pair_pokes)."""
    from tools.recalib.evaluate import gauge_pokes, pair_pokes

    return gauge_pokes(frames, reference, rules) if by == "gauge" else pair_pokes(frames, reference, rules)
