"""Calibration store: one folder per sensor, versioned, atomic, hash-verified (docs/calibration_store.md).

Writers of one sensor queue on a lock file (flock). Every operation that derives a version from the
current one (derive, rollback, a caller's read-modify-write inside `locked()`) reads the current
version under that lock, so two processes never lose each other's change. A new version goes to a
temporary folder inside `versions/`; every file is fsynced and hashed, the folder fsynced, renamed into place and `versions/`
fsynced; the `CURRENT` pointer is replaced last with an atomic rename and the sensor folder fsynced.
A crash or a full disk at any point leaves the previous version active and intact. Loads check
calibration.json by type and by plausibility (contracts/calibration_schema.py), confine every path
to the version folder, verify hashes and check that every table is finite and in range. Arrays load
with `allow_pickle=False`.
"""
from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import math
import os
import re
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from . import paths
from .calibration_schema import check_calibration
from .errors import CalibrationError
from .files import atomic_write
from .names import confined, is_name

log = logging.getLogger(__name__)

SCHEMA = "tensortouch.calibration"
SCHEMA_VERSION = 1
TABLES = ("theta", "phi", "surface_xyz", "normals", "pixel_area", "mask")
_VERSION_RE = re.compile(r"^v(\d{4,})$")
_FILE_RE = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9._-]*$")
_SHA_RE = re.compile(r"^[0-9a-f]{64}$")
_STALE_TMP_RE = re.compile(r"^\.tmp-v\d{4,}-")
LOCK_NAME = ".lock"
ANY = object()     # write(base_version=ANY): store on top of whatever version is active


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


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def check_file_name(name, where: str) -> str:
    """A file named in calibration.json must be a plain name inside its version folder."""
    if not isinstance(name, str) or not _FILE_RE.match(name):
        raise CalibrationError(f"{where}: file name {name!r} must be a plain file name "
                               f"(letters, digits, '.', '_', '-'; no folders)")
    return name


def _check_meta(meta, where: str) -> None:
    """Type checks of calibration.json; every table and the correction file must be hashed in "files"."""
    if not isinstance(meta, dict):
        raise CalibrationError(f"{where}: expected a JSON object, got {type(meta).__name__}")
    if meta.get("schema") != SCHEMA:
        raise CalibrationError(f"{where}: schema is {meta.get('schema')!r}, expected {SCHEMA!r}")
    sv = meta.get("schema_version", 0)
    if not isinstance(sv, int) or isinstance(sv, bool):
        raise CalibrationError(f"{where}: schema_version must be an integer, got {sv!r}")
    if sv > SCHEMA_VERSION:
        raise CalibrationError(f"{where}: schema_version {sv} is newer than this runtime reads")
    for key in ("sensor_id", "gel_center_px", "gel_radius_px", "model_size", "tables", "files"):
        if key not in meta:
            raise CalibrationError(f"{where}: field '{key}' missing")
    if not isinstance(meta["sensor_id"], str):
        raise CalibrationError(f"{where}: sensor_id must be a string")
    c = meta["gel_center_px"]
    if not (isinstance(c, list) and len(c) == 2 and all(_is_num(v) for v in c)):
        raise CalibrationError(f"{where}: gel_center_px must be [cx, cy] (two finite numbers), got {c!r}")
    r = meta["gel_radius_px"]
    if not (_is_num(r) and r > 0):
        raise CalibrationError(f"{where}: gel_radius_px must be a finite number > 0, got {r!r}")
    ms = meta["model_size"]
    if not (isinstance(ms, list) and len(ms) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 4096 for v in ms)):
        raise CalibrationError(f"{where}: model_size must be [H, W] (two integers 1..4096), got {ms!r}")
    tables, files = meta["tables"], meta["files"]
    if not isinstance(tables, dict):
        raise CalibrationError(f"{where}: tables must be an object {{name: file}}")
    if not isinstance(files, dict) or not files:
        raise CalibrationError(f"{where}: files must be a non-empty object {{file: sha256}}")
    for name, digest in files.items():
        check_file_name(name, f"{where}: files")
        if not (isinstance(digest, str) and _SHA_RE.match(digest)):
            raise CalibrationError(f"{where}: files.{name} must be a 64-hex-digit SHA-256, got {digest!r}")
    for key in TABLES:
        if key not in tables:
            raise CalibrationError(f"{where}: tables.{key} missing")
    for key, name in tables.items():
        check_file_name(name, f"{where}: tables.{key}")
        if name not in files:
            raise CalibrationError(f"{where}: tables.{key} = {name!r} is not hashed in files")
    corr = meta.get("correction")
    if corr is not None:
        if not isinstance(corr, dict) or not isinstance(corr.get("file"), str):
            raise CalibrationError(f"{where}: correction must be null or an object with a \"file\"")
        check_file_name(corr["file"], f"{where}: correction.file")
        if corr["file"] not in files:
            raise CalibrationError(f"{where}: correction.file {corr['file']!r} is not hashed in files")
    if not isinstance(meta.get("effects") if meta.get("effects") is not None else [], list):
        raise CalibrationError(f"{where}: effects must be a list")
    if not isinstance(meta.get("provenance") if meta.get("provenance") is not None else {}, dict):
        raise CalibrationError(f"{where}: provenance must be an object")
    check_calibration(meta, where)      # plausibility: rim inside the image, gel lengths, ... (calibration_schema.py)


