"""Stage 5 of a distilled build (BuildConfig.teacher): training sessions' frames → the teacher package's
outputs as targets (docs/train.md "Distillation").

A student learns the teacher's function, not the FE labels, so a sample needs only a pair of frames
(baseline, current): the frames are those stage 5 would pick (`dataset.select_frames`), cropped through
the runtime's Preprocessor at the unit's calibrated rim and, `copies` more times, at a jittered rim
(radius × U(1 − s, 1 + s), centre ± c px: the spread of the protocol units' rims around the nominal
lens). The teacher labels every crop it is shown, so the jittered samples stay consistent; its outputs
are already min/max-normalized with its manifest's bounds, which become the dataset's bounds.

Each sample also keeps what the rig measured at its frame: the indenters' total force on the gel (F/T,
`measured_total`), which a fit can hold the student's total force to (FitConfig.measured_force_weight),
so it need not inherit the teacher's force errors. Where two indenters press at once the rig measures each
one's force apart (one F/T module per indenter), and a frame also keeps both, each at the model pixel nearest
its tip (`contact_pixels`), so a fit can hold the force on each side of the two contacts to each
(FitConfig.measured_force_split): the teacher splits two contacts' force wrongly, and a total holds only their sum.

Pure cores: `jittered_circles`, `teacher_targets`, `measured_total`, `contact_pixels`, `pixels_in_crop`. Shell:
`distill_session`, `write_distilled`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...contracts.errors import TensorTouchError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DistillConfig:
    copies: int = 0                   # jittered crops per frame beside the calibrated one
    scale_jitter: float = 0.04        # rim radius × U(1 − s, 1 + s)
    center_jitter_px: float = 1.0     # rim centre + U(−c, c) px in x and y
    seed: int = 0


def jittered_circles(cx: float, cy: float, r: float, n: int, cfg: DistillConfig, rng: np.random.Generator
                     ) -> np.ndarray:
    """(1 + n, 3) crop circles (cx, cy, radius): the calibrated one first, then n jittered ones."""
    if not (np.isfinite([cx, cy, r]).all() and r > 0):
        raise ValueError(f"jittered_circles: circle ({cx}, {cy}, {r}) must be finite with a positive radius")
    if n < 0:
        raise ValueError(f"jittered_circles: n = {n}; expected ≥ 0")
    out = np.empty((1 + n, 3))
    out[0] = cx, cy, r
    if n:
        out[1:, 0] = cx + rng.uniform(-cfg.center_jitter_px, cfg.center_jitter_px, n)
        out[1:, 1] = cy + rng.uniform(-cfg.center_jitter_px, cfg.center_jitter_px, n)
        out[1:, 2] = r * rng.uniform(1 - cfg.scale_jitter, 1 + cfg.scale_jitter, n)
    return out


def teacher_targets(run, inputs: np.ndarray) -> np.ndarray:
    """(N, 15, H, W) float32 teacher outputs for uint8 inputs (N, 6, H, W); `run` maps a float32 (1, 6, H, W)
    batch in [0, 1] to (1, 15, H, W) (e.g. an onnxruntime session's run)."""
    if inputs.dtype != np.uint8 or inputs.ndim != 4 or inputs.shape[1] != 6:
        raise ValueError(f"teacher_targets: expected uint8 (N, 6, H, W) inputs, got {inputs.dtype}{inputs.shape}")
    outs = [np.asarray(run(inputs[i:i + 1].astype(np.float32) / 255.0), np.float32) for i in range(len(inputs))]
    y = np.concatenate(outs) if outs else np.zeros((0, 15) + inputs.shape[2:], np.float32)
    if y.shape[0] != inputs.shape[0] or y.shape[2:] != inputs.shape[2:] or y.shape[1] != 15:
        raise ValueError(f"teacher_targets: teacher gave {y.shape} for inputs {inputs.shape}")
    return y


def measured_total(measured: dict[int, dict], frames: np.ndarray) -> np.ndarray:
    """(n, 3) N: the total force the indenters apply to the gel at `frames` (indices into the times
    `measured` was taken at), from `tools.scoring.measured_at`'s {id: {"force" (T, 3)}}: what the rig's
    F/T sensors read, summed, in the sensor frame and the runtime's sign."""
    frames = np.asarray(frames, int)
    if not measured:
        raise ValueError("measured_total: no indenter was measured")
    total = sum(np.asarray(v["force"], float) for v in measured.values())
    if total.ndim != 2 or total.shape[1] != 3:
        raise ValueError(f"measured_total: expected (T, 3) forces, got {total.shape}")
    if len(frames) and (frames.min() < 0 or frames.max() >= len(total)):
        raise ValueError(f"measured_total: frame indices {frames.min()}..{frames.max()} outside 0..{len(total) - 1}")
    return total[frames].astype(np.float32)


def contact_pixels(tips: np.ndarray, forces: np.ndarray, surface_xyz: np.ndarray, mask: np.ndarray,
                   active_n: float = 0.2, reach_mm: float = 3.0) -> np.ndarray:
    """(n, 2, 5) float32 [fx, fy, fz, u, v] per frame: the measured force (N) of each of the two indenters
    pressing at once, and the model pixel (u column, v row) of the masked gel surface point nearest its tip.
    tips, forces (n, K, 3) mm and N in the sensor frame; surface_xyz (S, S, 3) mm and mask (S, S) of the crop.
    An indenter presses when it carries ≥ `active_n` N (the scorer's contact level, 10× the F/T noise) with
    its tip within `reach_mm` of the surface; a frame where fewer or more than two press is all NaN (its
    total force holds)."""
    tips, forces = np.asarray(tips, float), np.asarray(forces, float)
    xyz, m = np.asarray(surface_xyz, float), np.asarray(mask, bool)
    if tips.ndim != 3 or tips.shape[2] != 3 or forces.shape != tips.shape:
        raise ValueError(f"contact_pixels: expected tips and forces (n, K, 3), got {tips.shape} and {forces.shape}")
    if xyz.ndim != 3 or xyz.shape[2] != 3 or m.shape != xyz.shape[:2]:
        raise ValueError(f"contact_pixels: expected surface_xyz (S, S, 3) and mask (S, S), got {xyz.shape} and {m.shape}")
    out = np.full((len(tips), 2, 5), np.nan, np.float32)
    if not m.any():
        return out
    rows, cols = np.nonzero(m)
    pts = xyz[rows, cols]
    for n in range(len(tips)):
        on = np.flatnonzero(np.linalg.norm(forces[n], axis=1) >= active_n)
        if len(on) != 2:
            continue
        dist = np.linalg.norm(pts[:, None, :] - tips[n, on][None], axis=2)      # (pixels, 2)
        near = dist.argmin(0)
        if (dist[near, [0, 1]] > reach_mm).any():
            continue
        for j, (k, i) in enumerate(zip(on, near)):
            out[n, j] = (*forces[n, k], cols[i], rows[i])
    return out


def pixels_in_crop(uv: np.ndarray, crop, other) -> np.ndarray:
    """(..., 2) model pixels (u, v) of the crop `crop` → the same raw image points in the crop `other` (two
    runtime.stages.preprocess.Preprocessor); NaN stays NaN."""
    uv = np.asarray(uv, float)
    if uv.shape[-1] != 2:
        raise ValueError(f"pixels_in_crop: expected (..., 2) pixels, got {uv.shape}")
    u, v = other.to_model(*crop.to_raw(uv[..., 0], uv[..., 1]))
    return np.stack([u, v], axis=-1)


def distill_session(session_dir: Path, calibration, run, cfg: DistillConfig, select_cfg, progress=None,
                    contacts: bool = False) -> dict:
    """One session's samples: {'input' (n,6,S,S) u8, 'target' (n,15,S,S) normalized, 'frame', 'baseline',
    'poke', 'copy' (n,), 'force_n' (n, 3): the rig's measured total force at the frame (`measured_total`)
    [, with `contacts`: 'contacts_n' (n, 2, 5), `contact_pixels` in each sample's own crop]}; frames picked by
    `dataset.select_frames(select_cfg)` from truth/frames.csv."""
    import cv2

    from ...contracts.session import load_session, read_table
    from ...runtime.stages.preprocess import Preprocessor
    from ..scoring import measured_at
    from ..sessions.writer import read_frames
    from .dataset import select_frames

    ses = load_session(session_dir)
    fr = read_table(Path(session_dir) / "truth" / "frames.csv", ["t", "index", "poke", "sigma"])
    picks = select_frames(fr[:, 2], select_cfg)
    need = sorted({i for i, _, _ in picks} | {b for _, b, _ in picks})
    frames = {i: cv2.cvtColor(img, cv2.COLOR_BGR2RGB) for i, img in read_frames(ses, need)}
    cx, cy = calibration.gel_center_px
    S = calibration.model_size
    rng = np.random.default_rng([cfg.seed, int(fr.shape[0]), len(picks)])
    measured = measured_at(ses, ses.table("frames")[:, 0])
    two = None
    if contacts:
        ids = sorted(measured)
        at = np.array([i for i, _, _ in picks], int)
        two = contact_pixels(np.stack([np.asarray(measured[k]["tip"], float)[at] for k in ids], axis=1),
                             np.stack([np.asarray(measured[k]["force"], float)[at] for k in ids], axis=1),
                             calibration.surface_xyz, calibration.mask)
    pre0 = Preprocessor(cx, cy, calibration.gel_radius_px, S)
    rows, inputs, per_sample = [], [], []
    for n, (i, b, p) in enumerate(picks):
        for k, (x, y, r) in enumerate(jittered_circles(cx, cy, calibration.gel_radius_px, cfg.copies, cfg, rng)):
            pre = Preprocessor(x, y, r, S)
            inputs.append(np.concatenate([pre.crop(frames[b]).transpose(2, 0, 1), pre.crop(frames[i]).transpose(2, 0, 1)]))
            rows.append((i, b, p, k))
            if two is not None:
                c = two[n].copy()
                c[:, 3:] = pixels_in_crop(c[:, 3:], pre0, pre)
                per_sample.append(c)
        if progress:
            progress(n + 1, len(picks))
    x = np.stack(inputs).astype(np.uint8) if inputs else np.zeros((0, 6) + tuple(S), np.uint8)
    arr = np.array(rows, int).reshape(-1, 4)
    out = {"input": x, "target": teacher_targets(run, x), "frame": arr[:, 0], "baseline": arr[:, 1],
           "poke": arr[:, 2], "copy": arr[:, 3], "force_n": measured_total(measured, arr[:, 0])}
    if two is not None:
        out["contacts_n"] = (np.stack(per_sample) if per_sample else np.zeros((0, 2, 5))).astype(np.float32)
    return out


def teacher_bounds(package: Path) -> dict:
    """The teacher's output bounds (its manifest), which normalize its outputs and so the dataset."""
    from .model.train import load_any_bounds

    return load_any_bounds(package)


def write_distilled(root: Path, parts: list[dict], bounds: dict, size: int, source: str,
                    pixel_area: np.ndarray | None = None) -> str:
    """parts: per session {'input', 'target' (already normalized by `bounds`), 'val'} → dataset directory
    (`dataset.write_dataset`); returns its hash."""
    from .dataset import write_dataset

    if not any(len(p["input"]) for p in parts):
        raise TensorTouchError(f"{root}: distillation found no frames in the training sessions")
    return write_dataset(root, parts, size, source, pixel_area, bounds=bounds, compress=False)
