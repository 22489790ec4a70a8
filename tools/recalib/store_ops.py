"""Storing a recalibration as a new calibration-store version (thin shell over CalibrationStore).

The store writes atomically (temp folder → fsync → rename → CURRENT replaced last), so a crash or a
full disk leaves the active version intact; this module turns the low-level OSError into a message
that says so, and verifies the new version (hashes, ONNX loads in onnxruntime) before leaving it
active — if that check fails, CURRENT goes back to the previous version.
"""
from __future__ import annotations

import errno
import logging
import time

import numpy as np

from ...contracts.errors import CalibrationError, TensorTouchError
from ...contracts.store import TABLES, Calibration, CalibrationStore
from ...runtime.stages.correction import ForceCorrection
from ...runtime.stages.geometry import DomeProfile, surface_tables

log = logging.getLogger(__name__)


def dome_profile(meta: dict) -> DomeProfile:
    """The gel profile named in calibration.json "gel" (sphere radius and centre height, mm)."""
    gel = meta.get("gel") or {}
    if "radius_mm" not in gel:
        raise CalibrationError("calibration.json: gel.radius_mm missing; cannot rebuild surface tables")
    return DomeProfile(radius_mm=float(gel["radius_mm"]), center_z_mm=float(gel.get("center_z_mm", 0.0)))


def _explain(exc: OSError, store: CalibrationStore, sensor_id: str, active: str) -> CalibrationError:
    what = "the disk is full" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
    return CalibrationError(f"could not store the new calibration of {sensor_id} in {store.root / sensor_id}: "
                            f"{what} ({type(exc).__name__} errno {exc.errno}); nothing was changed, the active "
                            f"calibration is still {active}")


def store_recalibration(store: CalibrationStore, cal: Calibration, provenance: dict,
                        correction: tuple[dict, bytes] | None = None,
                        geometry: dict | None = None, crop: dict | None = None) -> str:
    """Write a new version of `cal.sensor_id` with a new correction (spec, onnx bytes), a new crop
    (`crop`: {"gel_center_px", "gel_radius_px"} from tools.recalib.rim.crop_changes; tables kept) and/or
    new geometry ({"gel_center_px", "theta", "phi"}); everything else is kept from `cal`. Returns the
    new version name; the previous version stays on disk for `tensortouch calib rollback`. Refused
    (CalibrationError, nothing stored) when the active version is no longer `cal.version`."""
    with store.locked(cal.sensor_id):   # the store, verify and any re-activation: no writer in between
        return _store_locked(store, cal, provenance, correction, geometry, crop)


def _store_locked(store: CalibrationStore, cal: Calibration, provenance: dict, correction, geometry, crop) -> str:
    sid, active = cal.sensor_id, store.current(cal.sensor_id)
    if active != cal.version:
        raise CalibrationError(f"sensor {sid}: the active calibration is {active}, not {cal.version} this "
                               f"recalibration started from (another writer came first); nothing was stored")
    prov = {"method": "recalibrate-pokes", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "base_version": cal.version, **provenance}
    try:
        if geometry is None:
            files = {correction[0]["file"]: correction[1]} if correction else None
            changes = {**(crop or {}), **({"correction": correction[0]} if correction else {})}
            version = store.derive(sid, changes, files=files, provenance=prov, base_version=active)
        else:
            meta = {k: v for k, v in cal.meta.items() if k not in ("files", "tables", "version", "created")}
            meta.update(crop or {})
            meta["gel_center_px"] = [float(v) for v in geometry["gel_center_px"]]
            meta["provenance"] = prov
            tables = surface_tables(geometry["theta"], geometry["phi"], dome_profile(cal.meta))
            files = {}
            if correction:
                meta["correction"] = correction[0]
                files[correction[0]["file"]] = correction[1]
            elif cal.meta.get("correction"):
                files[cal.meta["correction"]["file"]] = cal.correction_path
            version = store.write(sid, {k: tables[k] for k in TABLES}, meta, files=files, base_version=active)
    except OSError as exc:
        raise _explain(exc, store, sid, active) from None
    except CalibrationError as exc:  # the store wraps I/O errors; explain them the same way
        if isinstance(exc.__cause__, OSError):
            raise _explain(exc.__cause__, store, sid, active) from None
        raise
    try:  # verify what was written before leaving it active
        new = store.load(sid, version)
        ForceCorrection.from_calibration(new)
    except TensorTouchError as exc:
        store.rollback(sid, active)
        raise CalibrationError(f"new calibration {sid}/{version} failed verification ({exc}); "
                               f"{active} re-activated") from None
    log.info("%s: recalibration stored as %s (was %s)", sid, version, active)
    return version


def active_magnitudes(cal: Calibration, pred_force: np.ndarray, uv: np.ndarray, theta_phi: np.ndarray) -> np.ndarray:
    """|F| the active calibration's correction gives for the raw model forces (identity if none)."""
    corr = ForceCorrection.from_calibration(cal)
    return np.linalg.norm(corr(pred_force, uv, theta_phi), axis=1)
