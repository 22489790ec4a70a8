"""`compare`: the model as deployed (raw prediction + enabled effects) against the measurements.

Shell around pure pieces: the sample table of a session (samples.py, cached), the model's raw
prediction (models.py, cached by the model's fingerprint: re-comparing after `effects add` only
re-applies the cheap effect chain), the effect chain of the sensor's calibration, errors.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from runtime import paths
from runtime.calibration import CalibrationStore
from runtime.effects import EffectChain, Registry
from runtime.errors import TensorTouchError
from runtime.session import load_session
from tools.workbench.samples import SampleConfig, build_table
from tools.workbench.table import SampleTable

log = logging.getLogger(__name__)


@dataclass
class CompareConfig:
    samples: SampleConfig = field(default_factory=SampleConfig)
    brightness: bool = True
    contact_depth: float = 0.0     # mm; rows deeper than this count as "in contact"


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
    h.update(json.dumps({"sensor": cal.sensor_id, "geometry": geometry, "cfg": asdict(cfg)},
                        sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def load_table(session_path, cal, cfg: CompareConfig | None = None, cache: bool = True) -> tuple[SampleTable, Path]:
    """The session's sample table (measurements + covariates), cached under cache/workbench/."""
    cfg = cfg or CompareConfig()
    session_path = Path(session_path)
    folder = cache_root() / session_key(session_path, cal, cfg)
    path = folder / "table.npz"
    if cache and path.is_file():
        return SampleTable.load(path), folder
    session = load_session(session_path)
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
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.save(fh, pred, allow_pickle=False)
        tmp.replace(path)
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


def compare_table(table: SampleTable, chain: EffectChain, cfg: CompareConfig | None = None) -> Comparison:
    """Pure core: apply the enabled chain to the raw prediction and measure the errors."""
    cfg = cfg or CompareConfig()
    cov = table.cov()
    pred = chain.apply(table.model, cov, stages=("force", "measurement"))
    contact = table.cols["depth"] > cfg.contact_depth
    summary = {"n_samples": int(len(table)), "contact_samples": int(contact.sum()),
               "duration_s": float(np.ptp(table.cols["time"])) if len(table) else 0.0,
               "effects": chain.to_list(),
               "force_error": errors(table.meas, pred),
               "force_error_contact": errors(table.meas[contact], pred[contact]),
               "position_error": None,
               "position_note": "the nominal model takes the contact position from mocap; position "
                                "errors need the network path"}
    if "brightness" in cov:
        ok = np.isfinite(cov["brightness"])
        g = chain.image_gain(cov, len(table))
        if ok.any():
            summary["brightness_error"] = {"n": int(ok.sum()), "rms": float(np.sqrt(np.mean((cov["brightness"][ok] - g[ok]) ** 2)))}
    return Comparison(table, pred, chain, summary)


def run_compare(session_path, sensor: str | None, store: CalibrationStore, model, registry: Registry,
                cfg: CompareConfig | None = None, cache: bool = True) -> Comparison:
    """Shell: load session/calibration, cached table and prediction, enabled effects, errors."""
    cfg = cfg or CompareConfig()
    t0 = time.perf_counter()
    session_path = Path(session_path)
    if not (session_path / "session.json").is_file():
        raise TensorTouchError(f"{session_path}: not a session (no session.json)")
    sensor = sensor or json.loads((session_path / "session.json").read_text())["sensor_id"]
    cal = store.load(sensor)
    table, folder = load_table(session_path, cal, cfg, cache)
    t1 = time.perf_counter()
    raw = predict_cached(table, model, folder if cache else None)
    t2 = time.perf_counter()
    table = table.with_model(raw)
    try:
        chain = EffectChain.from_calibration(cal, registry)
    except ValueError as exc:
        raise TensorTouchError(f"{cal.folder / 'calibration.json'}: {exc}") from None
    comp = compare_table(table, chain, cfg)
    comp.folder = folder
    comp.summary.update({"session": str(session_path), "sensor_id": sensor,
                         "calibration_version": cal.version,
                         "model": {"name": model.name, "fingerprint": model.fingerprint(),
                                   "source": getattr(model, "source", "")},
                         "seconds": {"table": t1 - t0, "model": t2 - t1, "total": time.perf_counter() - t0}})
    return comp