# Physical range of each table: θ is a polar angle, φ an azimuth, mm and mm² bounded by any plausible
# gel; normals are unit vectors (or zero off the gel). θ and φ are checked on gel pixels only (off the
# gel they mean nothing and may be NaN); the other tables everywhere.
TABLE_RANGES = {"theta": (0.0, math.pi), "phi": (-2 * math.pi, 2 * math.pi), "surface_xyz": (-1000.0, 1000.0),
                "normals": (-1.001, 1.001), "pixel_area": (0.0, 1000.0)}
ON_GEL_ONLY = ("theta", "phi")


def check_tables(arrays: dict[str, np.ndarray], where: str) -> None:
    """Every table finite and in TABLE_RANGES, normals of length <= 1, at least one gel pixel."""
    mask = arrays["mask"]
    if mask.dtype != bool and not (np.issubdtype(mask.dtype, np.integer) and np.isin(mask, (0, 1)).all()):
        raise CalibrationError(f"{where}: table mask has dtype {mask.dtype}, expected bool")
    mask = mask.astype(bool)
    if not mask.any():
        raise CalibrationError(f"{where}: table mask has no gel pixel")
    for key, (lo, hi) in TABLE_RANGES.items():
        a = arrays[key]
        if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
            raise CalibrationError(f"{where}: table {key} has dtype {a.dtype}, expected float32")
        if key in ON_GEL_ONLY and a.shape == mask.shape:
            a = a[mask]
        bad = ~np.isfinite(a)
        if bad.any():
            on = " on the gel" if key in ON_GEL_ONLY else ""
            raise CalibrationError(f"{where}: table {key} has {int(bad.sum())} non-finite value(s) (inf/NaN){on}")
        if a.size and (a.min() < lo or a.max() > hi):
            raise CalibrationError(f"{where}: table {key} spans [{float(a.min()):.6g}, {float(a.max()):.6g}], "
                                   f"expected within [{lo:.6g}, {hi:.6g}]")
    normals = arrays["normals"]
    if normals.size and np.linalg.norm(normals, axis=-1).max() > 1.001:
        raise CalibrationError(f"{where}: table normals has vectors longer than 1")


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


_held = threading.local()     # the sensor folders this thread holds the lock of (re-entry is free)


