"""Stage 7 — ONNX export, int8 quantization, parity report, model package (docs/model_package.md).

- `export_onnx`     legacy TorchScript exporter (dynamo=False, opset 20), input "input" (1, 6, H, W),
                    output "fields" (1, 15, H, W), after the exact rewrites of `export_graph`;
- `quantize_int8`   scheme "hybrid" (default): static QDQ int8 for Conv (uint8 activations, per-channel
                    int8 weights, MinMax calibration on training inputs spread over the split) + int8
                    weights for the weighted MatMuls with activations quantized per frame (onnxruntime
                    DynamicQuantizeMatMul);
                    scheme "static": the earlier all-static QDQ of Conv/Gemm/MatMul;
- `latency_ms`      single-thread latency of both models measured interleaved in one run;
- `parity_report`   per-modality PSNR of int8 vs fp32 (and of each vs ground truth when given);
- `export_run`      the package: int8 only unless asked (`with_fp32`): the fp32 graph goes to the build
                    cache (`fp32_cache_path`), its hash and parity metrics stay in the manifest; written
                    and verified by package.py (`build_manifest`, `write_package`, `verify_package`).
"""
from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...contracts.errors import ModelPackageError
from ...contracts.names import confined
from .model.network_input import IN_CHANS
from .package import FP32, FP32_HALF, INT8, atomic_copy, build_manifest, repo_relative, verify_package, write_package

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExportConfig:
    opset: int = 20                      # GELU as one ONNX op (opset 20): int8 5 % faster than 17, same output
    # Activation ranges (MinMax) come from `quantization_samples` training inputs picked by
    # `quantization_pick`: "spread" = evenly over the whole train split, "first" = its first samples.
    # The dataset is written session by session, so its first samples are a few pokes of one unit:
    # ranges too narrow for slides, whose clipped activations then move their forces.
    quantization_samples: int = 128
    quantization_pick: str = "spread"     # "spread" | "first"
    per_channel: bool = True
    rewrite: bool = True                 # exact graph rewrites of export_graph (fused heads, deconv)
    # Quantization scheme, measured on hiera-qup-128 (128², one thread, interleaved, CPU time per frame
    # on a loaded machine, when the scheme was chosen; docs/history/BENCHMARKS-sessions-1-16.md): fp32 (rewritten) 8.8 ms; all-static QDQ
    # Conv+Gemm+MatMul 10.0 ms, QOperator the same; static Conv only 9.6; dynamic MatMul only 8.8
    # (-0.02 dB); hybrid = static Conv + dynamic MatMul 6.5 ms (-0.10 dB PSNR vs fp32); hybrid with any
    # of the three convs left fp32 was slower. Quantizing every op (Softmax/Mul/Add/attention MatMul)
    # was slower still; dynamic ConvInteger 5x slower.
    # scheme "full": static QDQ of every op of a network made of convolutions (tools/train/model/convnet.py):
    # convolutions, the skip additions, the nearest upsamplings and the head's shuffle; measured on it
    # (128², one thread, interleaved, CPU ms/frame, load ≈ 7): fp32 4.35, static Conv only 3.09, all ops the
    # quantizer knows 2.74, these 2.49
    scheme: str = "hybrid"               # "hybrid" | "static" | "full"
    full_op_types: tuple[str, ...] = ("Conv", "Add", "Resize", "Relu", "Concat", "DepthToSpace")
    # scheme "full": the head (the last convolution and what follows it) stays float. With its output in
    # uint8 steps (1/255 of each channel's range), the total force the runtime sums over 16k pixels moved
    # by 0.26 N (p95, int8 − fp32) on the student's validation samples
    quantize_head: bool = False
    op_types: tuple[str, ...] = ("Conv", "Gemm", "MatMul")     # static ops of scheme "static"
    hybrid_static_op_types: tuple[str, ...] = ("Conv",)       # static ops of scheme "hybrid"
    quantize_activation_matmul: bool = False   # attention q·kᵀ and p·v (no weight input) stay fp32
    with_fp32: bool = False              # ship model.fp32.onnx inside the package (default: build cache)
    # ship model.fp32-half.onnx (the fp32 graph with float16-stored weights, half its size) when the exact
    # fp32 graph is not shipped, so that `bench runtime` and the parity check run from a clean checkout
    fp32_half: bool = True
    half_min_elements: int = 1024        # initializers at least this large are stored as float16
    latency_runs: int = 50
    latency_warmup: int = 5
    latency_threads: int = 1


