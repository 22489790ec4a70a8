"""Model packages (docs/model_package.md): verified loading and onnxruntime inference.

`load_package` checks the manifest, file hashes, channel contract and graph shapes before anything
runs, raising ModelPackageError with the file and field at fault. `FieldModel` wraps one
onnxruntime session: 6-channel input (baseline + current), 15-channel output denormalized with
the package's bounds into physical units.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...contracts import paths
from ...contracts.errors import ModelPackageError
from ...contracts.fields import CHANNELS, N_CHANNELS
from ...contracts.manifest_schema import check_manifest
from ...contracts.store import sha256_file

log = logging.getLogger(__name__)

SCHEMA = "tensortouch.model"
SCHEMA_VERSION = 1
PRECISION_FILES = {"int8": "model.int8.onnx", "fp32": "model.fp32.onnx"}


@dataclass
class ModelPackage:
    folder: Path
    manifest: dict

    @property
    def name(self) -> str:
        return self.manifest.get("name", self.folder.name)

    @property
    def size(self) -> tuple[int, int]:
        h, w = self.manifest["input"]["size"]
        return int(h), int(w)

    def file(self, precision: str) -> Path:
        if precision not in PRECISION_FILES:
            raise ModelPackageError(f"precision {precision!r}: expected one of {sorted(PRECISION_FILES)}")
        return self.folder / PRECISION_FILES[precision]

    def sha256(self, precision: str) -> str:
        return self.manifest["files"][PRECISION_FILES[precision]]["sha256"]

    def has(self, precision: str) -> bool:
        """True when the package folder holds the model of this precision (fp32 is optional)."""
        return self.file(precision).is_file()

    def missing_message(self, precision: str) -> str:
        """Why a precision cannot run and the command that regenerates its file."""
        info = self.manifest.get("files", {}).get(PRECISION_FILES[precision], {})
        path = self.file(precision)
        if not info:
            return f"{path}: {precision} model not in this package (manifest.files has no entry for it)"
        where = f" (the export left a copy in {info['cache']})" if info.get("cache") else ""
        how = info.get("regenerate") or self.manifest.get("training", {}).get("command", "tensortouch train export")
        ships = " and ".join(p for p, f in PRECISION_FILES.items() if (self.folder / f).is_file()) or "no model"
        return (f"{path}: this package ships {ships} only; the {precision} model (sha256 "
                f"{info.get('sha256', '?')[:12]}…) is not in the folder{where}. Regenerate it with: {how}")

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        b = self.manifest["output"]["bounds"]
        lo = np.array([b[c][0] for c in CHANNELS], dtype=np.float32)
        hi = np.array([b[c][1] for c in CHANNELS], dtype=np.float32)
        return lo, hi


def _model_roots(root: Path | None) -> list[Path]:
    """`root`, or the writable models folder then the packages shipped inside an installed wheel."""
    if root is not None:
        return [Path(root)]
    return [r for r in (paths.models_dir(), paths.shipped_models_dir()) if r is not None]


def installed_packages(root: Path | None = None) -> list[Path]:
    found: dict[str, Path] = {}
    for r in reversed(_model_roots(root)):           # a writable package shadows a shipped one of its name
        if r.is_dir():
            found.update({p.name: p for p in r.iterdir() if (p / "manifest.json").is_file()})
    return sorted(found.values())


def _fail(where, msg):
    raise ModelPackageError(f"{where}: {msg}")


CONTACT_LIMIT = 1e6      # no contact setting (N, px, mm, frames) is larger
POSITIVE = ("threshold_n", "stable_frames")     # contact settings that must be > 0 (a threshold, a divisor)
FRACTIONS = ("split_dip",)                       # contact settings that must be < 1


def _number(v) -> bool:
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:          # an integer beyond any float
        return False


def _check_runtime(rt, mpath) -> None:
    """The manifest's optional `runtime` section: `runtime.tare` is a boolean or null; `runtime.contacts` holds
    ContactConfig fields by their own names, each null or a finite number in [0, CONTACT_LIMIT] (> 0 for
    POSITIVE; integers for the int fields)."""
    from dataclasses import fields

    from .contacts import ContactConfig

    if rt is None:
        return
    if not isinstance(rt, dict):
        _fail(mpath, f"runtime must be an object, got {type(rt).__name__}")
    if rt.get("tare") is not None and not isinstance(rt["tare"], bool):
        _fail(mpath, f"runtime.tare is {rt['tare']!r}, expected true, false or null")
    contacts = rt.get("contacts")
    if contacts is None:
        return
    if not isinstance(contacts, dict):
        _fail(mpath, f"runtime.contacts must be an object, got {type(contacts).__name__}")
    known = {f.name for f in fields(ContactConfig)}
    ints = {f.name for f in fields(ContactConfig) if f.type in (int, "int")}
    for key, v in contacts.items():
        if key not in known:
            _fail(mpath, f"runtime.contacts.{key}: not a contact setting (expected some of {sorted(known)})")
        if v is None:
            continue
        if key in FRACTIONS and (not _number(v) or not 0 <= v < 1):
            _fail(mpath, f"runtime.contacts.{key} is {v!r}, expected null or a finite number in [0, 1)")
        if not _number(v) or v < 0 or (key in POSITIVE and v == 0) or v > CONTACT_LIMIT \
                or (key in ints and not isinstance(v, int)):
            need = "> 0" if key in POSITIVE else ">= 0"
            kind = "an integer" if key in ints else "a finite number"
            _fail(mpath, f"runtime.contacts.{key} is {v!r}, expected null or {kind} {need} and <= {CONTACT_LIMIT:g}")


def load_package(folder: str | Path, verify_hashes: bool = True) -> ModelPackage:
    """Read and check a model package folder (manifest, hashes, channel contract)."""
    folder = Path(folder)
    mpath = folder / "manifest.json"
    if not folder.is_dir():
        _fail(folder, "model package folder does not exist")
    if not mpath.is_file():
        _fail(mpath, "missing (every model package has a manifest.json)")
    try:
        m = json.loads(mpath.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        _fail(mpath, f"not UTF-8 text ({exc.reason} at byte {exc.start}); expected a JSON object")
    except (json.JSONDecodeError, RecursionError) as exc:
        _fail(mpath, f"not valid JSON ({str(exc)[:200]})")
    if not isinstance(m, dict):
        _fail(mpath, f"expected a JSON object, got {type(m).__name__}")
    if m.get("schema") != SCHEMA:
        _fail(mpath, f"schema is {m.get('schema')!r}, expected {SCHEMA!r}")
    if not isinstance(m.get("schema_version"), int) or m["schema_version"] > SCHEMA_VERSION:
        _fail(mpath, f"schema_version {m.get('schema_version')!r} not supported (<= {SCHEMA_VERSION})")
    for key in ("input", "output", "files"):
        if not isinstance(m.get(key), dict):
            _fail(mpath, f"field '{key}' missing or not an object")
    check_manifest(m, mpath)          # input, output, bounds: types and plausible ranges (contracts/manifest_schema.py)
    _check_runtime(m.get("runtime"), mpath)
    if not m["files"]:
        _fail(mpath, "files is empty: every model file must be listed with its sha256")
    for name, info in m["files"].items():
        if not (isinstance(info, dict) and isinstance(info.get("sha256"), str)):
            _fail(mpath, f"files.{name} must be an object with a \"sha256\" string")
        if Path(name).name != name or name in (".", ".."):
            _fail(mpath, f"files: {name!r} must be a file name inside the package folder")
        path = folder / name
        if not path.is_file():
            if info.get("optional"):
                continue          # e.g. an int8-only package: the fp32 hash is recorded, the file is not shipped
            _fail(path, "listed in manifest.files but missing")
        if verify_hashes and sha256_file(path) != info.get("sha256"):
            _fail(path, "SHA-256 does not match manifest (corrupt or replaced file)")
    return ModelPackage(folder, m)


def find_package(name: str | None = None, root: Path | None = None) -> ModelPackage:
    """The named package, or the only/newest installed one (manifest `created`, then file time); a clear
    message when none exists."""
    roots = _model_roots(root)
    if name:
        candidate = Path(name)
        folder = candidate if candidate.is_dir() else next(
            (r / name for r in roots if (r / name).is_dir()), roots[0] / name)
        return load_package(folder)
    found = installed_packages(root)
    root = roots[0]
    if not found:
        from ...contracts.extras import install_command

        raise ModelPackageError(
            f"no trained model is installed in {root}. Build one with `tensortouch train all` "
            f"(needs the train extra: {install_command('train')}), or pass --model PATH to a model package.")
    return load_package(max(found, key=_newest_key))


def _newest_key(folder: Path) -> tuple[str, float]:
    """Sort key of an installed package: its manifest's `created` time (ISO 8601 UTC, written by the
    export; a fresh clone gives every file the same modification time), then the manifest's mtime."""
    path = folder / "manifest.json"
    try:
        created = json.loads(path.read_text()).get("created")
    except (OSError, ValueError, AttributeError):
        created = None
    return (created if isinstance(created, str) else "", path.stat().st_mtime)


