"""Training loops: MAE pretraining of the Hiera encoder and supervised fitting (seed §III.J, §IV-C).

L1 loss, AdamW (lr 1e-3), linear warmup then cosine decay; progress lines with samples/s and ETA;
checkpoint (atomic) every `checkpoint_every_s` and at each epoch end; an interrupted run resumes from
`checkpoint.pt` (same epoch order: each epoch's permutation is seeded by (seed, epoch)); the best
validation weights are kept in `best.pt`. A run directory holds:

  config.json  train_config.json  checkpoint.pt  best.pt  history.jsonl  metrics.json        (fit)
  config.json  train_config.json  checkpoint.pt  encoder.pt  history.jsonl                   (pretrain)

config.json is what a resume must match (no device); train_config.json (also inside every checkpoint.pt)
is the full config with the places the run trained in — device, precision, torch version, threads
(`run_place`, `train_config`).
"""
from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ....contracts.files import atomic_write, atomic_write_json
from . import build_model
from .data import DatasetError, load_measured, load_split, read_index, stacked_split
from .device import Precision, cpu_state, resolve_device
from .metrics import evaluate

log = logging.getLogger(__name__)


@dataclass
class LoopConfig:
    """The training loop both runs share (`_loop`): seed §IV-C setup as defaults (AdamW, lr 1e-3, warmup then
    cosine decay), epochs and batch scaled to a 2-core CPU."""

    epochs: int = 20
    batch_size: int = 16
    lr: float = 1e-3
    weight_decay: float = 0.05
    warmup_steps: int = 500              # seed: 500 warmup steps ...
    warmup_max_fraction: float = 0.1     # ... but at most this fraction of a short run
    threads: int = 2
    seed: int = 0
    checkpoint_every_s: float = 120.0
    log_every: int = 10
    device: str = "auto"                 # auto | cpu | cuda (tools.train.model.device); not part of config.json
    amp: bool = True                     # mixed precision (float16 autocast + grad scaling) on CUDA only


@dataclass
class FitConfig(LoopConfig):
    """Supervised fit of the fields (seed §IV-C); the loss terms beyond plain L1 are off by default."""

    arch: str = "hiera_qup"
    eval_batch: int = 16
    # Extra L1 weight on pixels whose target is away from the channel's zero level (contact fields are
    # sparse: with plain L1 a short CPU run collapses to the background). 0 = plain L1 (seed).
    fg_weight: float = 0.0
    fg_eps: float = 0.005                # |y − y(0)| above this (normalized units) counts as foreground
    # Total-force term: weight (per N) of |Σ_pixels (pred − target)·pixel_area| of the contact channels
    # (fn + fs, physical units via the bounds; the dataset's pixel_area.npy), i.e. the error of the force
    # the runtime integrates. 0 = off. Needs pixel_area.npy in the dataset directory.
    force_weight: float = 0.0
    # Light-contact emphasis: a sample whose target contact force |F| (N, from the fields as the runtime
    # integrates them) is at least light_min_n weighs clip((light_ref_n / |F|)^light_weight, 1, light_max),
    # so a 0.3 N touch is not learnt as "rest" beside 5 N presses. 0 = off (every sample weighs 1).
    light_weight: float = 0.0
    # Per-pixel force term: weight (per N) of Σ_pixels max(0, |ΔF_pixel| − pixel_force_tol_n), the force error of
    # single pixels beyond a tolerance below the runtime's cluster threshold (≈ 0.0015 N per pixel). L1 over
    # the fields tolerates a few badly wrong pixels (at the crop's rim, say) that the contact stage reads as a
    # cluster core on every rest frame. 0 = off. Needs pixel_area.npy, as force_weight.
    pixel_force_weight: float = 0.0
    pixel_force_tol_n: float = 0.0005
    # Measured-force term: weight (per N) of |Σ_pixels pred·pixel_area − F_measured|, the predicted total contact
    # force (fn + fs, as the runtime integrates it) against what the rig's F/T sensors read at the sample's frame
    # (the dataset's `force_n`, tools/train/distill.py). A distilled student otherwise learns the teacher's force
    # errors along with its fields. 0 = off. Needs pixel_area.npy and `force_n` on every sample.
    measured_force_weight: float = 0.0
    # ... split at two contacts: where a sample holds two indenters' measured forces and pixels (`contacts_n`),
    # the term is Σ_k |Σ_pixels nearer contact k's pixel than the other's − F_k| instead of the total's error
    # (measured_force_split_error). Needs measured_force_weight > 0.
    measured_force_split: bool = False
    light_ref_n: float = 1.0
    light_max: float = 3.0
    light_min_n: float = 0.05
    init_from: str = ""                  # fine-tune: start from this state dict (e.g. a shipped run's best.pt)
    # the output bounds `init_from` was trained with: a bounds.json or a model package's manifest.json;
    # default: the bounds.json a fit writes beside its best.pt. When they differ from this dataset's,
    # the heads are rescaled so the fine-tune starts at the init's physical output (remap_heads).
    init_bounds: str = ""
    # Photometric jitter of the inputs: per sample, a gain per colour U(1 − p, 1 + p) and a linear brightness
    # ramp of amplitude U(0, p) in a random direction, the same on the baseline and the current frame (units
    # differ in LED brightness, ±10 % per LED in the twin). 0 = off.
    photometric: float = 0.0
    # Crop jitter of input and target alike: per sample, the crop circle's radius × U(1 − s, 1 + s) and its centre
    # moved by U(−c, c) of the radius in x and y (a unit's rim and centre as a rig would misjudge them; the
    # fields are per area, so the same warp of the targets is what the labels at that crop would be). 0 = off.
    crop_scale_jitter: float = 0.0
    crop_shift: float = 0.0


