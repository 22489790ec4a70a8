"""Synthetic ONNX field networks for tests and runtime benchmarks (never shipped).

Built directly with `onnx.helper` (no torch), so the runtime's benchmark and tests can exercise a
realistically sized network (a conv encoder–decoder with skip connections, ~1–3 M parameters) and
its static int8 QDQ version without a trained model. Weights are seeded random: packages made here
go to temporary folders only, never into `exported_models/` (their manifest says "synthetic").
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from ...contracts.fields import CHANNEL_UNITS, CHANNELS, INPUT_CHANNELS


def _conv(nodes, inits, rng, name, x, cin, cout, k=3, stride=1, act=True, pad=None):
    w = (rng.standard_normal((cout, cin, k, k)) * np.sqrt(2.0 / (cin * k * k))).astype(np.float32)
    b = np.zeros(cout, np.float32)
    from onnx import helper, numpy_helper

    inits += [numpy_helper.from_array(w, f"{name}.w"), numpy_helper.from_array(b, f"{name}.b")]
    nodes.append(helper.make_node("Conv", [x, f"{name}.w", f"{name}.b"], [f"{name}.y"],
                                  kernel_shape=[k, k], strides=[stride, stride], pads=[k // 2 if pad is None else pad] * 4))
    if not act:
        return f"{name}.y"
    nodes.append(helper.make_node("Relu", [f"{name}.y"], [f"{name}.r"]))
    return f"{name}.r"


def build_unet(size: int, width: int = 32, depth: int = 3, seed: int = 0, stem: int = 1):
    """A conv U-Net 6→15 channels with sigmoid output. `stem` > 1 patchifies the input first (a
    stride-`stem` conv, like Hiera's 4×4 patch embedding) and upsamples back at the end, which gives
    a ViT-like compute profile; stem 4 / width 32 / depth 3 ≈ 2.2 M parameters."""
    from onnx import TensorProto, helper

    rng = np.random.default_rng(seed)
    nodes, inits = [], []
    x = "input"
    skips, cin = [], 6
    if stem > 1:
        x = _conv(nodes, inits, rng, "stem", x, cin, width, k=stem, stride=stem, pad=0)
        cin = width
    for d in range(depth):
        cout = width * 2 ** d
        x = _conv(nodes, inits, rng, f"enc{d}a", x, cin, cout)
        x = _conv(nodes, inits, rng, f"enc{d}b", x, cout, cout)
        skips.append((x, cout))
        x = _conv(nodes, inits, rng, f"down{d}", x, cout, cout * 2, stride=2)
        cin = cout * 2
    x = _conv(nodes, inits, rng, "mid", x, cin, cin)
    for d in reversed(range(depth)):
        skip, cs = skips[d]
        up = f"up{d}"
        nodes.append(helper.make_node("Resize", [x, "", "up_scales"], [up], mode="nearest"))
        cat = f"cat{d}"
        nodes.append(helper.make_node("Concat", [up, skip], [cat], axis=1))
        x = _conv(nodes, inits, rng, f"dec{d}a", cat, cin + cs, cs)
        x = _conv(nodes, inits, rng, f"dec{d}b", x, cs, cs)
        cin = cs
    from onnx import numpy_helper

    if stem > 1:
        nodes.append(helper.make_node("Resize", [x, "", "stem_scales"], ["unstem"], mode="linear"))
        inits.append(numpy_helper.from_array(np.array([1, 1, stem, stem], np.float32), "stem_scales"))
        x = _conv(nodes, inits, rng, "refine", "unstem", cin, 16)
        cin = 16
    y = _conv(nodes, inits, rng, "head", x, cin, len(CHANNELS), k=1, act=False)
    nodes.append(helper.make_node("Sigmoid", [y], ["fields"]))
    inits.append(numpy_helper.from_array(np.array([1, 1, 2, 2], np.float32), "up_scales"))
    graph = helper.make_graph(
        nodes, "synthetic_unet",
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, ["N", 6, size, size])],
        [helper.make_tensor_value_info("fields", TensorProto.FLOAT, ["N", len(CHANNELS), size, size])],
        inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return model


def param_count(model) -> int:
    return int(sum(np.prod(t.dims) for t in model.graph.initializer))


def quantize_int8(fp32_path: Path, int8_path: Path, size: int, n_calib: int = 8, seed: int = 0) -> None:
    """Static QDQ int8: uint8 activations, per-channel int8 weights (DESIGN §10's fastest setting)."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    rng = np.random.default_rng(seed)

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.items = iter([{"input": _structured_input(rng, size)} for _ in range(n_calib)])

        def get_next(self):
            return next(self.items, None)

    quantize_static(str(fp32_path), str(int8_path), Reader(), quant_format=QuantFormat.QDQ,
                    activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True)


def _structured_input(rng, size: int) -> np.ndarray:
    """Baseline + current image with a smooth blob, like a poke on the gel."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    base = 0.5 + 0.2 * np.sin(8 * xx)[None] * np.ones((3, 1, 1))
    cx, cy = rng.uniform(0.3, 0.7, 2)
    blob = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 0.01)
    cur = base + 0.2 * blob[None]
    return np.concatenate([base, cur])[None].astype(np.float32)


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def write_package(folder: Path, size: int = 32, width: int = 4, depth: int = 2, seed: int = 0,
                  bounds: dict | None = None, int8: bool = True, stem: int = 1) -> Path:
    """A complete synthetic model package (manifest + fp32 [+ int8]) in `folder` (a temp dir)."""
    import onnx

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    model = build_unet(size, width, depth, seed, stem)
    fp32 = folder / "model.fp32.onnx"
    onnx.save(model, str(fp32))
    files = {"model.fp32.onnx": {"sha256": sha256(fp32)}}
    if int8:
        int8_path = folder / "model.int8.onnx"
        quantize_int8(fp32, int8_path, size)
        files["model.int8.onnx"] = {"sha256": sha256(int8_path)}
    if bounds is None:
        bounds = {c: ([-1.0, 1.0] if u == "mm" else [-0.05, 0.05]) for c, u in zip(CHANNELS, CHANNEL_UNITS)}
    manifest = {
        "schema": "tensortouch.model", "schema_version": 1, "name": f"synthetic-unet-{size}",
        "created": "synthetic", "synthetic": True,
        "input": {"name": "input", "layout": "NCHW", "size": [size, size], "dtype": "float32",
                  "channels": list(INPUT_CHANNELS), "range": [0.0, 1.0]},
        "output": {"name": "fields", "layout": "NCHW", "size": [size, size], "channels": list(CHANNELS),
                   "units": list(CHANNEL_UNITS), "normalization": "minmax", "bounds": bounds},
        "files": files,
        "training": {"command": "tools.bench.models.write_package (synthetic, untrained)", "data_hash": None},
        "metrics": {"params": param_count(model)},
    }
    (folder / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return folder


def build_difference_model(size: int, gain: float = 4.0):
    """A deterministic, physics-free test network: contact normal traction fn_z = −gain·|current −
    baseline| (mean over RGB, clipped at 1), every other channel 0. Outputs are normalized for the
    bounds of `difference_bounds()`; used by integration tests to put contacts where frames change."""
    from onnx import TensorProto, helper, numpy_helper

    n = len(CHANNELS)
    k = CHANNELS.index("fn_z")
    consts = {
        "s0": np.array([0], np.int64), "s3": np.array([3], np.int64), "s6": np.array([6], np.int64),
        "ax1": np.array([1], np.int64), "gain": np.array(gain, np.float32), "one": np.array(1.0, np.float32),
        "zero": np.array(0.0, np.float32),
    }
    nodes = [
        helper.make_node("Slice", ["input", "s0", "s3", "ax1"], ["base"]),
        helper.make_node("Slice", ["input", "s3", "s6", "ax1"], ["cur"]),
        helper.make_node("Sub", ["cur", "base"], ["diff"]),
        helper.make_node("Abs", ["diff"], ["adiff"]),
        helper.make_node("ReduceMean", ["adiff"], ["mdiff"], axes=[1], keepdims=1),
        helper.make_node("Mul", ["mdiff", "gain"], ["scaled"]),
        helper.make_node("Clip", ["scaled", "zero", "one"], ["d"]),
        helper.make_node("Sub", ["one", "d"], ["y_fnz"]),           # bounds [-1, 0]: y = 1 - d
        helper.make_node("Mul", ["mdiff", "zero"], ["z"]),
        helper.make_node("Add", ["z", "one"], ["ones"]),
        helper.make_node("Mul", ["ones", "half"], ["halfmap"]),     # symmetric bounds: 0 ↦ y = 0.5
    ]
    consts["half"] = np.array(0.5, np.float32)
    parts = ["halfmap"] * k + ["y_fnz"] + ["halfmap"] * (n - k - 1)
    nodes.append(helper.make_node("Concat", parts, ["fields"], axis=1))
    graph = helper.make_graph(
        nodes, "difference_model",
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, ["N", 6, size, size])],
        [helper.make_tensor_value_info("fields", TensorProto.FLOAT, ["N", n, size, size])],
        [numpy_helper.from_array(v, name) for name, v in consts.items()])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return model


def difference_bounds(traction_mpa: float = 0.02) -> dict:
    b = {c: [-1.0, 1.0] for c in CHANNELS}
    b["fn_z"] = [-traction_mpa, 0.0]
    return b


def write_difference_package(folder: Path, size: int = 32, traction_mpa: float = 0.02, gain: float = 4.0) -> Path:
    """Model package around `build_difference_model` (fp32 file used for both precisions)."""
    import onnx

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    onnx.save(build_difference_model(size, gain), str(folder / "model.fp32.onnx"))
    onnx.save(build_difference_model(size, gain), str(folder / "model.int8.onnx"))
    files = {n: {"sha256": sha256(folder / n)} for n in ("model.fp32.onnx", "model.int8.onnx")}
    manifest = {
        "schema": "tensortouch.model", "schema_version": 1, "name": f"difference-{size}", "synthetic": True,
        "input": {"name": "input", "layout": "NCHW", "size": [size, size], "dtype": "float32",
                  "channels": list(INPUT_CHANNELS), "range": [0.0, 1.0]},
        "output": {"name": "fields", "layout": "NCHW", "size": [size, size], "channels": list(CHANNELS),
                   "units": list(CHANNEL_UNITS), "normalization": "minmax",
                   "bounds": difference_bounds(traction_mpa)},
        "files": files,
        "training": {"command": "tools.bench.models.write_difference_package (test network, not trained)"},
        "metrics": {},
    }
    (folder / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return folder