@contextlib.contextmanager
def _locked(sensor_dir: Path):
    """Exclusive lock of one sensor's folder (flock on LOCK_NAME): writers queue, one at a time.
    Re-entrant within a thread, so a read-modify-write can hold it around write/derive/rollback."""
    key = os.path.realpath(sensor_dir)
    held = _held.__dict__.setdefault("dirs", set())
    if key in held:
        yield
        return
    sensor_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(sensor_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        held.add(key)
        try:
            yield
        finally:
            held.discard(key)
    finally:
        os.close(fd)   # closing releases the lock


class CalibrationStore:
    """The folder holding every sensor's calibration versions.

    `root` is where versions are written (default contracts.paths.calibration_dir()). `shipped` is an
    optional read-only store underneath it (default: the calibrations inside an installed package,
    contracts.paths.shipped_calibration_dir()): a sensor or version missing from `root` is read from
    there, and a new version of a shipped sensor is written to `root`, numbered after the shipped ones."""

    def __init__(self, root: str | Path | None = None, shipped: str | Path | None = None):
        self.root = Path(root) if root is not None else paths.calibration_dir()
        if shipped is None and root is None:
            shipped = paths.shipped_calibration_dir()
        self.shipped = Path(shipped) if shipped is not None and Path(shipped).resolve() != self.root.resolve() else None

    def _sensor_dir(self, sensor_id: str) -> Path:
        """The sensor's folder in the writable store (where its lock, CURRENT and new versions go)."""
        return confined(self.root, sensor_id, "sensor id", CalibrationError)

    def _bases(self, sensor_id: str) -> list[Path]:
        """The sensor's folders to read from: the writable store's first, then the shipped one's."""
        bases = [self._sensor_dir(sensor_id)]
        if self.shipped is not None:
            bases.append(confined(self.shipped, sensor_id, "sensor id", CalibrationError))
        return bases

    # ----- reading -------------------------------------------------------------------------
    def sensors(self) -> list[str]:
        found = set()
        for root in (self.root, self.shipped):
            if root is not None and root.is_dir():
                found.update(p.name for p in root.iterdir() if (p / "CURRENT").is_file() and is_name(p.name))
        return sorted(found)

    def versions(self, sensor_id: str) -> list[str]:
        found = set()
        for base in self._bases(sensor_id):
            if (base / "versions").is_dir():
                found.update(p.name for p in (base / "versions").iterdir() if _VERSION_RE.match(p.name))
        return sorted(found)

    def current(self, sensor_id: str) -> str:
        pointer = next((b / "CURRENT" for b in self._bases(sensor_id) if (b / "CURRENT").is_file()),
                       self._sensor_dir(sensor_id) / "CURRENT")
        if not pointer.is_file():
            known = ", ".join(self.sensors()) or "none"
            raise CalibrationError(f"{pointer}: no calibration for sensor '{sensor_id}' "
                                   f"(store {self.root} has: {known}); a new sensor's first one: "
                                   f"tensortouch calib init --source ... --sensor {sensor_id} (docs/bringup.md)")
        try:
            text = pointer.read_bytes()[:64].decode("ascii").strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise CalibrationError(f"{pointer}: unreadable ({exc})") from None
        if not _VERSION_RE.match(text):
            raise CalibrationError(f"{pointer}: names {text!r}, expected a version name like v0001")
        return text

    def _version_dir(self, sensor_id: str, version: str) -> Path:
        """The folder of `version`, which must be a real folder directly inside versions/ (no symlink out);
        the writable store's if it has it, else the shipped store's."""
        if not isinstance(version, str) or not _VERSION_RE.match(version):
            raise CalibrationError(f"sensor {sensor_id}: version {version!r} is not a version name like v0001")
        for base in self._bases(sensor_id):
            versions_dir = base / "versions"
            folder = versions_dir / version
            if folder.is_symlink() or (folder.exists() and folder.resolve().parent != versions_dir.resolve()):
                raise CalibrationError(f"{folder}: is a link out of the store; refusing it")
            if folder.exists():
                return folder
        return self._sensor_dir(sensor_id) / "versions" / version

    @staticmethod
    def _inside(folder: Path, name: str) -> Path:
        path = folder / name
        if path.is_symlink() or (path.exists() and path.resolve().parent != folder.resolve()):
            raise CalibrationError(f"{path}: is a link out of the store; refusing it")
        return path

    def load(self, sensor_id: str, version: str | None = None, verify: bool = True) -> Calibration:
        version = version or self.current(sensor_id)
        folder = self._version_dir(sensor_id, version)
        meta_path = folder / "calibration.json"
        if not meta_path.is_file():
            raise CalibrationError(f"{meta_path}: missing (version {version} of sensor {sensor_id})")
        try:
            meta = json.loads(self._inside(folder, "calibration.json").read_bytes().decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise CalibrationError(f"{meta_path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
        except (json.JSONDecodeError, RecursionError) as exc:
            raise CalibrationError(f"{meta_path}: not valid JSON ({exc})") from None
        except OSError as exc:
            raise CalibrationError(f"{meta_path}: unreadable ({exc.strerror or exc})") from None
        _check_meta(meta, str(meta_path))
        if meta["sensor_id"] != sensor_id:
            raise CalibrationError(f"{meta_path}: sensor_id {meta['sensor_id']!r} does not match folder {sensor_id!r}")
        if verify:
            for name, digest in meta["files"].items():
                path = self._inside(folder, name)
                if not path.is_file():
                    raise CalibrationError(f"{path}: listed in calibration.json but missing")
                if sha256_file(path) != digest:
                    raise CalibrationError(f"{path}: SHA-256 mismatch (file corrupt or replaced)")
        arrays = {}
        for key in TABLES:
            path = self._inside(folder, meta["tables"][key])
            try:
                arrays[key] = np.load(path, allow_pickle=False)
            except (OSError, ValueError, EOFError) as exc:
                raise CalibrationError(f"{path}: cannot load table '{key}' ({exc})") from None
            if not isinstance(arrays[key], np.ndarray):
                raise CalibrationError(f"{path}: table '{key}' is not a single .npy array")
        h, w = meta["model_size"]
        expect = {"theta": (h, w), "phi": (h, w), "surface_xyz": (h, w, 3), "normals": (h, w, 3),
                  "pixel_area": (h, w), "mask": (h, w)}
        for key, shape in expect.items():
            if arrays[key].shape != shape:
                raise CalibrationError(f"{folder / meta['tables'][key]}: shape {arrays[key].shape}, "
                                       f"expected {shape} (model_size {h}x{w})")
        check_tables(arrays, f"{sensor_id}/{version}")
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
                meta = json.loads((self._version_dir(sensor_id, v) / "calibration.json").read_text())
            except (OSError, ValueError, RecursionError, CalibrationError):
                meta = {}
            meta = meta if isinstance(meta, dict) else {}
            rows.append({"version": v, "active": v == active, "created": meta.get("created"),
                         "provenance": meta.get("provenance", {})})
        return rows

    # ----- writing -------------------------------------------------------------------------
    def locked(self, sensor_id: str):
        """Context manager holding `sensor_id`'s writer lock: read the current version, compute, then
        write/derive/rollback inside it, and no other writer (thread or process) comes in between."""
        return _locked(self._sensor_dir(sensor_id))

    def write(self, sensor_id: str, tables: dict[str, np.ndarray], meta: dict,
              files: dict[str, bytes | Path] | None = None, activate: bool = True,
              base_version=ANY) -> str:
        """Store a new version atomically and (by default) make it current. Returns its name.

        `tables` maps every name of TABLES to an array; `meta` holds at least gel_center_px,
        gel_radius_px and model_size (schema, sensor_id, version, tables, files are filled in);
        `files` adds extra files (e.g. correction.onnx) as bytes or paths to copy.
        Concurrent writers (threads or processes) queue on the sensor's lock file. With `base_version`
        (a version name, or None for "no version yet") the write is refused unless that is still the
        active version once the lock is held: a caller that read version N stores N+1 only on top of N.
        """
        sensor_dir = self._sensor_dir(sensor_id)
        missing = [k for k in TABLES if k not in tables]
        if missing:
            raise CalibrationError(f"calibration for {sensor_id}: tables {missing} missing")
        arrays = {k: (np.asarray(tables[k]).astype(bool) if k == "mask" else np.asarray(tables[k]).astype(np.float32))
                  for k in TABLES}
        check_tables(arrays, f"new calibration for {sensor_id}")
        for name in files or {}:
            check_file_name(name, f"new calibration for {sensor_id}: files")
        versions_dir = sensor_dir / "versions"
        new_dirs = [d for d in (self.root, sensor_dir, versions_dir) if not d.is_dir()]
        try:
            versions_dir.mkdir(parents=True, exist_ok=True)
            for d in new_dirs:          # make the new folders' entries durable in their parents
                _fsync_dir(d.parent)
        except OSError as exc:
            raise CalibrationError(f"{versions_dir}: cannot create ({exc.strerror or exc}); nothing was "
                                   f"stored") from exc
        with _locked(sensor_dir):
            active = self._active_or_none(sensor_id)
            if base_version is not ANY and active != base_version:
                raise CalibrationError(
                    f"sensor {sensor_id}: the active calibration is {active or 'none'}, not "
                    f"{base_version or 'none'} as when this change was computed (another writer came first); "
                    f"nothing was stored, run it again")
            self._clean_stale(sensor_dir)
            existing = [int(_VERSION_RE.match(v).group(1)) for v in self.versions(sensor_id)]
            version = f"v{(max(existing) + 1) if existing else 1:04d}"
            unchanged = (f"nothing was stored, the active version is still {active}" if active
                         else "nothing was stored, the sensor has no active version")
            tmp = versions_dir / f".tmp-{version}-{os.getpid()}"
            try:
                os.mkdir(tmp)      # mode 0o777 & ~umask, like any folder (readable by the runtime's account)
                self._fill(tmp, sensor_id, version, arrays, meta, files)
                _fsync_dir(tmp)
                os.rename(tmp, versions_dir / version)
                _fsync_dir(versions_dir)
            except OSError as exc:
                shutil.rmtree(tmp, ignore_errors=True)
                raise CalibrationError(f"{versions_dir / version}: could not write the new calibration "
                                       f"({exc.strerror or exc}); {unchanged}") from exc
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
            if activate:
                try:
                    self._set_current(sensor_id, version)
                except OSError as exc:
                    now = self._active_or_none(sensor_id)
                    raise CalibrationError(f"{sensor_dir / 'CURRENT'}: {version} was stored but could not be "
                                           f"activated ({exc.strerror or exc}); the active version is "
                                           f"{now or 'none'}") from None
        log.info("calibration %s/%s written%s", sensor_id, version, " and activated" if activate else "")
        return version

    @staticmethod
    def _fill(tmp: Path, sensor_id: str, version: str, arrays: dict, meta: dict, files: dict | None) -> None:
        """Write tables, extra files and calibration.json into `tmp`, each fsynced."""
        names = {}
        for key in TABLES:
            names[key] = f"{key}.npy"
            with open(tmp / names[key], "wb") as fh:
                np.save(fh, arrays[key], allow_pickle=False)
                fh.flush()
                os.fsync(fh.fileno())
        for name, content in (files or {}).items():
            if isinstance(content, (bytes, bytearray)):
                (tmp / name).write_bytes(content)
            else:
                shutil.copyfile(content, tmp / name)
            _fsync_file(tmp / name)
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

    def _active_or_none(self, sensor_id: str) -> str | None:
        try:
            return self.current(sensor_id)
        except CalibrationError:
            return None

    @staticmethod
    def _clean_stale(sensor_dir: Path) -> None:
        """Remove what a killed writer left (temp version folders, temp pointers). Called under the lock,
        when no other writer can be mid-write, so everything matching is stale."""
        versions_dir = sensor_dir / "versions"
        stale = [p for p in versions_dir.iterdir() if _STALE_TMP_RE.match(p.name)] if versions_dir.is_dir() else []
        stale += [p for p in sensor_dir.iterdir() if p.name.startswith(".CURRENT.") and p.name.endswith(".tmp")]
        for p in stale:
            try:
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p)
                else:
                    p.unlink()
                log.info("removed %s left by an interrupted write", p)
            except OSError as exc:
                log.warning("cannot remove %s left by an interrupted write: %s", p, exc)

    def derive(self, sensor_id: str, changes: dict | Callable[[Calibration], dict],
               files: dict[str, bytes | Path] | None = None, provenance: dict | None = None,
               base_version: str | None = None) -> str:
        """New version = current version with `changes` merged into its metadata (tables kept).

        The current version is read under the sensor's lock and the new one written before it is
        released. `changes` may be a function of the current Calibration (e.g. its effects list plus
        one), evaluated under the lock. With `base_version`, refused unless that is the current one."""
        with self.locked(sensor_id):
            cal = self.load(sensor_id)
            if base_version is not None and cal.version != base_version:
                raise CalibrationError(
                    f"sensor {sensor_id}: the active calibration is {cal.version}, not {base_version} as when "
                    f"this change was computed (another writer came first); nothing was stored, run it again")
            if callable(changes):
                changes = changes(cal)
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
            return self.write(sensor_id, tables, meta, files=keep, base_version=cal.version)

    def rollback(self, sensor_id: str, version: str | None = None) -> str:
        """Make `version` (default: the one before the active one) current again."""
        with _locked(self._sensor_dir(sensor_id)):
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
        """Replace CURRENT atomically (temp file fsynced, renamed, sensor folder fsynced). Call under the lock."""
        sensor_dir = self._sensor_dir(sensor_id)
        pointer = sensor_dir / "CURRENT"
        atomic_write(pointer, (version + "\n").encode(), mkdir=False)