@dataclass
class PretrainConfig(LoopConfig):
    """MAE pretraining of the Hiera encoder (seed §III.J)."""

    epochs: int = 10
    mask_ratio: float = 0.75             # seed: 75 % of the 6-channel input patches are masked
    decoder_dim: int = 64
    decoder_depth: int = 2


RUN_PLACE_KEYS = ("device", "amp")   # where a run executes: left out of config.json, a run resumes anywhere


def lr_at(step: int, total: int, base: float, warmup_steps: int, warmup_max_fraction: float) -> float:
    """Linear warmup to `base`, then cosine decay to 0 at `total`."""
    warm = max(1, min(warmup_steps, int(warmup_max_fraction * total)))
    if step < warm:
        return base * (step + 1) / warm
    progress = min(1.0, (step - warm) / max(1, total - warm))
    return base * 0.5 * (1 + math.cos(math.pi * progress))




def _prepare_run(out: Path, config: dict) -> dict | None:
    """Create the run dir; refuse to resume a run made with a different config; return the checkpoint."""
    out.mkdir(parents=True, exist_ok=True)
    cfg_path, ckpt_path = out / "config.json", out / "checkpoint.pt"
    if cfg_path.exists():
        old = json.loads(cfg_path.read_text())
        if ckpt_path.exists() and old != config:
            diff = sorted(k for k in set(old) | set(config) if old.get(k) != config.get(k))
            raise DatasetError(f"{cfg_path}: run exists with a different configuration ({diff}); "
                               "use a new --out or delete the run")
    atomic_write_json(cfg_path, config)
    if ckpt_path.exists():
        return torch.load(ckpt_path, weights_only=False, map_location="cpu")
    return None


class _Progress:
    def __init__(self, total_steps: int, batch: int, every: int, what: str):
        self.total, self.batch, self.every, self.what = total_steps, batch, every, what
        self.t0, self.n0 = time.monotonic(), 0

    def start(self, step: int):
        self.t0, self.n0 = time.monotonic(), step

    def rate(self, step: int) -> float:
        return (step - self.n0) * self.batch / max(1e-9, time.monotonic() - self.t0)

    def tick(self, step: int, epoch: int, loss: float, lr: float):
        if step % self.every == 0 or step == self.total:
            r = self.rate(step)
            eta = (self.total - step) * self.batch / max(r, 1e-9)
            log.info("%s step %d/%d epoch %d loss %.5f lr %.2e  %.1f samples/s  eta %.0f s",
                     self.what, step, self.total, epoch, loss, lr, r, eta)


def _batches(n: int, batch: int, seed: int, epoch: int) -> list[np.ndarray]:
    perm = np.random.default_rng([seed, epoch]).permutation(n)
    return [perm[i:i + batch] for i in range(0, n - batch + 1 if n >= batch else 1, batch)]


def run_place(device: torch.device, precision: Precision, model: torch.nn.Module) -> dict:
    """Where and how a run executes — the things that change its weights but not its config.json:
    device, precision, parameter dtype, torch (and CUDA) version, CPU threads."""
    import platform

    cuda = device.type == "cuda"
    return {"device": str(device),
            "device_name": torch.cuda.get_device_name(device) if cuda else (platform.processor() or platform.machine()),
            "precision": "float16 autocast + grad scaling" if precision.enabled else "float32",
            "param_dtype": str(next(model.parameters()).dtype).removeprefix("torch."),
            "torch": torch.__version__, "cuda": torch.version.cuda if cuda else None,
            "threads": torch.get_num_threads(),
            "deterministic_algorithms": torch.are_deterministic_algorithms_enabled()}