def export_onnx(model, path: str | Path, image_size: int, opset: int = ExportConfig.opset,
                dynamic_batch: bool = False, rewrite: bool = ExportConfig.rewrite) -> Path:
    """Export a torch model (6 → 15 channels) to ONNX with the legacy exporter.

    The default is a static batch of 1 (the runtime runs one frame at a time): every reshape is then
    constant-folded, which removes ~500 Shape/Gather/Concat nodes from the Hiera graph. With `rewrite`
    the exact rewrites of tools/train/export_graph.py are applied first (checked numerically); the
    exported graph is deterministic for a given checkpoint (same bytes, same SHA-256)."""
    import copy

    import torch

    from .export_graph import reparametrize

    path = Path(path)
    model = model.eval()
    if rewrite:
        model, _ = reparametrize(copy.deepcopy(model), image_size)
    dummy = torch.rand(1, IN_CHANS, image_size, image_size)
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
    """int8 model of `fp32_path` with the scheme of `cfg` (see the module docstring)."""
    import onnx
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_dynamic, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    if cfg.scheme not in ("hybrid", "static", "full"):
        raise ModelPackageError(f"ExportConfig.scheme {cfg.scheme!r}: expected 'hybrid', 'static' or 'full'")
    reader = type("Reader", (_Reader, CalibrationDataReader), {})(np.ascontiguousarray(calibration, np.float32))
    static_ops = {"hybrid": cfg.hybrid_static_op_types, "static": cfg.op_types, "full": cfg.full_op_types}[cfg.scheme]
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        # hybrid: no pre-optimization — onnxruntime's MatMul+Add→Gemm fusion would wrap every weighted
        # MatMul in 2-D reshapes; kept N-D, they quantize to DynamicQuantizeMatMul with the bias fused
        # at load and a shared input quantization for q/k/v (measured 3 % faster, same output)
        quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True,
                          skip_optimization=cfg.scheme == "hybrid")
        g = onnx.load(str(pre)).graph
        weights = {t.name for t in g.initializer}
        act_matmul = [n.name for n in g.node if n.op_type == "MatMul" and not any(i in weights for i in n.input)]
        exclude = [] if cfg.quantize_activation_matmul else act_matmul
        if cfg.scheme == "full" and not cfg.quantize_head:
            exclude = exclude + output_head_nodes(g)
        static_out = Path(tmp) / "static.onnx" if cfg.scheme == "hybrid" else Path(int8_path)
        quantize_static(str(pre), str(static_out), reader, quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        per_channel=cfg.per_channel, op_types_to_quantize=list(static_ops),
                        nodes_to_exclude=exclude)
        if cfg.scheme == "hybrid":
            quantize_dynamic(str(static_out), str(int8_path), op_types_to_quantize=["MatMul"],
                             weight_type=QuantType.QInt8, nodes_to_exclude=exclude)
    return Path(int8_path)


def output_head_nodes(graph) -> list[str]:
    """Names of the nodes from the graph's output back to (and including) the last weighted Conv /
    ConvTranspose: the head, whose output the runtime integrates over every pixel into forces."""
    producer = {o: n for n in graph.node for o in n.output}
    names, frontier = [], [o.name for o in graph.output]
    while frontier:
        node = producer.get(frontier.pop())
        if node is None or node.name in names:
            continue
        names.append(node.name)
        if node.op_type not in ("Conv", "ConvTranspose"):
            frontier.extend(i for i in node.input[:1] if i)
    return names


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
    """{name: {median, min, p10, p90, p99, mean, cpu_median}} single-frame latency (ms), models run
    alternately in one loop so that load from other processes hits all of them alike. `cpu_median` is
    the calling thread's CPU time per run (with one onnxruntime thread the whole inference runs on
    it): on a shared machine it tracks the model's cost better than wall time."""
    sessions = {k: session(p, cfg.latency_threads) for k, p in paths.items()}
    x = np.ascontiguousarray(sample[:1], np.float32)
    times = {k: [] for k in sessions}
    cpu = {k: [] for k in sessions}
    for i in range(cfg.latency_warmup + cfg.latency_runs):
        for k, s in sessions.items():
            t0, c0 = time.perf_counter(), time.thread_time()
            s.run(None, {"input": x})
            if i >= cfg.latency_warmup:
                times[k].append((time.perf_counter() - t0) * 1e3)
                cpu[k].append((time.thread_time() - c0) * 1e3)
    return {k: {"median": float(np.median(v)), "min": float(np.min(v)), "p10": float(np.percentile(v, 10)),
                "p90": float(np.percentile(v, 90)), "p99": float(np.percentile(v, 99)), "mean": float(np.mean(v)),
                "cpu_median": float(np.median(cpu[k]))} for k, v in times.items()}


