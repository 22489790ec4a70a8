"""A model package's ONNX weights back into the training network, so a fine-tune can start from
what ships when the build cache that made it (`<run>/best.pt`) is gone.

    tensortouch train weights exported_models/hiera-qup-128 --out cache/train/from-package
    tensortouch train all ... --init-from cache/train/from-package/best.pt   # bounds.json beside it: heads rescaled

How the weights are found, without a hand-written name table:
1. A template network of the package's architecture and size gets a distinct integer id on every
   parameter element (4,000,000 + k: exact in float32, far from any value a graph constant takes).
2. The template goes through the same export-time rewrites and ONNX export as the package did
   (`export_onnx`). Every initializer of that graph whose elements are all ids (or the rewrites'
   structural zeros) says where each parameter element went (transposes, fused heads and the heads'
   ConvTranspose form included).
3. The package's graph has the same initializer names (same exporter, same architecture; the int8
   one adds `_quantized` / `_scale` / `_zero_point`). Its values -- fp32 as they are, int8 and int32
   dequantized, (q - zero_point) * scale, per channel along axis 0 where the scale is a vector -- are
   read back element by element into the parameters.
Every weight must be found, and where the graph holds it twice the copies must agree; else it raises.
From an int8 package the weights carry the int8 rounding (≤ half a quantization step per weight);
a fine-tune starts from there. Pure core: `dequantized`, `id_positions`, `assemble`.
"""
from __future__ import annotations

import copy
import logging
import tempfile
from pathlib import Path

import numpy as np

from ...contracts.errors import ModelPackageError
from ...contracts.files import atomic_write, atomic_write_json
from ...contracts.store import sha256_file
from .package import FP32, INT8

log = logging.getLogger(__name__)

ID0 = 4_000_000          # first parameter id; ids stay below 2**24 (exact in float32) for < 12.7 M params