def train_config(cfg: LoopConfig, what: str, previous: dict | None, place: dict, step: int, **more) -> dict:
    """The run's full train config (every LoopConfig field, device and amp included) with the run places
    it trained in: `segments` = [{from_step, **run_place}], one more whenever a run resumes elsewhere.
    Saved in every checkpoint and as train_config.json beside it (as LeRobot keeps its train_config.json
    with each checkpoint); the package manifest copies the segments (training.run_place)."""
    segments = list((previous or {}).get("segments", []))
    if not segments or {k: v for k, v in segments[-1].items() if k != "from_step"} != place:
        segments.append({"from_step": int(step), **place})
    return {"what": what, "config": asdict(cfg), **more, "segments": segments}


def _loop(out: Path, model, loss_fn, x_all: np.ndarray, y_all, cfg: LoopConfig, what: str, on_epoch=None,
          state_extra=None, config_extra: dict | None = None, aux_all: np.ndarray | None = None) -> dict:
    """Shared epoch/step loop with checkpoint + resume. loss_fn(model, xb, yb) -> scalar tensor, or
    loss_fn(model, xb, yb, aux) with `aux_all` (N, ...) per-sample values batched alongside."""
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    device = resolve_device(cfg.device)
    precision = Precision(device, cfg.amp)
    model.to(device)
    channels_last = bool(getattr(model, "channels_last", False))     # convnet: ×1.35 per step on the CPU (measured)
    if channels_last:
        model.to(memory_format=torch.channels_last)
    log.info("%s on %s%s", what, device, " with mixed precision (float16 autocast)" if precision.enabled else "")
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    n = x_all.shape[0]
    per_epoch = len(_batches(n, cfg.batch_size, cfg.seed, 0))
    total = per_epoch * cfg.epochs
    config = {"what": what, **asdict(cfg), "n_train": n}
    for k in RUN_PLACE_KEYS:
        config.pop(k, None)
    for k in ("init_bounds", "photometric", "crop_scale_jitter", "crop_shift", "measured_force_weight", "measured_force_split"):   # runs made before these options existed resume unchanged
        if k in config and not config[k]:
            config.pop(k)
    ckpt = _prepare_run(out, config)
    step, epoch0, batch0, extra = 0, 0, 0, dict(state_extra or {})
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        step, epoch0, batch0, extra = ckpt["step"], ckpt["epoch"], ckpt["batch"], ckpt.get("extra", extra)
        torch.set_rng_state(ckpt["torch_rng"])
        precision.load_state_dict(ckpt.get("grad_scaler", {}))
        log.info("%s: resuming %s at step %d (epoch %d, batch %d)", what, out, step, epoch0, batch0)
    tconf = train_config(cfg, what, None if ckpt is None else ckpt.get("train_config"),
                         run_place(device, precision, model), step, **(config_extra or {}))
    atomic_write_json(out / "train_config.json", tconf)
    prog = _Progress(total, cfg.batch_size, cfg.log_every, what)
    prog.start(step)
    last_ckpt = time.monotonic()
    hist = open(out / "history.jsonl", "a")

    def save(epoch: int, batch: int):
        save_state({"model": cpu_state(model), "optimizer": opt.state_dict(), "step": step,
                      "epoch": epoch, "batch": batch, "extra": extra, "torch_rng": torch.get_rng_state(),
                      "grad_scaler": precision.state_dict(), "train_config": tconf},
                     out / "checkpoint.pt")

    for epoch in range(epoch0, cfg.epochs):
        model.train()
        batches = _batches(n, cfg.batch_size, cfg.seed, epoch)
        losses = []
        for b, idx in enumerate(batches):
            if epoch == epoch0 and b < batch0:
                continue
            lr = lr_at(step, total, cfg.lr, cfg.warmup_steps, cfg.warmup_max_fraction)
            for g in opt.param_groups:
                g["lr"] = lr
            xb = torch.from_numpy(x_all[idx].astype(np.float32) / 255.0).to(device)
            if channels_last:
                xb = xb.contiguous(memory_format=torch.channels_last)
            yb = None if y_all is None else torch.from_numpy(np.asarray(y_all[idx], dtype=np.float32)).to(device)
            opt.zero_grad(set_to_none=True)
            with precision.autocast():
                if aux_all is None:
                    loss = loss_fn(model, xb, yb)
                else:
                    loss = loss_fn(model, xb, yb, torch.from_numpy(np.asarray(aux_all[idx], np.float32)).to(device))
            precision.step(loss.float(), opt)
            step += 1
            losses.append(loss.item())
            prog.tick(step, epoch, losses[-1], lr)
            if time.monotonic() - last_ckpt > cfg.checkpoint_every_s:
                save(epoch, b + 1)
                last_ckpt = time.monotonic()
        record = {"epoch": epoch, "step": step, "train_loss": float(np.mean(losses)) if losses else None,
                  "samples_per_s": prog.rate(step)}
        if on_epoch is not None:
            record.update(on_epoch(epoch, extra))
        hist.write(json.dumps(record) + "\n")
        hist.flush()
        save(epoch + 1, 0)
        last_ckpt = time.monotonic()
    hist.close()
    extra["samples_per_s"] = prog.rate(step) if step > prog.n0 else extra.get("samples_per_s")
    extra["steps"] = step
    return extra