def total_force_n(y: np.ndarray, bounds: dict, pixel_area: np.ndarray) -> np.ndarray:
    """(N, 3) total contact force in N of min/max-normalized fields (N, 15, H, W): what the runtime
    integrates (normal + shear traction times pixel area, runtime.contacts.pixel_forces)."""
    from ...contracts.fields import CHANNELS

    lo = np.array([bounds[c][0] for c in CHANNELS[9:15]], np.float64)[None, :, None, None]
    hi = np.array([bounds[c][1] for c in CHANNELS[9:15]], np.float64)[None, :, None, None]
    t = lo + np.asarray(y[:, 9:15], np.float64) * (hi - lo)
    return ((t[:, 0:3] + t[:, 3:6]) * np.asarray(pixel_area, np.float64)[None, None]).sum(axis=(2, 3))


def parity_report(fp32_path, int8_path, inputs: np.ndarray, targets: np.ndarray | None = None,
                  bounds: dict | None = None, pixel_area: np.ndarray | None = None) -> dict:
    """Per-modality PSNR of int8 against fp32; with targets also each model against the truth; with
    bounds and the dataset's pixel area also the int8 - fp32 total force |ΔF| (N: mean, p95, max).
    PSNR alone can miss clipped int8 ranges that move a slide's force by tenths of a newton."""
    from .model.metrics import evaluate, psnr_per_modality

    y32 = run_model(session(fp32_path, 2), inputs)
    y8 = run_model(session(int8_path, 2), inputs)
    rep = {"int8_vs_fp32_psnr": psnr_per_modality(y8, y32), "samples": int(len(inputs))}
    rep["int8_vs_fp32_psnr_mean"] = float(np.mean(list(rep["int8_vs_fp32_psnr"].values())))
    if bounds is not None and pixel_area is not None:
        d = np.linalg.norm(total_force_n(y8, bounds, pixel_area) - total_force_n(y32, bounds, pixel_area), axis=1)
        rep["int8_vs_fp32_force_n"] = {"mean": float(d.mean()), "p95": float(np.percentile(d, 95)),
                                       "max": float(d.max())}
    if targets is not None:
        e32, e8 = evaluate(y32, targets, bounds), evaluate(y8, targets, bounds)
        rep["fp32"], rep["int8"] = e32, e8
        rep["psnr_loss_db"] = e32["mean"]["psnr"] - e8["mean"]["psnr"]
        rep["psnr_loss_db_per_modality"] = {m: e32["per_modality"][m]["psnr"] - e8["per_modality"][m]["psnr"]
                                            for m in e32["per_modality"]}
    return rep


def fp32_cache_path(run: str | Path, name: str) -> Path:
    """Where an export leaves the fp32 graph of package `name` when the package ships int8 only: beside
    the checkpoint it came from, in the fit run's folder (the build cache, never committed)."""
    return Path(run) / "export" / name / FP32


def regenerate_command(run: str | Path, data: str | Path, name: str, models_root: str | Path) -> str:
    """The export command that writes the package again with the fp32 graph inside it."""
    import shlex

    return shlex.join(["tensortouch", "train", "export", "--run", repo_relative(Path(run)),
                       "--data", repo_relative(Path(data)), "--name", name,
                       "--models-dir", repo_relative(Path(models_root)), "--with-fp32"])


