"""`compare`: the model as deployed (raw prediction -> enabled effects -> correction) against the
measurements.

Shell around pure pieces: the sample table of a session (samples.py, cached), the model's raw
prediction -- the deployed network over the session's frames (network.py: raw clusters cached by
frames/model/geometry, effects and correction replayed with the runtime's own code) or the nominal
contact law (models.py, cached by fingerprint) -- the sensor's effect chain and correction, errors.
Re-comparing after `effects add` only re-applies the cheap effect chain and correction.
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ...contracts import paths
from ...contracts.errors import TensorTouchError
from ...contracts.files import atomic_write
from ...contracts.session import Session, load_session
from ...contracts.store import CalibrationStore
from ...runtime.stages.effects import EffectChain, Registry
from .fit import deployed_prediction
from .samples import SampleConfig, build_table
from .table import SampleTable

log = logging.getLogger(__name__)


@dataclass
class CompareConfig:
    samples: SampleConfig = field(default_factory=SampleConfig)
    brightness: bool = True
    contact_depth: float = 0.0     # mm; rows deeper than this count as "in contact"


TABLE_VERSION = 2      # part of the sample-table cache key: bump when samples.build_table changes


def cache_root() -> Path:
    return paths.cache_dir() / "workbench"


def session_key(session_path: Path, cal, cfg: CompareConfig) -> str:
    h = hashlib.sha256()
    h.update((Path(session_path) / "session.json").read_bytes())
    for name in ("wrench.csv", "poses.csv", "temperature.csv", "frames.csv"):
        p = Path(session_path) / name
        if p.is_file():
            st = p.stat()
            h.update(f"{name}:{st.st_size}:{st.st_mtime_ns}".encode())
    # only what the table depends on: gel geometry and image circle (not the version, so adding
    # an effect -- a new calibration version -- reuses the table and the raw predictions)
    geometry = {k: cal.meta.get(k) for k in ("gel", "gel_center_px", "gel_radius_px")}
    h.update(json.dumps({"sensor": cal.sensor_id, "geometry": geometry, "cfg": asdict(cfg), "table": TABLE_VERSION},
                        sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def load_table(session_path, cal, cfg: CompareConfig | None = None, cache: bool = True,
               session: Session | None = None) -> tuple[SampleTable, Path]:
    """The session's sample table (measurements + covariates), cached under cache/workbench/.
    `session`: the session already loaded (or changed in memory: then pass cache=False)."""
    cfg = cfg or CompareConfig()
    session_path = Path(session_path)
    folder = cache_root() / session_key(session_path, cal, cfg)
    path = folder / "table.npz"
    if cache and path.is_file():
        return SampleTable.load(path), folder
    session = session or load_session(session_path)
    t0 = time.perf_counter()
    table = build_table(session, cal, cfg.samples, brightness=cfg.brightness)
    log.info("sample table of %s: %d rows in %.1f s", session_path, len(table), time.perf_counter() - t0)
    if cache:
        folder.mkdir(parents=True, exist_ok=True)
        table.save(path)
    return table, folder


def predict_cached(table: SampleTable, model, folder: Path | None) -> np.ndarray:
    """Raw model prediction (N,3), cached per model fingerprint beside the table."""
    path = folder / f"pred-{model.name}-{model.fingerprint()}.npy" if folder else None
    if path is not None and path.is_file():
        pred = np.load(path, allow_pickle=False)
        if pred.shape == table.meas.shape:
            return pred
    pred = np.asarray(model.predict(table), dtype=np.float64)
    if path is not None:
        atomic_write(path, lambda fh: np.save(fh, pred, allow_pickle=False))
    return pred


def errors(meas: np.ndarray, pred: np.ndarray) -> dict:
    """Per-axis and magnitude errors (N)."""
    r = meas - pred
    if len(r) == 0:
        return {"n": 0}
    out = {"n": int(len(r))}
    for j, ax in enumerate("xyz"):
        out[f"mae_{ax}"] = float(np.mean(np.abs(r[:, j])))
        out[f"rms_{ax}"] = float(np.sqrt(np.mean(r[:, j] ** 2)))
    out["rms_vector"] = float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
    out["mae_magnitude"] = float(np.mean(np.abs(np.linalg.norm(meas, axis=1) - np.linalg.norm(pred, axis=1))))
    return out


@dataclass
class Comparison:
    table: SampleTable
    pred: np.ndarray               # deployed prediction (raw + enabled effects), (N,3)
    chain: EffectChain
    summary: dict
    folder: Path | None = None     # cache folder of the session
    post: object = None            # the sensor's correction on table rows (None = none)


def position_errors(table: SampleTable) -> dict | None:
    """Cluster centroid - mocap tip (mm) over matched contact rows; None without positions."""
    pos = table.vec.get("position_residual")
    if pos is None:
        return None
    ok = np.all(np.isfinite(pos), axis=1) & (table.cols.get("mocap_depth", table.cols["depth"]) > 0)
    if not ok.any():
        return {"n": 0}
    out = {"n": int(ok.sum())}
    for j, ax in enumerate("xyz"):
        out[f"mae_{ax}"] = float(np.mean(np.abs(pos[ok, j])))
        out[f"bias_{ax}"] = float(np.mean(pos[ok, j]))
        out[f"rms_{ax}"] = float(np.sqrt(np.mean(pos[ok, j] ** 2)))
    out["rms_distance"] = float(np.sqrt(np.mean(np.sum(pos[ok] ** 2, axis=1))))
    return out


def compare_table(table: SampleTable, chain: EffectChain, cfg: CompareConfig | None = None,
                  post=None, deployed: np.ndarray | None = None) -> Comparison:
    """Pure core: the deployed prediction (raw model -> enabled effects -> correction; or `deployed`,
    the runtime's own numbers, + measurement-stage effects) against the measurements."""
    cfg = cfg or CompareConfig()
    cov = table.cov()
    if deployed is not None:
        pred = chain.apply(deployed, cov, stages=("measurement",))
    else:
        pred = deployed_prediction(table.model, cov, chain, post)
    depth = table.cols.get("mocap_depth", table.cols["depth"])
    contact = depth > cfg.contact_depth
    summary = {"n_samples": int(len(table)), "contact_samples": int(contact.sum()),
               "duration_s": float(np.ptp(table.cols["time"])) if len(table) else 0.0,
               "effects": chain.to_list(),
               "force_error": errors(table.meas, pred),
               "force_error_contact": errors(table.meas[contact], pred[contact]),
               "position_error": position_errors(table)}
    if summary["position_error"] is None:
        summary["position_note"] = ("the contact-law model takes the contact position from mocap; position "
                                    "errors need the network path")
    if "matched" in table.cols:
        summary["detected_fraction"] = float(np.mean(table.cols["matched"][contact] > 0)) if contact.any() else 0.0
    if "brightness" in cov:
        ok = np.isfinite(cov["brightness"])
        g = chain.image_gain(cov, len(table))
        if ok.any():
            summary["brightness_error"] = {"n": int(ok.sum()), "rms": float(np.sqrt(np.mean((cov["brightness"][ok] - g[ok]) ** 2)))}
    comp = Comparison(table, pred, chain, summary)
    comp.post = post
    if deployed is not None:   # the batch form diagnosis fits vs the runtime's frame-by-frame replay
        batch = deployed_prediction(table.model, cov, chain, post)
        summary["batch_vs_runtime_max_n"] = float(np.max(np.abs(batch - pred))) if len(pred) else 0.0
    return comp


def run_compare(session_path, sensor: str | None, store: CalibrationStore, model, registry: Registry,
                cfg: CompareConfig | None = None, cache: bool = True, progress=None,
                session: Session | None = None) -> Comparison:
    """Shell: load session/calibration, cached table and prediction, enabled effects, errors.
    `session`: a session changed in memory (its streams, not `session_path`'s files, are compared;
    nothing is cached)."""
    cfg = cfg or CompareConfig()
    if session is not None:
        session_path, cache = session.path, False
    t0 = time.perf_counter()
    session_path = Path(session_path)
    if not (session_path / "session.json").is_file():
        raise TensorTouchError(f"{session_path}: not a session (no session.json)")
    sensor = sensor or json.loads((session_path / "session.json").read_text())["sensor_id"]
    cal = store.load(sensor)
    table, folder = load_table(session_path, cal, cfg, cache, session)
    t1 = time.perf_counter()
    try:
        chain = EffectChain.from_calibration(cal, registry)
    except ValueError as exc:
        raise TensorTouchError(f"{cal.folder / 'calibration.json'}: {exc}") from None
    extra = {}
    if hasattr(model, "build_table"):   # the deployed network: frames through the runtime's code
        from .fastpost import correction_post

        session = session or load_session(session_path)
        table = model.build_table(session, cal, table, folder if cache else None,
                                  cache_root() / "net" if cache else None, progress)
        t2 = time.perf_counter()
        deployed, info = model.deployed(session, table, cal)
        comp = compare_table(table, chain, cfg, post=correction_post(table, cal), deployed=deployed)
        extra = {"network_pass": dict(model.info), "runtime_flags": info["flags"],
                 "runtime_stale_at": info.get("stale_at"),
                 "correction": cal.meta.get("correction")}
    else:
        raw = predict_cached(table, model, folder if cache else None)
        t2 = time.perf_counter()
        table = table.with_model(raw)
        comp = compare_table(table, chain, cfg)
    comp.folder = folder
    comp.summary.update({"session": str(session_path), "sensor_id": sensor,
                         "calibration_version": cal.version,
                         "model": {"name": model.name, "fingerprint": model.fingerprint(),
                                   "source": getattr(model, "source", "")}, **extra,
                         "seconds": {"table": t1 - t0, "model": t2 - t1, "total": time.perf_counter() - t0}})
    return comp