def load_any_bounds(path: str | Path) -> dict[str, list[float]]:
    """Output bounds from a bounds.json or from a model package's manifest.json (output.bounds)."""
    from ..fields import read_bounds

    path = Path(path)
    if path.is_dir():
        path = path / "manifest.json"
    if path.name != "manifest.json":
        return read_bounds(path)
    try:
        bounds = json.loads(path.read_text())["output"]["bounds"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{path}: no output.bounds in this model manifest ({exc})") from None
    from ....contracts.fields import CHANNELS

    missing = [c for c in CHANNELS if c not in bounds]
    if missing:
        raise DatasetError(f"{path}: output.bounds lacks channels {missing}")
    return {c: [float(bounds[c][0]), float(bounds[c][1])] for c in CHANNELS}


def head_remap(old: dict, new: dict) -> tuple[np.ndarray, np.ndarray]:
    """(scale, offset) per channel that turn outputs normalized with `old` bounds into the same physical
    values normalized with `new`: y_new = (lo_o − lo_n + span_o · y_old) / span_n."""
    from ....contracts.fields import CHANNELS

    lo_o, hi_o = (np.array([old[c][i] for c in CHANNELS], np.float64) for i in (0, 1))
    lo_n, hi_n = (np.array([new[c][i] for c in CHANNELS], np.float64) for i in (0, 1))
    span_o = np.where(hi_o > lo_o, hi_o - lo_o, 1.0)
    span_n = np.where(hi_n > lo_n, hi_n - lo_n, 1.0)
    return span_o / span_n, (lo_o - lo_n) / span_n


def remap_heads(model, cfg: FitConfig, bounds: dict) -> bool:
    """Rescale the heads of a model initialised from `cfg.init_from` to this dataset's `bounds`
    (FitConfig.init_bounds); True when they were changed."""
    path = Path(cfg.init_bounds) if cfg.init_bounds else Path(cfg.init_from).parent / "bounds.json"
    if not path.exists():
        if cfg.init_bounds:
            raise DatasetError(f"init_bounds {path}: no such file (a bounds.json or a model manifest.json)")
        log.warning("%s: no bounds.json beside the init weights; the heads are not rescaled (if its dataset had "
                    "other bounds, pass FitConfig.init_bounds / --init-bounds)", cfg.init_from)
        return False
    old = load_any_bounds(path)
    scale, offset = head_remap(old, bounds)
    if np.allclose(scale, 1.0) and np.allclose(offset, 0.0):
        return False
    model.heads.remap_output(torch.from_numpy(scale).float(), torch.from_numpy(offset).float())
    log.info("heads rescaled from the init's bounds (%s) to this dataset's: scale %.3f..%.3f, offset %+.3f..%+.3f",
             path, scale.min(), scale.max(), offset.min(), offset.max())
    return True


def predict(model, x_uint8: np.ndarray, batch: int = 16) -> np.ndarray:
    """Model outputs (N, 15, H, W) float32 for uint8 inputs (N, 6, H, W)."""
    model.eval()
    device = next(model.parameters()).device
    outs = []
    with torch.no_grad():
        for i in range(0, x_uint8.shape[0], batch):
            xb = torch.from_numpy(x_uint8[i:i + batch].astype(np.float32) / 255.0).to(device)
            outs.append(model(xb).float().cpu().numpy())
    return np.concatenate(outs)


def fit(data: str | Path, out: str | Path, cfg: FitConfig = FitConfig(), encoder_init: str | Path | None = None
        ) -> dict:
    """Supervised training on a dataset directory; returns {'metrics', 'samples_per_s', ...}."""
    from ..fields import read_bounds, write_bounds

    data, out = Path(data), Path(out)
    index = read_index(data)
    size = int(index["size"][0])
    x_tr, y_tr = stacked_split(data, "train")
    try:
        x_va, y_va = load_split(data, "val")
    except DatasetError:
        x_va, y_va = x_tr[: cfg.eval_batch], y_tr[: cfg.eval_batch]
    bounds = read_bounds(data / "bounds.json")
    out.mkdir(parents=True, exist_ok=True)
    write_bounds(out / "bounds.json", bounds)       # what a later fine-tune from this run's best.pt needs
    torch.manual_seed(cfg.seed)
    model = build_model(cfg.arch, size)
    model.heads.set_output_bias(torch.from_numpy(np.asarray(y_tr.mean(axis=(0, 2, 3)))).float())
    if cfg.init_from and not (out / "checkpoint.pt").exists():
        model.load_state_dict(torch.load(cfg.init_from, weights_only=True, map_location="cpu"), strict=True)
        log.info("model initialised from %s (fine-tuning)", cfg.init_from)
        remap_heads(model, cfg, bounds)
    elif encoder_init is not None and not (out / "checkpoint.pt").exists():
        state = torch.load(encoder_init, weights_only=True, map_location="cpu")
        model.encoder.load_state_dict(state, strict=True)
        log.info("encoder initialised from %s", encoder_init)

    from ....contracts.fields import CHANNELS

    lo = np.array([bounds[c][0] for c in CHANNELS])
    hi = np.array([bounds[c][1] for c in CHANNELS])
    y_zero = torch.tensor(np.clip(-lo / np.where(hi > lo, hi - lo, 1.0), 0.0, 1.0),   # physical 0, normalized
                          dtype=torch.float32).view(1, -1, 1, 1)
    device = resolve_device(cfg.device)
    y_zero = y_zero.to(device)
    zero = y_zero if cfg.fg_weight > 0 else None

    force_scale = None
    if cfg.force_weight > 0 or cfg.light_weight > 0 or cfg.pixel_force_weight > 0 or cfg.measured_force_weight > 0:
        force_scale = _force_scale(data, bounds).to(device)
    if cfg.measured_force_split and cfg.measured_force_weight <= 0:
        raise DatasetError("measured_force_split needs measured_force_weight > 0 (the weight of the measured-force term)")
    measured = load_measured(data, "train", contacts=cfg.measured_force_split) if cfg.measured_force_weight > 0 else None
    if cfg.measured_force_weight > 0 and (cfg.crop_scale_jitter > 0 or cfg.crop_shift > 0):
        raise DatasetError("measured_force_weight with crop jitter: the jittered crop cuts off force the rig measured; "
                           "use one of them")

    def loss_fn(m, xb, yb, measured_b=None):
        if cfg.photometric > 0:
            xb = photometric_jitter(xb, cfg.photometric)
        if cfg.crop_scale_jitter > 0 or cfg.crop_shift > 0:
            xb, yb = crop_jitter(xb, yb, y_zero, cfg.crop_scale_jitter, cfg.crop_shift)
        pred = m(xb).float()        # the loss in float32 also under CUDA autocast
        w = None if zero is None else 1.0 + cfg.fg_weight * (torch.abs(yb - zero) > cfg.fg_eps).float()
        if cfg.light_weight > 0:
            s = light_sample_weight(yb, y_zero, force_scale, cfg).view(-1, 1, 1, 1)
            w = s.expand_as(yb) if w is None else w * s
        if w is None:
            loss = torch.nn.functional.l1_loss(pred, yb)
        else:
            loss = (w * torch.abs(pred - yb)).sum() / w.sum()
        if cfg.force_weight > 0:
            loss = loss + cfg.force_weight * total_force_error(pred, yb, force_scale).mean()
        if cfg.pixel_force_weight > 0:
            loss = loss + cfg.pixel_force_weight * pixel_force_excess(pred, yb, force_scale, cfg.pixel_force_tol_n).mean()
        if measured_b is not None:
            term = measured_force_split_error if cfg.measured_force_split else measured_force_error
            loss = loss + cfg.measured_force_weight * term(pred, y_zero, force_scale, measured_b).mean()
        return loss

    def on_epoch(epoch, extra):
        pred = predict(model, x_va, cfg.eval_batch)
        val = float(np.mean(np.abs(pred - y_va)))
        if val < extra.get("best_val", float("inf")):
            extra["best_val"] = val
            extra["best_epoch"] = epoch
            save_state(cpu_state(model), out / "best.pt")
        return {"val_l1": val}

    init = {}
    if cfg.init_from:
        init["init_from"] = {"path": str(cfg.init_from), "run": _run_train_config(Path(cfg.init_from).parent)}
    elif encoder_init is not None:
        init["encoder_init"] = {"path": str(encoder_init), "run": _run_train_config(Path(encoder_init).parent)}
    extra = _loop(out, model, loss_fn, x_tr, y_tr, cfg, "fit", on_epoch, config_extra=init, aux_all=measured)
    del x_tr, y_tr     # the training split's memory maps; the final evaluation reads the validation split
    model.load_state_dict(torch.load(out / "best.pt", weights_only=True, map_location="cpu"))
    metrics = evaluate(predict(model, x_va, cfg.eval_batch), y_va, bounds)
    result = {"arch": cfg.arch, "image_size": size, "params": sum(p.numel() for p in model.parameters()),
              "metrics": metrics, "val_samples": int(x_va.shape[0]), **extra}
    atomic_write_json(out / "metrics.json", result)
    return result


def _run_train_config(run: Path) -> dict | None:
    """A run folder's train_config.json (None for runs made before it was written)."""
    try:
        return json.loads((run / "train_config.json").read_text())
    except (OSError, ValueError):
        return None


def run_places(run: str | Path) -> dict:
    """{"fit": segments[, "pretrain": segments | "init": segments]} of a fit run and the run its weights
    started from, for the package manifest (training.run_place); {} for runs without train_config.json."""
    tc = _run_train_config(Path(run))
    if tc is None:
        return {}
    out = {tc.get("what", "fit"): tc.get("segments", [])}
    for key, name in (("encoder_init", "pretrain"), ("init_from", "init")):
        start = (tc.get(key) or {}).get("run")
        if start:
            out[name] = start.get("segments", [])
    return out


def _force_scale(data: Path, bounds: dict) -> torch.Tensor:
    """(6, H, W) tensor: channel span (MPa per normalized unit) × pixel area (mm²) of the contact channels
    (fn_x … fs_z), so Σ_pixels Δy·scale is a force in N."""
    from ....contracts.fields import CHANNELS

    path = data / "pixel_area.npy"
    if not path.is_file():
        raise DatasetError(f"{path}: missing; force_weight, light_weight or pixel_force_weight > 0 needs the dataset's mean pixel area (mm², (H, W))")
    area = np.load(path).astype(np.float32)
    span = np.array([bounds[c][1] - bounds[c][0] for c in CHANNELS[9:15]], np.float32)
    return torch.from_numpy(span[:, None, None] * area[None])


def photometric_jitter(x: torch.Tensor, p: float) -> torch.Tensor:
    """(B, 6, H, W) inputs in [0, 1] (baseline RGB, current RGB) → the same scenes under other LEDs: per sample a
    gain per colour U(1 − p, 1 + p) times 1 + a·(cos β·u + sin β·v) (u, v ∈ [−1, 1] across the image, a ~ U(0, p),
    β ~ U(0, 2π)), applied alike to both frames, clipped to [0, 1]. Draws from torch's global generator (its
    state is in the checkpoint, so a resumed fit draws the same)."""
    if x.ndim != 4 or x.shape[1] != 6:
        raise ValueError(f"photometric_jitter: expected (B, 6, H, W) inputs, got {tuple(x.shape)}")
    B, _, H, W = x.shape
    gain = 1.0 + p * (2.0 * torch.rand(B, 3, 1, 1, device=x.device) - 1.0)
    a = p * torch.rand(B, 1, 1, 1, device=x.device)
    beta = 2.0 * np.pi * torch.rand(B, 1, 1, 1, device=x.device)
    v = torch.linspace(-1.0, 1.0, H, device=x.device).view(1, 1, H, 1)
    u = torch.linspace(-1.0, 1.0, W, device=x.device).view(1, 1, 1, W)
    g = gain * (1.0 + a * (torch.cos(beta) * u + torch.sin(beta) * v))
    return (x * g.repeat(1, 2, 1, 1)).clamp(0.0, 1.0)


def crop_affine(scale: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """(B, 2, 3) affine_grid matrices of crops whose circle has radius `scale` (B,) and centre `shift` (B, 2), both
    in units of the calibrated crop's radius (normalized image coordinates, x then y): output pixel p samples
    the calibrated crop at scale·p + shift."""
    if scale.ndim != 1 or shift.shape != (scale.shape[0], 2):
        raise ValueError(f"crop_affine: expected scale (B,) and shift (B, 2), got {tuple(scale.shape)}, {tuple(shift.shape)}")
    theta = torch.zeros(scale.shape[0], 2, 3, dtype=scale.dtype, device=scale.device)
    theta[:, 0, 0] = scale
    theta[:, 1, 1] = scale
    theta[:, :, 2] = shift
    return theta


def warp_crop(x: torch.Tensor, y: torch.Tensor, y_zero: torch.Tensor, scale: torch.Tensor, shift: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Inputs (B, 6, H, W) and normalized targets (B, C, H, W) of each sample's calibrated crop, seen through the
    crop circle of radius `scale` (B,) and centre `shift` (B, 2) radii (`crop_affine`). Both are resampled
    bilinearly by the same warp; the inputs are masked outside the new crop's circle as the runtime's
    Preprocessor masks them, the targets read the physical zero `y_zero` (1, C, 1, 1) where the calibrated
    crop saw nothing."""
    if x.ndim != 4 or x.shape[1] != 6 or y.ndim != 4 or y.shape[0] != x.shape[0] or y.shape[2:] != x.shape[2:]:
        raise ValueError(f"warp_crop: expected inputs (B, 6, H, W) and targets (B, C, H, W), got "
                         f"{tuple(x.shape)}, {tuple(y.shape)}")
    if y_zero.shape != (1, y.shape[1], 1, 1):
        raise ValueError(f"warp_crop: y_zero {tuple(y_zero.shape)}, expected (1, {y.shape[1]}, 1, 1)")
    B, _, H, W = x.shape
    grid = torch.nn.functional.affine_grid(crop_affine(scale, shift).to(x.dtype), [B, 1, H, W], align_corners=False)
    xo = torch.nn.functional.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    v = torch.linspace(-1.0 + 1.0 / H, 1.0 - 1.0 / H, H, device=x.device).view(1, 1, H, 1)
    u = torch.linspace(-1.0 + 1.0 / W, 1.0 - 1.0 / W, W, device=x.device).view(1, 1, 1, W)
    xo = xo * ((u * u + v * v) <= 1.0).to(x.dtype)
    z = y_zero.to(y.dtype)
    yo = torch.nn.functional.grid_sample(y - z, grid.to(y.dtype), mode="bilinear", padding_mode="zeros",
                                         align_corners=False) + z
    return xo, yo


def crop_jitter(x: torch.Tensor, y: torch.Tensor, y_zero: torch.Tensor, s: float, c: float
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """`warp_crop` at a random crop per sample: radius × U(1 − s, 1 + s), centre + U(−c, c) radii in x and y.
    Draws from torch's global generator (its state is in the checkpoint, so a resumed fit draws the same)."""
    if not (0 <= s < 1 and 0 <= c < 1):
        raise ValueError(f"crop_jitter: scale jitter {s} and shift {c} must lie in [0, 1)")
    B = x.shape[0]
    scale = 1.0 + s * (2.0 * torch.rand(B, device=x.device) - 1.0)
    shift = c * (2.0 * torch.rand(B, 2, device=x.device) - 1.0)
    return warp_crop(x, y, y_zero, scale, shift)


def light_sample_weight(target: torch.Tensor, y_zero: torch.Tensor, scale: torch.Tensor, cfg) -> torch.Tensor:
    """(B,) per-sample loss weight of FitConfig.light_weight from normalized targets (B, 15, H, W):
    |F| = the total contact force the runtime integrates (N); 1 below cfg.light_min_n (rest) and for
    firm contacts, up to cfg.light_max for light ones."""
    with torch.no_grad():
        f = ((target[:, 9:15] - y_zero[:, 9:15]) * scale).sum(dim=(2, 3))
        mag = torch.linalg.vector_norm(f[:, :3] + f[:, 3:], dim=1)
        w = (cfg.light_ref_n / mag.clamp(min=1e-6)) ** cfg.light_weight
        return torch.where(mag >= cfg.light_min_n, w.clamp(1.0, cfg.light_max), torch.ones_like(w))


def total_force_error(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """(B,) |ΔF| in N: the error of the total contact force (normal + shear) the runtime integrates,
    from normalized predictions/targets (B, 15, H, W) and `_force_scale`."""
    return torch.linalg.vector_norm(_pixel_force_error(pred, target, scale).sum(dim=(2, 3)), dim=1)


def measured_force_error(pred: torch.Tensor, zero: torch.Tensor, scale: torch.Tensor, measured: torch.Tensor
                         ) -> torch.Tensor:
    """(B,) N: |Σ_pixels F_pixel − measured|, the predicted total contact force (normal + shear, as the
    runtime integrates it) against the rig's measured total force (B, 3) N, from normalized predictions
    (B, 15, H, W), the normalized physical zero (1, 15, 1, 1) and `_force_scale` (6, H, W)."""
    if pred.ndim != 4 or pred.shape[1] != 15 or measured.shape != (pred.shape[0], 3):
        raise ValueError(f"measured_force_error: expected (B, 15, H, W) pred and (B, 3) measured, got {tuple(pred.shape)} "
                         f"and {tuple(measured.shape)}")
    if scale.shape != (6, *pred.shape[2:]):
        raise ValueError(f"measured_force_error: expected a (6, {pred.shape[2]}, {pred.shape[3]}) scale, got {tuple(scale.shape)}")
    d = ((pred[:, 9:15] - zero[:, 9:15]) * scale).sum(dim=(2, 3))          # (B, 6) N per channel
    return torch.linalg.vector_norm(d[:, :3] + d[:, 3:] - measured, dim=1)


def measured_force_split_error(pred: torch.Tensor, zero: torch.Tensor, scale: torch.Tensor, measured: torch.Tensor
                               ) -> torch.Tensor:
    """(B,) N: `measured_force_error` where a sample has one contact; where two indenters press at once,
    Σ_k |Σ_{pixels nearer k} F_pixel − F_k|, each pixel going to the nearer of the two contacts' pixels (ties
    to the first). measured (B, 13): the total (3), then the two contacts' [fx, fy, fz, u, v] (u column, v row,
    model pixels), NaN in a sample without two."""
    if pred.ndim != 4 or pred.shape[1] != 15 or measured.shape != (pred.shape[0], 13):
        raise ValueError(f"measured_force_split_error: expected (B, 15, H, W) pred and (B, 13) measured, got "
                         f"{tuple(pred.shape)} and {tuple(measured.shape)}")
    if scale.shape != (6, *pred.shape[2:]):
        raise ValueError(f"measured_force_split_error: expected a (6, {pred.shape[2]}, {pred.shape[3]}) scale, got "
                         f"{tuple(scale.shape)}")
    d = (pred[:, 9:15] - zero[:, 9:15]) * scale
    f = d[:, :3] + d[:, 3:]                                                  # (B, 3, H, W) N per pixel
    total = f.sum(dim=(2, 3))
    err = torch.linalg.vector_norm(total - measured[:, :3], dim=1)
    two = torch.isfinite(measured[:, 3:]).all(dim=1)
    if not bool(two.any()):
        return err
    c = torch.nan_to_num(measured[:, 3:]).view(-1, 2, 5)
    v, u = torch.meshgrid(torch.arange(pred.shape[2], dtype=f.dtype, device=f.device),
                          torch.arange(pred.shape[3], dtype=f.dtype, device=f.device), indexing="ij")
    d0 = (u - c[:, 0, 3, None, None]) ** 2 + (v - c[:, 0, 4, None, None]) ** 2
    d1 = (u - c[:, 1, 3, None, None]) ** 2 + (v - c[:, 1, 4, None, None]) ** 2
    f0 = (f * (d0 <= d1).to(f.dtype)[:, None]).sum(dim=(2, 3))
    split = (torch.linalg.vector_norm(f0 - c[:, 0, :3], dim=1)
             + torch.linalg.vector_norm(total - f0 - c[:, 1, :3], dim=1))
    return torch.where(two, split, err)


def _pixel_force_error(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) N: each pixel's error of the contact force the runtime reads (fn + fs)."""
    d = (pred[:, 9:15] - target[:, 9:15]) * scale                            # (B, 6, H, W) N per channel
    return d[:, :3] + d[:, 3:]


def pixel_force_excess(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor, tol_n: float) -> torch.Tensor:
    """(B,) N: Σ over pixels of max(0, |ΔF_pixel| − tol_n), where ΔF_pixel is one pixel's error of the contact
    force (normal + shear, N) from normalized predictions/targets (B, 15, H, W) and `_force_scale` (6, H, W)."""
    if pred.shape != target.shape or pred.ndim != 4 or pred.shape[1] != 15:
        raise ValueError(f"pixel_force_excess: expected (B, 15, H, W) pred and target, got {tuple(pred.shape)} "
                         f"and {tuple(target.shape)}")
    if scale.shape != (6, *pred.shape[2:]):
        raise ValueError(f"pixel_force_excess: expected a (6, {pred.shape[2]}, {pred.shape[3]}) scale, got {tuple(scale.shape)}")
    err = torch.linalg.vector_norm(_pixel_force_error(pred, target, scale), dim=1)     # (B, H, W)
    return torch.relu(err - tol_n).sum(dim=(1, 2))


def pretrain(data: str | Path, out: str | Path, cfg: PretrainConfig = PretrainConfig()) -> dict:
    """MAE pretraining of the Hiera encoder on the 6-channel inputs; writes encoder.pt."""
    from .hiera import Hiera, HieraConfig, HieraMAE

    data, out = Path(data), Path(out)
    size = int(read_index(data)["size"][0])
    x_tr, _ = stacked_split(data, "train")        # self-supervised, but validation inputs stay unseen
    torch.manual_seed(cfg.seed)
    mae = HieraMAE(Hiera(HieraConfig(image_size=size)), cfg.decoder_dim, cfg.decoder_depth,
                   mask_ratio=cfg.mask_ratio)

    def loss_fn(m, xb, _):
        return m(xb)[0]

    extra = _loop(out, mae, loss_fn, x_tr, None, cfg, "pretrain")
    save_state(cpu_state(mae.encoder), out / "encoder.pt")
    return {"image_size": size, **extra}


def load_trained(run: str | Path):
    """(model in eval mode, metrics.json dict) of a finished fit run."""
    run = Path(run)
    info = json.loads((run / "metrics.json").read_text())
    model = build_model(info["arch"], info["image_size"])
    model.load_state_dict(torch.load(run / "best.pt", weights_only=True, map_location="cpu"))
    return model.eval(), info


def save_state(obj, path: Path) -> None:
    """torch.save, atomically (contracts.files)."""
    atomic_write(path, lambda fh: torch.save(obj, fh))