def half_weights(fp32_path: str | Path, out_path: str | Path,
                 min_elements: int = ExportConfig.half_min_elements) -> dict:
    """The fp32 graph with every float32 initializer of at least `min_elements` values stored as float16,
    each followed by a Cast back to float32: the graph still computes in float32 (ONNX Runtime folds the
    casts when the session starts, so it runs at fp32 speed) with weights rounded to float16 (relative
    error ≤ 2⁻¹¹, far below int8's). An initializer that float16 cannot hold (|w| > 65504, or a nonzero
    weight that would become 0) stays float32. Returns {"converted", "kept", "bytes"}."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    model = onnx.load(str(fp32_path))
    g = model.graph
    inits, casts, converted, kept = [], [], 0, 0
    names = {i.name for i in g.initializer} | {n for node in g.node for n in node.output}
    for init in g.initializer:
        if init.data_type != TensorProto.FLOAT or int(np.prod(init.dims)) < min_elements:
            inits.append(init)
            continue
        w = numpy_helper.to_array(init)
        h = w.astype(np.float16)
        if not np.isfinite(h).all() or np.any((h == 0) & (w != 0)):
            inits.append(init)
            kept += 1
            continue
        stored = f"{init.name}__float16"
        while stored in names:
            stored += "_"
        names.add(stored)
        inits.append(numpy_helper.from_array(h, stored))
        casts.append(helper.make_node("Cast", [stored], [init.name], to=TensorProto.FLOAT,
                                      name=f"{stored}__to_float32"))
        converted += 1
    del g.initializer[:]
    g.initializer.extend(inits)
    nodes = casts + list(g.node)
    del g.node[:]
    g.node.extend(nodes)
    onnx.checker.check_model(model)
    out_path = Path(out_path)
    onnx.save(model, str(out_path))
    return {"converted": converted, "kept": kept, "bytes": out_path.stat().st_size}


def count_quantize_nodes(path: str | Path) -> int:
    """Quantization nodes (static QuantizeLinear and per-frame DynamicQuantizeLinear) in a graph."""
    import onnx

    return sum(n.op_type in ("QuantizeLinear", "DynamicQuantizeLinear") for n in onnx.load(str(path)).graph.node)


def _previous_build(folder: Path, data_hash: str) -> dict | None:
    """The `training` block of an existing package made from the same data (kept as `build` when a
    package is re-exported from the same checkpoint, so the manifest still names the full build)."""
    try:
        old = json.loads((folder / "manifest.json").read_text())["training"]
    except (OSError, ValueError, KeyError):
        return None
    if old.get("data_hash") != data_hash:
        return None
    return old.get("build") or {k: old[k] for k in ("command", "git_commit", "wall_time_s") if k in old}


def export_run(run: str | Path, data: str | Path, name: str, models_root: str | Path, command: str,
               cfg: ExportConfig = ExportConfig(), wall_time_s: float = 0.0) -> dict:
    """Fit run + dataset → exported_models/<name>/ (int8 [+ fp32], manifest with parity metrics).

    The fp32 graph is always made (parity and latency are measured against it); without
    `cfg.with_fp32` it is left in the build cache (`fp32_cache_path(run, name)`), not in the package."""
    from .fields import read_bounds

    package = confined(models_root, name, "package name", ModelPackageError)    # before any work
    from .model.data import data_hash, load_split
    from .model.train import load_trained, run_places

    run, data = Path(run), Path(data)
    model, info = load_trained(run)
    size = int(info["image_size"])
    bounds = read_bounds(data / "bounds.json")
    if cfg.quantization_pick not in ("spread", "first"):
        raise ModelPackageError(f"ExportConfig.quantization_pick {cfg.quantization_pick!r}: expected 'spread' or 'first'")
    x_tr, _ = load_split(data, "train", limit=cfg.quantization_samples, spread=cfg.quantization_pick == "spread")
    try:
        x_va, y_va = load_split(data, "val")
    except Exception:  # noqa: BLE001 — a dataset without a val split evaluates on training samples
        x_va, y_va = load_split(data, "train", limit=16)
    dhash = data_hash(data)
    previous = _previous_build(package, dhash)
    with tempfile.TemporaryDirectory() as tmp:
        fp32, int8 = Path(tmp) / FP32, Path(tmp) / INT8
        export_onnx(model, fp32, size, cfg.opset, rewrite=cfg.rewrite)
        quantize_int8(fp32, int8, x_tr.astype(np.float32) / 255.0, cfg)
        area = np.load(data / "pixel_area.npy") if (data / "pixel_area.npy").is_file() else None
        rep = parity_report(fp32, int8, x_va.astype(np.float32) / 255.0, y_va, bounds, area)
        lat = latency_ms({"fp32": fp32, "int8": int8}, x_va.astype(np.float32) / 255.0, cfg)
        metrics = {"fp32": {**rep["fp32"]["mean"], "per_modality": rep["fp32"]["per_modality"]},
                   "int8": {**rep["int8"]["mean"], "per_modality": rep["int8"]["per_modality"]},
                   "int8_vs_fp32_psnr": rep["int8_vs_fp32_psnr"],
                   "psnr_loss_db": rep["psnr_loss_db"],
                   "latency_ms": {"fp32": lat["fp32"]["median"], "int8": lat["int8"]["median"],
                                  "cpu_fp32": lat["fp32"]["cpu_median"], "cpu_int8": lat["int8"]["cpu_median"],
                                  "threads": cfg.latency_threads, "load_average": list(os.getloadavg()),
                                  "detail": lat},
                   "eval_samples": rep["samples"], "arch": info["arch"], "params": info["params"],
                   "quantization": {"scheme": cfg.scheme, "rewrite": cfg.rewrite,
                                    "quantization_samples": int(len(x_tr)),
                                    "quantization_pick": cfg.quantization_pick,
                                    "int8_vs_fp32_force_n": rep.get("int8_vs_fp32_force_n")}}
        shipped = (INT8, FP32) if cfg.with_fp32 else (INT8,)
        made = {FP32: fp32, INT8: int8}
        if cfg.fp32_half and not cfg.with_fp32:
            half = Path(tmp) / FP32_HALF
            info_half = half_weights(fp32, half, cfg.half_min_elements)
            y32 = run_model(session(fp32, 2), x_va.astype(np.float32) / 255.0)
            yh = run_model(session(half, 2), x_va.astype(np.float32) / 255.0)
            from .model.metrics import psnr_per_modality

            # identical outputs have an infinite PSNR: recorded as null (JSON has no infinity)
            vs = {k: (float(v) if np.isfinite(v) else None) for k, v in psnr_per_modality(yh, y32).items()}
            finite = [v for v in vs.values() if v is not None]
            metrics["fp32_half"] = {**info_half, "fp32_bytes": fp32.stat().st_size, "vs_fp32_psnr": vs,
                                    "vs_fp32_psnr_min": min(finite) if finite else None}
            made[FP32_HALF] = half
            shipped = (INT8, FP32_HALF)
        cache = None
        if not cfg.with_fp32:
            cache = fp32_cache_path(run, name)
            atomic_copy(fp32, cache)
        man = build_manifest(name, size, bounds, made, command, dhash, metrics,
                             wall_time_s, shipped=shipped, run=run, fp32_cache=cache,
                             regenerate=regenerate_command(run, data, name, models_root))
        if previous and previous.get("command") != command:
            man["training"]["build"] = previous
        places = run_places(run)          # device, precision, torch, threads of the runs behind the weights
        if places:
            man["training"]["run_place"] = places
        folder = write_package(models_root, name, {k: p for k, p in made.items() if k in shipped}, man)
    verify_package(folder)
    df = rep.get("int8_vs_fp32_force_n")
    log.info("packaged %s (%s): PSNR fp32 %.2f int8 %.2f dB, latency fp32 %.2f int8 %.2f ms%s%s", folder,
             "+".join(shipped), metrics["fp32"]["psnr"], metrics["int8"]["psnr"], metrics["latency_ms"]["fp32"],
             metrics["latency_ms"]["int8"], f"; int8 - fp32 total force p95 {df['p95']:.3f} N" if df else "",
             f"; fp32 graph in {cache}" if cache else "")
    return man
