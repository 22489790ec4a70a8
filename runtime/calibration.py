"""Calibration store: one folder per sensor, versioned, atomic, hash-verified (docs/calibration_store.md).

Writes go to a temporary folder beside `versions/`, are fsynced and hashed, then renamed into place;
the `CURRENT` pointer is replaced last with an atomic rename. A crash or a full disk at any point
leaves the previous version active and intact. Arrays load with `allow_pickle=False`.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime import paths
from runtime.errors import CalibrationError

log = logging.getLogger(__name__)

SCHEMA = "tensortouch.calibration"
SCHEMA_VERSION = 1
TABLES = ("theta", "phi", "surface_xyz", "normals", "pixel_area", "mask")
_VERSION_RE = re.compile(r"^v(\d{4,})$")


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass
class Calibration:
    """One loaded calibration version of one sensor."""

    sensor_id: str
    version: str
    folder: Path
    meta: dict
    theta: np.ndarray
    phi: np.ndarray
    surface_xyz: np.ndarray
    normals: np.ndarray
    pixel_area: np.ndarray
    mask: np.ndarray
    extra: dict = field(default_factory=dict)

    @property
    def gel_center_px(self) -> tuple[float, float]:
        cx, cy = self.meta["gel_center_px"]
        return float(cx), float(cy)

    @property
    def gel_radius_px(self) -> float:
        return float(self.meta["gel_radius_px"])

    @property
    def model_size(self) -> tuple[int, int]:
        h, w = self.meta["model_size"]
        return int(h), int(w)

    @property
    def effects(self) -> list[dict]:
        return list(self.meta.get("effects") or [])

    @property
    def correction_path(self) -> Path | None:
        corr = self.meta.get("correction")
        return self.folder / corr["file"] if corr else None


def _check_meta(meta: dict, where: str) -> None:
    if meta.get("schema") != SCHEMA:
        raise CalibrationError(f"{where}: schema is {meta.get('schema')!r}, expected {SCHEMA!r}")
    if meta.get("schema_version", 0) > SCHEMA_VERSION:
        raise CalibrationError(f"{where}: schema_version {meta.get('schema_version')} is newer than this runtime reads")
    for key in ("sensor_id", "gel_center_px", "gel_radius_px", "model_size", "tables", "files"):
        if key not in meta:
            raise CalibrationError(f"{where}: field '{key}' missing")
    if len(meta["gel_center_px"]) != 2 or float(meta["gel_radius_px"]) <= 0:
        raise CalibrationError(f"{where}: gel_center_px must be [cx, cy] and gel_radius_px > 0")


class CalibrationStore:
    """The folder holding every sensor's calibration versions."""

    def __init__(self, root: str | Path | None = None):
        self.root = Path(root) if root is not None else paths.calibration_dir()

    # ----- reading -------------------------------------------------------------------------
    def sensors(self) -> list[str]:
        if not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir() if (p / "CURRENT").is_file())

    def versions(self, sensor_id: str) -> list[str]:
        folder = self.root / sensor_id / "versions"
        if not folder.is_dir():
            return []
        return sorted(p.name for p in folder.iterdir() if _VERSION_RE.match(p.name))

    def current(self, sensor_id: str) -> str:
        pointer = self.root / sensor_id / "CURRENT"
        if not pointer.is_file():
            known = ", ".join(self.sensors()) or "none"
            raise CalibrationError(f"{pointer}: no calibration for sensor '{sensor_id}' "
                                   f"(store {self.root} has: {known}); a new sensor's first one: "
                                   f"tensortouch calib init --source ... --sensor {sensor_id} (docs/bringup.md)")
        return pointer.read_text().strip()

    def load(self, sensor_id: str, version: str | None = None, verify: bool = True) -> Calibration:
        version = version or self.current(sensor_id)
        folder = self.root / sensor_id / "versions" / version
        meta_path = folder / "calibration.json"
        if not meta_path.is_file():
            raise CalibrationError(f"{meta_path}: missing (version {version} of sensor {sensor_id})")
        try:
            meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError as exc:
            raise CalibrationError(f"{meta_path}: not valid JSON ({exc})") from None
        _check_meta(meta, str(meta_path))
        if meta["sensor_id"] != sensor_id:
            raise CalibrationError(f"{meta_path}: sensor_id {meta['sensor_id']!r} does not match folder {sensor_id!r}")
        if verify:
            for name, digest in meta["files"].items():
                path = folder / name
                if not path.is_file():
                    raise CalibrationError(f"{path}: listed in calibration.json but missing")
                if sha256_file(path) != digest:
                    raise CalibrationError(f"{path}: SHA-256 mismatch (file corrupt or replaced)")
        arrays = {}
        for key in TABLES:
            fname = meta["tables"].get(key)
            if fname is None:
                raise CalibrationError(f"{meta_path}: tables.{key} missing")
            try:
                arrays[key] = np.load(folder / fname, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise CalibrationError(f"{folder / fname}: cannot load table '{key}' ({exc})") from None
        h, w = (int(v) for v in meta["model_size"])
        expect = {"theta": (h, w), "phi": (h, w), "surface_xyz": (h, w, 3), "normals": (h, w, 3),
                  "pixel_area": (h, w), "mask": (h, w)}
        for key, shape in expect.items():
            if arrays[key].shape != shape:
                raise CalibrationError(f"{folder / meta['tables'][key]}: shape {arrays[key].shape}, "
                                       f"expected {shape} (model_size {h}x{w})")
        return Calibration(sensor_id=sensor_id, version=version, folder=folder, meta=meta,
                           theta=arrays["theta"].astype(np.float32), phi=arrays["phi"].astype(np.float32),
                           surface_xyz=arrays["surface_xyz"].astype(np.float32),
                           normals=arrays["normals"].astype(np.float32),
                           pixel_area=arrays["pixel_area"].astype(np.float32),
                           mask=arrays["mask"].astype(bool))

    def history(self, sensor_id: str) -> list[dict]:
        """Version, created, provenance of every stored version (oldest first)."""
        rows = []
        active = self.current(sensor_id)
        for v in self.versions(sensor_id):
            try:
                meta = json.loads((self.root / sensor_id / "versions" / v / "calibration.json").read_text())
            except (OSError, json.JSONDecodeError):
                meta = {}
            rows.append({"version": v, "active": v == active, "created": meta.get("created"),
                         "provenance": meta.get("provenance", {})})
        return rows

    # ----- writing -------------------------------------------------------------------------
    def write(self, sensor_id: str, tables: dict[str, np.ndarray], meta: dict,
              files: dict[str, bytes | Path] | None = None, activate: bool = True) -> str:
        """Store a new version atomically and (by default) make it current. Returns its name.

        `tables` maps every name of TABLES to an array; `meta` holds at least gel_center_px,
        gel_radius_px and model_size (schema, sensor_id, version, tables, files are filled in);
        `files` adds extra files (e.g. correction.onnx) as bytes or paths to copy.
        """
        if not re.match(r"^[A-Za-z0-9._-]+$", sensor_id):
            raise CalibrationError(f"sensor id {sensor_id!r}: use letters, digits, '.', '_' or '-'")
        missing = [k for k in TABLES if k not in tables]
        if missing:
            raise CalibrationError(f"calibration for {sensor_id}: tables {missing} missing")
        sensor_dir = self.root / sensor_id
        versions_dir = sensor_dir / "versions"
        versions_dir.mkdir(parents=True, exist_ok=True)
        existing = [int(_VERSION_RE.match(v).group(1)) for v in self.versions(sensor_id)]
        version = f"v{(max(existing) + 1) if existing else 1:04d}"
        tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{version}-", dir=versions_dir))
        try:
            names = {}
            for key in TABLES:
                arr = np.asarray(tables[key])
                arr = arr.astype(bool) if key == "mask" else arr.astype(np.float32)
                names[key] = f"{key}.npy"
                with open(tmp / names[key], "wb") as fh:
                    np.save(fh, arr, allow_pickle=False)
                    fh.flush()
                    os.fsync(fh.fileno())
            for name, content in (files or {}).items():
                if isinstance(content, (bytes, bytearray)):
                    (tmp / name).write_bytes(content)
                else:
                    shutil.copyfile(content, tmp / name)
            full = dict(meta)
            full.update({"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "sensor_id": sensor_id,
                         "version": version, "tables": names,
                         "created": full.get("created") or time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
            full.setdefault("effects", [])
            full.setdefault("correction", None)
            full.setdefault("provenance", {})
            full["files"] = {p.name: sha256_file(p) for p in sorted(tmp.iterdir())}
            _check_meta(full, f"new calibration for {sensor_id}")
            with open(tmp / "calibration.json", "w") as fh:
                json.dump(full, fh, indent=2, sort_keys=True)
                fh.flush()
                os.fsync(fh.fileno())
            os.rename(tmp, versions_dir / version)
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            raise CalibrationError(f"{versions_dir / version}: could not write the new calibration "
                                   f"({exc.strerror or exc}); nothing was stored, the active version is "
                                   f"unchanged") from exc
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        if activate:
            self._set_current(sensor_id, version)
        log.info("calibration %s/%s written%s", sensor_id, version, " and activated" if activate else "")
        return version

    def derive(self, sensor_id: str, changes: dict, files: dict[str, bytes | Path] | None = None,
               provenance: dict | None = None) -> str:
        """New version = current version with `changes` merged into its metadata (tables kept)."""
        cal = self.load(sensor_id)
        meta = {k: v for k, v in cal.meta.items() if k not in ("files", "tables", "version", "created")}
        meta.update(changes)
        if provenance is not None:
            meta["provenance"] = provenance
        keep = {}
        corr = meta.get("correction")
        if corr and corr.get("file") and not (files and corr["file"] in files):
            keep[corr["file"]] = cal.folder / corr["file"]
        keep.update(files or {})
        tables = {k: getattr(cal, k) for k in TABLES}
        return self.write(sensor_id, tables, meta, files=keep)

    def rollback(self, sensor_id: str, version: str | None = None) -> str:
        """Make `version` (default: the one before the active one) current again."""
        versions = self.versions(sensor_id)
        active = self.current(sensor_id)
        if version is None:
            older = [v for v in versions if v < active]
            if not older:
                raise CalibrationError(f"sensor {sensor_id}: no version older than {active} to roll back to")
            version = older[-1]
        if version not in versions:
            raise CalibrationError(f"sensor {sensor_id}: no version {version} (have {', '.join(versions)})")
        self.load(sensor_id, version)  # verifies before activating
        self._set_current(sensor_id, version)
        return version

    def _set_current(self, sensor_id: str, version: str) -> None:
        pointer = self.root / sensor_id / "CURRENT"
        tmp = pointer.with_name(f".CURRENT.{os.getpid()}.tmp")
        with open(tmp, "w") as fh:
            fh.write(version + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, pointer)
