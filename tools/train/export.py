"""Stage 7 — ONNX export, static int8 quantization, parity report, model package (docs/model_package.md).

- `export_onnx`     legacy TorchScript exporter (dynamo=False, opset 17), input "input" (N, 6, H, W),
                    output "fields" (N, 15, H, W), dynamic batch;
- `quantize_int8`   onnxruntime static QDQ: uint8 activations, per-channel int8 weights (DESIGN §10:
                    the fastest of the variants measured), MinMax calibration on training inputs;
- `latency_ms`      single-thread latency of both models measured interleaved in one run;
- `parity_report`   per-modality PSNR of int8 vs fp32 (and of each vs ground truth when given);
- `write_package`   exported_models/<name>/ with manifest.json, written atomically (temp dir + rename);
- `verify_package`  the checks the runtime applies on load (hashes, schema, graph shapes, channels).
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.errors import ModelPackageError
from runtime.fields import CHANNEL_UNITS, CHANNELS, INPUT_CHANNELS

log = logging.getLogger(__name__)

SCHEMA = "tensortouch.model"
SCHEMA_VERSION = 1
FP32, INT8 = "model.fp32.onnx", "model.int8.onnx"


@dataclass(frozen=True)
class ExportConfig:
    opset: int = 17
    calibration_samples: int = 32        # training inputs used to calibrate activation ranges
    per_channel: bool = True
    # Only layers with weights are quantized. Measured on this machine (128², one thread, interleaved,
    # best of 120): fp32 7.7 ms; QDQ of every op 8.4 ms (slower: Softmax/Mul/Add/attention MatMul in
    # int8 cost more than they save); Conv + Gemm only 7.05 ms.
    op_types: tuple[str, ...] = ("Conv", "Gemm", "MatMul")
    quantize_activation_matmul: bool = False   # attention q·kᵀ and p·v (no weight input) stay fp32
    latency_runs: int = 50
    latency_warmup: int = 5
    latency_threads: int = 1


def export_onnx(model, path: str | Path, image_size: int, opset: int = ExportConfig.opset,
                dynamic_batch: bool = False) -> Path:
    """Export a torch model (6 → 15 channels) to ONNX with the legacy exporter.

    The default is a static batch of 1 (the runtime runs one frame at a time): every reshape is then
    constant-folded, which removes ~500 Shape/Gather/Concat nodes from the Hiera graph."""
    import torch

    path = Path(path)
    model = model.eval()
    dummy = torch.rand(1, 6, image_size, image_size)
    torch.onnx.export(model, (dummy,), str(path), input_names=["input"], output_names=["fields"],
                      opset_version=opset, dynamo=False, do_constant_folding=True,
                      dynamic_axes={"input": {0: "N"}, "fields": {0: "N"}} if dynamic_batch else None)
    return path


class _Reader:
    """onnxruntime CalibrationDataReader over (N, 6, H, W) float32 inputs, one sample per call."""

    def __init__(self, inputs: np.ndarray):
        self.inputs, self.i = inputs, 0

    def get_next(self):
        if self.i >= len(self.inputs):
            return None
        self.i += 1
        return {"input": self.inputs[self.i - 1:self.i]}

    def rewind(self):
        self.i = 0


def quantize_int8(fp32_path: str | Path, int8_path: str | Path, calibration: np.ndarray,
                  cfg: ExportConfig = ExportConfig()) -> Path:
    """Static QDQ quantization (uint8 activations, int8 weights, per channel) of the weighted layers."""
    import onnx
    from onnxruntime.quantization import (CalibrationDataReader, QuantFormat, QuantType, quantize_static)
    from onnxruntime.quantization.shape_inference import quant_pre_process

    reader = type("Reader", (_Reader, CalibrationDataReader), {})(np.ascontiguousarray(calibration, np.float32))
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True)
        exclude = []
        if not cfg.quantize_activation_matmul:
            g = onnx.load(str(pre)).graph
            weights = {t.name for t in g.initializer}
            exclude = [n.name for n in g.node if n.op_type == "MatMul" and not any(i in weights for i in n.input)]
        quantize_static(str(pre), str(int8_path), reader, quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        per_channel=cfg.per_channel, op_types_to_quantize=list(cfg.op_types),
                        nodes_to_exclude=exclude)
    return Path(int8_path)


def session(path: str | Path, threads: int = 1):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def run_model(sess, inputs: np.ndarray) -> np.ndarray:
    """Run a session frame by frame (packages have a static batch of 1)."""
    outs = [sess.run(None, {"input": np.ascontiguousarray(inputs[i:i + 1], np.float32)})[0]
            for i in range(len(inputs))]
    return np.concatenate(outs)


def latency_ms(paths: dict[str, str | Path], sample: np.ndarray, cfg: ExportConfig = ExportConfig()) -> dict:
    """{name: {median, min, p10, p90, p99, mean}} single-frame latency (ms), models run alternately in one
    loop so that load from other processes hits all of them alike."""
    sessions = {k: session(p, cfg.latency_threads) for k, p in paths.items()}
    x = np.ascontiguousarray(sample[:1], np.float32)
    times = {k: [] for k in sessions}
    for i in range(cfg.latency_warmup + cfg.latency_runs):
        for k, s in sessions.items():
            t0 = time.perf_counter()
            s.run(None, {"input": x})
            if i >= cfg.latency_warmup:
                times[k].append((time.perf_counter() - t0) * 1e3)
    return {k: {"median": float(np.median(v)), "min": float(np.min(v)), "p10": float(np.percentile(v, 10)),
                "p90": float(np.percentile(v, 90)),
                "p99": float(np.percentile(v, 99)), "mean": float(np.mean(v))} for k, v in times.items()}


def parity_report(fp32_path, int8_path, inputs: np.ndarray, targets: np.ndarray | None = None,
                  bounds: dict | None = None) -> dict:
    """Per-modality PSNR of int8 against fp32; with targets also each model against the truth."""
    from tools.train.model.metrics import evaluate, psnr_per_modality

    y32 = run_model(session(fp32_path, 2), inputs)
    y8 = run_model(session(int8_path, 2), inputs)
    rep = {"int8_vs_fp32_psnr": psnr_per_modality(y8, y32), "samples": int(len(inputs))}
    rep["int8_vs_fp32_psnr_mean"] = float(np.mean(list(rep["int8_vs_fp32_psnr"].values())))
    if targets is not None:
        e32, e8 = evaluate(y32, targets, bounds), evaluate(y8, targets, bounds)
        rep["fp32"], rep["int8"] = e32, e8
        rep["psnr_loss_db"] = e32["mean"]["psnr"] - e8["mean"]["psnr"]
        rep["psnr_loss_db_per_modality"] = {m: e32["per_modality"][m]["psnr"] - e8["per_modality"][m]["psnr"]
                                            for m in e32["per_modality"]}
    return rep


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def git_commit() -> str:
    from runtime.paths import ROOT

    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def build_manifest(name: str, size: int, bounds: dict, files: dict[str, Path], command: str,
                   data_hash: str, metrics: dict, wall_time_s: float = 0.0) -> dict:
    return {
        "schema": SCHEMA, "schema_version": SCHEMA_VERSION, "name": name,
        "created": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "input": {"name": "input", "layout": "NCHW", "size": [size, size], "dtype": "float32",
                  "channels": list(INPUT_CHANNELS), "range": [0.0, 1.0]},
        "output": {"name": "fields", "layout": "NCHW", "size": [size, size], "channels": list(CHANNELS),
                   "units": list(CHANNEL_UNITS), "normalization": "minmax",
                   "bounds": {c: [float(bounds[c][0]), float(bounds[c][1])] for c in CHANNELS}},
        "files": {k: {"sha256": sha256_file(p)} for k, p in files.items()},
        "training": {"command": command, "data_hash": data_hash, "git_commit": git_commit(),
                     "wall_time_s": float(wall_time_s)},
        "metrics": metrics,
    }


def write_package(root: str | Path, name: str, fp32_path: Path, int8_path: Path, manifest: dict) -> Path:
    """Atomically create/replace <root>/<name>/ holding both models and manifest.json."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    final = root / name
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=f".{name}.tmp"))
    os.chmod(tmp, 0o755)
    try:
        shutil.copyfile(fp32_path, tmp / FP32)
        shutil.copyfile(int8_path, tmp / INT8)
        for k in (FP32, INT8):
            if sha256_file(tmp / k) != manifest["files"][k]["sha256"]:
                raise ModelPackageError(f"{tmp / k}: copy does not match the hashed file")
        with open(tmp / "manifest.json", "w") as fh:
            json.dump(manifest, fh, indent=1)
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
    for fname, info in man.get("files", {}).items():
        if not (folder / fname).is_file():
            raise ModelPackageError(f"{mpath}: files.{fname} does not exist")
        if sha256_file(folder / fname) != info.get("sha256"):
            raise ModelPackageError(f"{folder / fname}: sha256 does not match manifest files.{fname}")
    out = man.get("output", {})
    if out.get("channels") != list(CHANNELS):
        raise ModelPackageError(f"{mpath}: output.channels differ from docs/fields.md")
    for c in CHANNELS:
        lo, hi = out["bounds"][c]
        if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
            raise ModelPackageError(f"{mpath}: output.bounds.{c} must be finite with lo ≤ hi")
    h, w = man["input"]["size"]
    for fname in man["files"]:
        g = onnx.load(str(folder / fname), load_external_data=False).graph
        dims = lambda v: [d.dim_value or d.dim_param for d in v.type.tensor_type.shape.dim]  # noqa: E731
        i_dims, o_dims = dims(g.input[0]), dims(g.output[0])
        if i_dims[1:] != [6, h, w] or o_dims[1:] != [15, *out["size"]]:
            raise ModelPackageError(f"{folder / fname}: graph input {i_dims} / output {o_dims} do not match "
                                    f"[N, 6, {h}, {w}] / [N, 15, {out['size'][0]}, {out['size'][1]}]")
    return man


