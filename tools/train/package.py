"""The model package on disk (docs/model_package.md): its manifest, written atomically, and the load
checks the runtime applies. Used by export.py (stage 7) and by the tests.

- `build_manifest`  manifest.json of a package: input/output contract, file hashes, training command;
- `write_package`   exported_models/<name>/ with manifest.json, written atomically (temp dir + rename);
- `verify_package`  the checks the runtime applies on load (hashes, schema, graph shapes, channels).
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from ...contracts.errors import ModelPackageError
from ...contracts.fields import CHANNEL_UNITS, CHANNELS, INPUT_CHANNELS
from ...contracts.files import atomic_write, atomic_write_json
from ...contracts.names import confined

SCHEMA = "tensortouch.model"
SCHEMA_VERSION = 1
FP32, INT8 = "model.fp32.onnx", "model.int8.onnx"
# the fp32 graph with its large weights stored as float16 and cast to float32 in the graph: what a package
# ships so that int8 can be compared with fp32 from a clean checkout (tools/train/export.py `half_weights`)
FP32_HALF = "model.fp32-half.onnx"


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def git_commit() -> str:
    from ...contracts.paths import ROOT

    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def repo_relative(path: Path) -> str:
    """How a committed manifest names a path: relative to the repository root when inside it; inside
    the build cache, as `cache/…` (the cache's place in a checkout, where a rebuild puts it, also when
    this build's cache was moved by TENSORTOUCH_CACHE); else absolute."""
    from ...contracts.paths import ROOT, cache_dir

    path = Path(path).resolve()
    for root, prefix in ((ROOT, None), (cache_dir().resolve(), "cache")):
        try:
            rel = path.relative_to(root)
        except ValueError:
            continue
        return str(Path(prefix) / rel) if prefix else str(rel)
    return str(path)


def build_manifest(name: str, size: int, bounds: dict, files: dict[str, Path], command: str,
                   data_hash: str, metrics: dict, wall_time_s: float = 0.0, shipped: tuple[str, ...] = (INT8,),
                   run: str | Path | None = None, fp32_cache: Path | None = None, regenerate: str = "") -> dict:
    """`files` lists every model the export made (hash recorded); those not in `shipped` are marked
    optional (absent from the package; `cache` says where the export left it, `regenerate` how to
    put it into the package)."""
    entries = {}
    for k, p in files.items():
        entries[k] = {"sha256": sha256_file(p)}
        if k not in shipped:
            entries[k].update(optional=True, regenerate=regenerate or command)
            if fp32_cache is not None and k == FP32:
                entries[k]["cache"] = repo_relative(fp32_cache)
    training = {"command": command, "data_hash": data_hash, "git_commit": git_commit(),
                "wall_time_s": float(wall_time_s)}
    if run is not None:
        training["run"] = repo_relative(Path(run))
    return {
        "schema": SCHEMA, "schema_version": SCHEMA_VERSION, "name": name,
        "created": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "input": {"name": "input", "layout": "NCHW", "size": [size, size], "dtype": "float32",
                  "channels": list(INPUT_CHANNELS), "range": [0.0, 1.0]},
        "output": {"name": "fields", "layout": "NCHW", "size": [size, size], "channels": list(CHANNELS),
                   "units": list(CHANNEL_UNITS), "normalization": "minmax",
                   "bounds": {c: [float(bounds[c][0]), float(bounds[c][1])] for c in CHANNELS}},
        "files": entries,
        "training": training,
        "metrics": metrics,
    }


def atomic_copy(src: Path, dst: Path) -> None:
    with open(src, "rb") as fh:
        atomic_write(dst, lambda out: shutil.copyfileobj(fh, out))


SEALED_LOG = "sealed_scores.json"     # tools/train/protocol.py: the package's log of sealed-set scores


def write_package(root: str | Path, name: str, models: dict[str, Path], manifest: dict) -> Path:
    """Atomically create/replace <root>/<name>/ with manifest.json and the `models` {file name: path}
    to ship (a subset of manifest.files: optional files may be left out). A replaced package's sealed-score
    log is carried over: its entries name the model files they scored, so they are never lost."""
    root = Path(root)
    final = confined(root, name, "package name", ModelPackageError)     # before anything is created
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=f".{name}.tmp"))
    os.chmod(tmp, 0o755)
    try:
        for k, src in models.items():
            if k not in manifest["files"]:
                raise ModelPackageError(f"{tmp / k}: not listed in the manifest's files")
            shutil.copyfile(src, tmp / k)
            if sha256_file(tmp / k) != manifest["files"][k]["sha256"]:
                raise ModelPackageError(f"{tmp / k}: copy does not match the hashed file")
        for k, info in manifest["files"].items():
            if k not in models and not info.get("optional"):
                raise ModelPackageError(f"{tmp / k}: required by the manifest but not written")
        with open(tmp / "manifest.json", "w") as fh:
            json.dump(manifest, fh, indent=1)
        log_file = final / SEALED_LOG           # the sealed scores of what shipped under this name stay with it
        if log_file.is_file():
            shutil.copyfile(log_file, tmp / SEALED_LOG)
        old = None
        if final.exists():
            old = root / f".{name}.old.{os.getpid()}"
            os.replace(final, old)
        os.replace(tmp, final)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def verify_package(folder: str | Path) -> dict:
    """The docs/model_package.md load checks; returns the manifest or raises ModelPackageError."""
    import onnx

    folder = Path(folder)
    mpath = folder / "manifest.json"
    try:
        man = json.loads(mpath.read_text())
    except (OSError, ValueError) as exc:
        raise ModelPackageError(f"{mpath}: missing or unreadable ({exc})") from None
    if man.get("schema") != SCHEMA or man.get("schema_version") != SCHEMA_VERSION:
        raise ModelPackageError(f"{mpath}: schema/schema_version must be {SCHEMA!r}/{SCHEMA_VERSION}")
    files = man.get("files", {})
    if files.get(INT8, {}).get("optional"):
        raise ModelPackageError(f"{mpath}: files.{INT8} is the runtime default and cannot be optional")
    present = []
    for fname, info in files.items():
        if not (folder / fname).is_file():
            if info.get("optional"):
                continue
            raise ModelPackageError(f"{mpath}: files.{fname} does not exist")
        if sha256_file(folder / fname) != info.get("sha256"):
            raise ModelPackageError(f"{folder / fname}: sha256 does not match manifest files.{fname}")
        present.append(fname)
    if INT8 not in present:
        raise ModelPackageError(f"{mpath}: files.{INT8} must be listed (every package ships the int8 model)")
    out = man.get("output", {})
    if out.get("channels") != list(CHANNELS):
        raise ModelPackageError(f"{mpath}: output.channels differ from docs/fields.md")
    for c in CHANNELS:
        lo, hi = out["bounds"][c]
        if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
            raise ModelPackageError(f"{mpath}: output.bounds.{c} must be finite with lo ≤ hi")
    h, w = man["input"]["size"]
    for fname in present:
        g = onnx.load(str(folder / fname), load_external_data=False).graph
        dims = lambda v: [d.dim_value or d.dim_param for d in v.type.tensor_type.shape.dim]  # noqa: E731
        i_dims, o_dims = dims(g.input[0]), dims(g.output[0])
        if i_dims[1:] != [6, h, w] or o_dims[1:] != [15, *out["size"]]:
            raise ModelPackageError(f"{folder / fname}: graph input {i_dims} / output {o_dims} do not match "
                                    f"[N, 6, {h}, {w}] / [N, 15, {out['size'][0]}, {out['size'][1]}]")
    return man


def update_manifest(folder: Path, change) -> None:
    """Apply `change(manifest)` to a package's manifest.json and write it atomically (the manifest is
    not itself hashed, so export-time records such as wall time, threshold, init checkpoint go here)."""
    p = Path(folder) / "manifest.json"
    man = json.loads(p.read_text())
    change(man)
    atomic_write_json(p, man)
