"""Weight-space average of a fine-tuned network and the network it started from (WiSE-FT style).

A fine-tune on new data (e.g. slide-rich twin units) can drift on what the older data covered (other
units, light touches). Averaging its weights with its starting point, both in the fine-tune's output
frame, often keeps most of the gain and most of the robustness; `weight` is the fine-tune's share.

    python -m tools.train.average --tuned RUN --base STATE_DICT [--base-bounds FILE] --weight 0.5 --out RUN_OUT \
        [--export DATASET --models-dir DIR]

RUN is a fit run folder (best.pt, bounds.json, metrics.json); STATE_DICT a best.pt the fine-tune
started from (its bounds.json beside it, or --base-bounds: a bounds.json or a package manifest). The
base's heads are rescaled to RUN's bounds first (tools.train.model.train.head_remap). RUN_OUT is a run
folder like RUN (best.pt, bounds.json, metrics.json, config.json with the provenance); `--export` turns
it into a package with `tools.train.export.export_run` (the command is recorded in its manifest); its
contact threshold is then measured as after any export: `python -m tools.train.threshold --package DIR --write ...`.
"""
from __future__ import annotations

import argparse
import json
import logging
import shutil
from pathlib import Path

from ...contracts.store import sha256_file
from .model.data import DatasetError

log = logging.getLogger(__name__)


def average_states(tuned: dict, base: dict, weight: float) -> dict:
    """weight · tuned + (1 − weight) · base for floating tensors; integer buffers (BatchNorm counters)
    are the tuned network's. Both state dicts must have the same keys and shapes."""
    import torch

    if not 0.0 <= weight <= 1.0:
        raise DatasetError(f"average weight {weight}: expected 0..1 (the fine-tuned network's share)")
    if set(tuned) != set(base):
        diff = sorted(set(tuned) ^ set(base))[:5]
        raise DatasetError(f"the two networks differ in their parameters (e.g. {diff}): not the same architecture")
    out = {}
    for k, t in tuned.items():
        b = base[k]
        if t.shape != b.shape:
            raise DatasetError(f"parameter {k}: shape {tuple(t.shape)} vs {tuple(b.shape)}")
        out[k] = weight * t + (1.0 - weight) * b if torch.is_floating_point(t) else t.clone()
    return out


def average_run(tuned_run: Path, base_state: Path, weight: float, out: Path, base_bounds: Path | None = None) -> dict:
    """Write the averaged run folder `out`; returns its config.json dict."""
    import torch

    from .fields import read_bounds
    from .model import build_model
    from ...contracts.files import atomic_write_json
    from .model.train import FitConfig, remap_heads

    tuned_run, base_state, out = Path(tuned_run), Path(base_state), Path(out)
    for need in ("best.pt", "bounds.json", "metrics.json"):
        if not (tuned_run / need).is_file():
            raise DatasetError(f"{tuned_run}: no {need} (expected a finished fit run folder)")
    if not base_state.is_file():
        raise DatasetError(f"{base_state}: no such state dict")
    info = json.loads((tuned_run / "metrics.json").read_text())
    bounds = read_bounds(tuned_run / "bounds.json")
    base = build_model(info["arch"], info["image_size"])
    base.load_state_dict(torch.load(base_state, weights_only=True, map_location="cpu"), strict=True)
    remapped = remap_heads(base, FitConfig(init_from=str(base_state), init_bounds=str(base_bounds or "")), bounds)
    tuned = torch.load(tuned_run / "best.pt", weights_only=True, map_location="cpu")
    state = average_states(tuned, base.state_dict(), weight)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / ".best.pt.tmp"
    torch.save(state, tmp)
    tmp.replace(out / "best.pt")
    shutil.copyfile(tuned_run / "bounds.json", out / "bounds.json")
    cfg = {"what": "average", "weight": weight, "heads_rescaled": bool(remapped),
           "tuned": {"run": str(tuned_run), "best_sha256": sha256_file(tuned_run / "best.pt")},
           "base": {"state_dict": str(base_state), "sha256": sha256_file(base_state),
                    "bounds": str(base_bounds or base_state.parent / "bounds.json")}}
    atomic_write_json(out / "config.json", cfg)
    atomic_write_json(out / "metrics.json",
                      dict(info, metrics=None, note="weight average: validation metrics are the export's parity report"))
    log.info("averaged %s (%.2f) with %s -> %s", tuned_run, weight, base_state, out)
    return cfg


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tuned", required=True, help="the fine-tuned fit run folder")
    p.add_argument("--base", required=True, help="the state dict (best.pt) the fine-tune started from")
    p.add_argument("--base-bounds", help="the base's output bounds (default: bounds.json beside it)")
    p.add_argument("--weight", type=float, default=0.5, help="the fine-tuned network's share (0..1)")
    p.add_argument("--out", required=True, help="the averaged run folder to write")
    p.add_argument("--export", metavar="DATASET", help="also export it as a package from this dataset folder "
                                                     "(int8 quantization samples and the parity report)")
    p.add_argument("--name", default="hiera-qup-128", help="package name (with --export)")
    p.add_argument("--models-dir", help="package root (with --export; default exported_models/)")


def run(args: argparse.Namespace) -> int:
    from ...contracts.paths import models_dir
    from .export import ExportConfig, export_run

    average_run(Path(args.tuned), Path(args.base), args.weight, Path(args.out),
                Path(args.base_bounds) if args.base_bounds else None)
    if args.export:
        root = Path(args.models_dir) if args.models_dir else models_dir()
        cmd = args.command_line
        man = export_run(Path(args.out), Path(args.export), args.name, root, cmd, ExportConfig())
        m = man["metrics"]
        print(f"exported {root / args.name}: PSNR fp32 {m['fp32']['psnr']:.2f} dB, int8 {m['int8']['psnr']:.2f} dB")
    return 0