def count_quantize_nodes(path: str | Path) -> int:
    import onnx

    return sum(n.op_type == "QuantizeLinear" for n in onnx.load(str(path)).graph.node)


def export_run(run: str | Path, data: str | Path, name: str, models_root: str | Path, command: str,
               cfg: ExportConfig = ExportConfig(), wall_time_s: float = 0.0) -> dict:
    """Fit run + dataset → exported_models/<name>/ (fp32, int8, manifest with parity metrics)."""
    from tools.train.fields import read_bounds
    from tools.train.model.data import data_hash, load_split
    from tools.train.model.train import load_trained

    run, data = Path(run), Path(data)
    model, info = load_trained(run)
    size = int(info["image_size"])
    bounds = read_bounds(data / "bounds.json")
    x_tr, _ = load_split(data, "train", limit=cfg.calibration_samples)
    try:
        x_va, y_va = load_split(data, "val")
    except Exception:  # noqa: BLE001 — a dataset without a val split evaluates on training samples
        x_va, y_va = load_split(data, "train", limit=16)
    with tempfile.TemporaryDirectory() as tmp:
        fp32, int8 = Path(tmp) / FP32, Path(tmp) / INT8
        export_onnx(model, fp32, size, cfg.opset)
        quantize_int8(fp32, int8, x_tr.astype(np.float32) / 255.0, cfg)
        rep = parity_report(fp32, int8, x_va.astype(np.float32) / 255.0, y_va, bounds)
        lat = latency_ms({"fp32": fp32, "int8": int8}, x_va.astype(np.float32) / 255.0, cfg)
        metrics = {"fp32": {**rep["fp32"]["mean"], "per_modality": rep["fp32"]["per_modality"]},
                   "int8": {**rep["int8"]["mean"], "per_modality": rep["int8"]["per_modality"]},
                   "int8_vs_fp32_psnr": rep["int8_vs_fp32_psnr"],
                   "latency_ms": {"fp32": lat["fp32"]["median"], "int8": lat["int8"]["median"],
                                  "threads": cfg.latency_threads, "detail": lat},
                   "eval_samples": rep["samples"], "arch": info["arch"], "params": info["params"]}
        man = build_manifest(name, size, bounds, {FP32: fp32, INT8: int8}, command, data_hash(data), metrics,
                             wall_time_s)
        folder = write_package(models_root, name, fp32, int8, man)
    verify_package(folder)
    log.info("packaged %s: PSNR fp32 %.2f int8 %.2f dB, latency fp32 %.2f int8 %.2f ms", folder,
             metrics["fp32"]["psnr"], metrics["int8"]["psnr"], metrics["latency_ms"]["fp32"],
             metrics["latency_ms"]["int8"])
    return man