class FieldModel:
    """One onnxruntime session running a model package at a chosen precision."""

    def __init__(self, package: ModelPackage, precision: str = "int8", threads: int = 1):
        import onnxruntime as ort

        self.package = package
        self.precision = precision
        path = package.file(precision)
        if not path.is_file():
            raise ModelPackageError(package.missing_message(precision))
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(1, int(threads))
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for corrupt graphs
            _fail(path, f"onnxruntime cannot load it ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})")
        h, w = package.size
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) != 1 or len(outputs) < 1:
            _fail(path, f"expected 1 input and >= 1 output, graph has {len(inputs)} and {len(outputs)}")
        self._check_shape(path, "input", inputs[0].shape, [6, h, w])
        self._check_shape(path, "output", outputs[0].shape, [N_CHANNELS, h, w])
        self.input_name = inputs[0].name
        self.output_name = outputs[0].name
        if not all(isinstance(d, int) for d in [*inputs[0].shape[1:], *outputs[0].shape[1:]]):
            self._probe(path, h, w)     # symbolic dims: the real shapes show only when it runs
        lo, hi = package.bounds()
        self.lo = lo[:, None, None]
        self.span = (hi - lo)[:, None, None]

    @staticmethod
    def _check_shape(path, what, shape, expect):
        if len(shape) != 4:
            _fail(path, f"{what} rank {len(shape)}, expected 4 (N, C, H, W)")
        for got, want, axis in zip(shape[1:], expect, ("C", "H", "W")):
            if isinstance(got, int) and got != want:
                _fail(path, f"{what} {axis} = {got}, manifest says {want} (shape {list(shape)})")

    def _probe(self, path, h: int, w: int) -> None:
        """One inference on a blank input: the output must be (1, 15, H, W) as the manifest says."""
        try:
            y = self.session.run([self.output_name], {self.input_name: np.zeros((1, 6, h, w), np.float32)})[0]
        except Exception as exc:  # noqa: BLE001 - onnxruntime's own exception types
            _fail(path, f"does not run on a (1, 6, {h}, {w}) input ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0][:200] if str(exc) else ''})")
        if tuple(y.shape) != (1, N_CHANNELS, h, w):
            _fail(path, f"output shape {list(y.shape)} for a (1, 6, {h}, {w}) input, expected "
                        f"[1, {N_CHANNELS}, {h}, {w}] (manifest input.size {h}x{w})")

    def run_normalized(self, x: np.ndarray) -> np.ndarray:
        """x: (6, H, W) or (N, 6, H, W) float32 in [0, 1] → raw network output (N, 15, H, W)."""
        x = np.ascontiguousarray(x, dtype=np.float32)
        if x.ndim == 3:
            x = x[None]
        return self.session.run([self.output_name], {self.input_name: x})[0]

    def denormalize(self, y: np.ndarray) -> np.ndarray:
        return self.lo + np.asarray(y, dtype=np.float32) * self.span

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """(6, H, W) input → (15, H, W) fields in physical units (mm, MPa)."""
        y = self.run_normalized(x)[0]
        if y.dtype != np.float32 or not y.flags.writeable:
            return self.denormalize(y)
        np.multiply(y, self.span, out=y)       # in place on onnxruntime's fresh output: no temporaries
        y += self.lo
        return y