def dequantized(inits: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """ONNX initializers by name → float64 values by the fp32 graph's names (quantized ones dequantized)."""
    out: dict[str, np.ndarray] = {}
    skip = set()
    for name, q in inits.items():
        if not name.endswith("_quantized"):
            continue
        base = name[: -len("_quantized")]
        sname = next((n for n in (name + "_scale", base + "_scale") if n in inits), None)
        if sname is None:
            raise ModelPackageError(f"initializer {name}: no {base}_scale or {name}_scale beside it")
        zname = sname[: -len("_scale")] + "_zero_point"
        scale = np.asarray(inits[sname], np.float64)
        zp = np.asarray(inits.get(zname, np.zeros_like(scale)), np.float64)
        if scale.ndim == 1 and q.ndim > 1:                       # per channel along axis 0
            shape = (-1,) + (1,) * (q.ndim - 1)
            scale, zp = scale.reshape(shape), zp.reshape(shape)
        out[base] = (np.asarray(q, np.float64) - zp) * scale
        skip.update((name, sname, zname))
    for name, v in inits.items():
        if name not in skip and name not in out and np.issubdtype(np.asarray(v).dtype, np.floating):
            out[name] = np.asarray(v, np.float64)
    return out


def id_positions(template_inits: dict[str, np.ndarray], n_ids: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """For each initializer made only of parameter ids (and zeros): (flat positions, ids) of its id elements."""
    out = {}
    for name, v in template_inits.items():
        v = np.asarray(v)
        if not np.issubdtype(v.dtype, np.floating) or v.size == 0:
            continue
        flat = v.astype(np.float64).ravel()
        is_id = (flat >= ID0) & (flat < ID0 + n_ids) & (flat == np.round(flat))
        if is_id.any() and np.all(is_id | (flat == 0.0)):
            pos = np.flatnonzero(is_id)
            out[name] = (pos, flat[pos].astype(np.int64) - ID0)
    return out


def assemble(positions: dict, values: dict[str, np.ndarray], n_ids: int, atol: float = 1e-6) -> np.ndarray:
    """The flat parameter vector (n_ids,) from the package's values at the template's id positions."""
    theta = np.full(n_ids, np.nan)
    for name, (pos, ids) in positions.items():
        if name not in values:
            raise ModelPackageError(f"the package's graph has no initializer {name!r} (a weight of the "
                                    "architecture): not the same architecture or exporter")
        v = values[name].ravel()
        if v.size <= pos.max():
            raise ModelPackageError(f"initializer {name!r} has {v.size} values, the architecture needs > {pos.max()}")
        got = v[pos]
        seen = ~np.isnan(theta[ids])
        if np.any(np.abs(theta[ids][seen] - got[seen]) > atol + 1e-3 * np.abs(got[seen])):
            raise ModelPackageError(f"initializer {name!r} disagrees with another copy of the same weights")
        theta[ids] = got
    if np.isnan(theta).any():
        raise ModelPackageError(f"{int(np.isnan(theta).sum())} of {n_ids} weights are not in the package's graph")
    return theta


def _initializers(path: Path) -> dict[str, np.ndarray]:
    import onnx
    from onnx import numpy_helper

    return {i.name: numpy_helper.to_array(i) for i in onnx.load(str(path)).graph.initializer}


def state_dict_from_package(folder: str | Path, precision: str = "best") -> tuple[dict, dict]:
    """(torch state dict of the training network, info) from a package folder; precision "best" reads
    the fp32 graph when the package ships it, else the int8 one."""
    import torch

    from ...runtime.stages.model import load_package
    from .model import build_model

    pkg = load_package(folder)
    man = pkg.manifest
    arch = (man.get("metrics") or {}).get("arch") or "hiera_qup"
    size = int(man["input"]["size"][0])
    files = man.get("files", {})
    files_of = {"fp32": FP32, "int8": INT8}
    if precision == "best":
        precision = "fp32" if (pkg.folder / FP32).is_file() else "int8"
    if precision not in files_of or not (pkg.folder / files_of[precision]).is_file():
        raise ModelPackageError(f"{pkg.folder}: no {files_of.get(precision, precision)} in this package")
    graph = pkg.folder / files_of[precision]

    model = build_model(arch, size)
    params = list(model.parameters())
    n_ids = sum(p.numel() for p in params)
    if ID0 + n_ids >= 2 ** 24:
        raise ModelPackageError(f"{arch}: {n_ids} parameters, too many for float32 ids")
    with torch.no_grad():
        k = ID0
        for p in params:
            p.copy_(torch.arange(k, k + p.numel(), dtype=torch.float64).reshape(p.shape).to(p.dtype))
            k += p.numel()
    values = dequantized(_initializers(graph))
    with tempfile.TemporaryDirectory() as tmp:
        # packages are exported with the rewrites (fused heads); a graph without them has the plain names
        use = _template_positions(model, size, n_ids, Path(tmp), rewrite=True)
        rewritten = all(n in values for n in use)
        if not rewritten:
            use = _template_positions(model, size, n_ids, Path(tmp), rewrite=False)
    theta = assemble(use, values, n_ids)
    state, k = {}, 0
    for name, p in model.named_parameters():
        state[name] = torch.from_numpy(theta[k:k + p.numel()].reshape(p.shape)).to(p.dtype)
        k += p.numel()
    info = {"package": str(pkg.folder), "file": graph.name, "precision": precision,
            "sha256": (files.get(graph.name) or {}).get("sha256") or sha256_file(graph), "arch": arch,
            "image_size": size, "params": n_ids, "rewritten_graph": rewritten}
    return state, info


def _template_positions(model, size: int, n_ids: int, tmp: Path, rewrite: bool) -> dict:
    """Id positions in the graph the export makes of the id-valued template (with or without the
    export_graph rewrites; the rewrites' numeric check is off: ids are not a network)."""
    from .export import export_onnx
    from .export_graph import RewriteConfig, reparametrize

    net = copy.deepcopy(model)
    if rewrite:
        net, _ = reparametrize(net, size, cfg=RewriteConfig(check_batch=0))
    path = tmp / f"template_{int(rewrite)}.onnx"
    export_onnx(net, path, size, rewrite=False)
    return id_positions(_initializers(path), n_ids)


def write_init(folder: str | Path, out: str | Path, precision: str = "best") -> Path:
    """out/best.pt (state dict) + out/bounds.json (the package's output bounds, so a fine-tune onto a
    dataset with other bounds rescales the heads) + out/from_package.json (provenance)."""
    import torch

    from .fields import write_bounds
    from .model.train import load_any_bounds

    state, info = state_dict_from_package(folder, precision)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / "best.pt", lambda fh: torch.save(state, fh))
    write_bounds(out / "bounds.json", load_any_bounds(Path(folder) / "manifest.json"))
    atomic_write_json(out / "from_package.json", info)
    log.info("weights of %s (%s) → %s", info["package"], info["file"], out / "best.pt")
    return out / "best.pt"
