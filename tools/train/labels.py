"""Stage 5 from re-solved FE (real-rig path): which camera frames get labels, and their fields.

No twin truth is read. Per session, the stage-2 sources (one re-solved FE scenario per stage-1 contact
period: FE frame times, indenter ids, result) define:
- **contact frames**: camera frames inside an FE frame span [first, last FE frame] of a period; their
  FE parameter σ = j + s comes from the measurements (`resolve.frame_sigma`: the least-squares place on
  the segment between FE frames j and j+1 of the smoothed mocap pose and, with `LabelConfig.sigma` =
  "pose+ft", of the F/T force against the FE reactions × the stage-4 ratios) and the fields are the linear
  interpolation of the two FE frames (`resolve.interp_frames`); frames within half a camera period of
  an FE frame are (up to that half period) the FE frame itself. `LabelConfig.frames` = "fe" keeps only
  those (no interpolated label), "keypoint" only the frames nearest a stage-1 keypoint (the seed's labels),
  "checked" the FE frames and those interpolated frames whose label force agrees with the F/T as well as
  the FE frames' labels do (`checked_frames`): an interpolated label is kept only where the rig's own
  measurement shows it is as good;
- **busy frames**: outside those spans but with a measured |F| above `rest_force_n` on some indenter
  (light contact before 1.5 N / after 1.1 N) or between a period's initial FE pose and its first
  frame: neither contact samples nor rest samples;
- **rest frames**: the others (all-zero fields), chosen by `dataset.select_frames` like the twin path.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...contracts.fields import N_CHANNELS
from .build import CHOICES

log = logging.getLogger(__name__)

BUSY_ID = 100000     # frame labels ≥ this mark busy frames (dropped after frame selection)


@dataclass(frozen=True)
class LabelConfig:
    rest_force_n: float = 0.1             # |F| above this outside a labelled span: not a rest frame
    frames: str = "interpolated"          # contact labels at: every frame of an FE span (interpolated
                                          # between FE frames) | "fe" (FE frames only) | "keypoint" (seed)
    sigma: str = "pose"                   # where a frame sits between two FE frames: from the mocap pose and
                                          # the F/T force ("pose+ft") | the pose alone ("pose")
    pose_sd_mm: float = 0.05              # weights of that fit: the mocap's error (seed appendix 0.03–0.08 mm)
    force_sd_n: float = 0.05              # ... and the F/T + sim-to-real error at FE frames (0.04–0.09 N)
    check_quantile: float = 0.9           # "checked": an interpolated label's |label F − F/T| must be within this
                                          # quantile of the same session's FE-frame labels' |label F − F/T|

    def __post_init__(self):
        for name, key in (("frames", "label_frames"), ("sigma", "label_sigma")):
            if getattr(self, name) not in CHOICES[key]:
                raise ValueError(f"LabelConfig.{name}: expected one of {', '.join(CHOICES[key])}, "
                                 f"got {getattr(self, name)!r}")
        if not 0.0 < self.check_quantile <= 1.0:
            raise ValueError(f"LabelConfig.check_quantile: expected a quantile in (0, 1], got {self.check_quantile!r}")


def half_period(frame_t: np.ndarray) -> float:
    """Half the camera period (s) of frame times `frame_t`: how near an FE frame a camera frame counts as at it."""
    t = np.asarray(frame_t, float)
    return 0.5 * float(np.median(np.diff(t))) if len(t) > 1 else 0.0


def near_times(t: np.ndarray, times: np.ndarray, half: float) -> np.ndarray:
    """(n,) bool: is each of the times `t` within `half` (s) of one of `times` (any order; none: False)?"""
    t = np.asarray(t, float).reshape(-1)
    ts = np.sort(np.asarray(times, float).reshape(-1))
    if not len(ts):
        return np.zeros(len(t), bool)
    j = np.clip(np.searchsorted(ts, t), 1, len(ts) - 1) if len(ts) > 1 else np.zeros(len(t), int)
    gap = np.minimum(np.abs(ts[j] - t), np.abs(ts[np.maximum(j - 1, 0)] - t))
    return gap <= half + 1e-9


def checked_frames(residual_n: np.ndarray, at_fe: np.ndarray, quantile: float) -> np.ndarray:
    """(n,) bool: which labelled frames to keep under `LabelConfig.frames = "checked"`.

    residual_n (n,): |label force − measured F/T force| per frame (N); at_fe (n,) bool: the frame is an FE
    frame. FE frames are always kept; an interpolated frame is kept when its residual is within the
    `quantile` of the FE frames' residuals. With no FE frame to compare against, no interpolated frame is kept."""
    r = np.asarray(residual_n, float)
    at = np.asarray(at_fe, bool)
    if r.ndim != 1 or at.shape != r.shape:
        raise ValueError(f"checked_frames: residual_n {r.shape} and at_fe {at.shape} must be the same (n,) shape")
    if not 0.0 < quantile <= 1.0:
        raise ValueError(f"checked_frames: quantile {quantile!r} not in (0, 1]")
    if not at.any():
        return at.copy()
    limit = float(np.quantile(r[at], quantile))
    return at | (r <= limit)


def frame_labels(frame_t: np.ndarray, sources: list, tracks: dict, wrench: np.ndarray,
                 rcfg=None, lcfg: LabelConfig = LabelConfig(), measured: dict | None = None,
                 ratios: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per camera frame: label (source index, −1 rest, ≥ BUSY_ID busy) and σ (NaN unless labelled).

    sources[p]: .times (J,), .t_init, .slots, .is_keypoint (J,), .result.RF (J, K, 3); tracks: {slot:
    resolve.PoseTrack}; wrench: session wrench table (t, indenter, fx, fy, fz, ...). With
    `lcfg.sigma = "pose+ft"` and `measured` ({slot: (len(frame_t), 3) force on the gel, sensor frame:
    `tools.scoring.measured_at`'s "force"), σ also fits it to the FE reactions × the stage-4 `ratios`;
    `lcfg.frames = "checked"` (needs `measured`) drops the interpolated frames `checked_frames` rejects."""
    from .resolve import ResolveConfig, frame_sigma, interp_frames
    from .simreal import slot_ratios

    rcfg = rcfg or ResolveConfig()
    checks = []
    t = np.asarray(frame_t, float)
    lab = np.full(len(t), -1, int)
    sig = np.full(len(t), np.nan)
    busy = np.zeros(len(t), bool)
    w = np.asarray(wrench, float)
    for k in np.unique(w[:, 1]).astype(int):
        wk = w[w[:, 1] == k]
        busy |= np.interp(t, wk[:, 0], np.linalg.norm(wk[:, 2:5], axis=1)) > lcfg.rest_force_n
    half = half_period(t)
    for p, src in enumerate(sources):
        times = np.asarray(src.times, float)
        busy |= (t >= src.t_init) & (t <= times[-1])
        inside = np.flatnonzero((t >= times[0]) & (t <= times[-1]))
        if lcfg.frames in ("fe", "keypoint"):
            kt = times[np.asarray(src.is_keypoint, bool)] if lcfg.frames == "keypoint" else times
            inside = inside[near_times(t[inside], kt, half)]
        if len(inside):
            lab[inside] = p
            force = None
            if measured is not None and (lcfg.sigma == "pose+ft" or lcfg.frames == "checked"):
                fe = np.asarray(src.result.RF, float)[:, :len(src.slots)] * slot_ratios(ratios, src.slots)
                fm = np.concatenate([np.asarray(measured[sl])[inside] for sl in src.slots], 1)
                force = (fm, fe.reshape(len(times), -1))
            sig[inside] = frame_sigma(t[inside], times, [tracks[s] for s in src.slots], rcfg,
                                      force if lcfg.sigma == "pose+ft" else None, lcfg.pose_sd_mm, lcfg.force_sd_n)
            if lcfg.frames == "checked":
                if force is None:
                    raise ValueError('LabelConfig.frames = "checked" needs the measured F/T forces (measured=)')
                label_f = np.array([interp_frames(force[1], s) for s in sig[inside]])
                checks.append((inside, np.linalg.norm(force[0] - label_f, axis=1), near_times(t[inside], times, half)))
    if checks:
        keep = checked_frames(np.concatenate([c[1] for c in checks]), np.concatenate([c[2] for c in checks]),
                              lcfg.check_quantile)
        drop = np.concatenate([c[0] for c in checks])[~keep]
        lab[drop], sig[drop] = -1, np.nan          # inside a span: they become busy frames below
    free = busy & (lab < 0)
    runs = np.cumsum(np.diff(np.concatenate([[0], free.astype(int)])) == 1)
    lab[free] = BUSY_ID + runs[free]
    return lab, sig


def keypoint_frame_share(frame_t: np.ndarray, label: np.ndarray, sources: list) -> dict:
    """How many labelled frames there are and how many sit at a stage-1 keypoint / any FE frame
    (within half a camera period): the cost of labelling only keypoint frames (seed)."""
    t = np.asarray(frame_t, float)
    half = half_period(t)
    n, at_key, at_fe = 0, 0, 0
    for p, src in enumerate(sources):
        idx = np.flatnonzero(label == p)
        times = np.asarray(src.times, float)
        kt = times[np.asarray(src.is_keypoint, bool)]
        n += len(idx)
        at_key += int(near_times(t[idx], kt, half).sum())
        at_fe += int(near_times(t[idx], times, half).sum())
    return {"labelled_frames": n, "at_keypoint": at_key, "at_fe_frame": at_fe}


def at_fe_frames(frame_t: np.ndarray, frames: np.ndarray, sources: list) -> np.ndarray:
    """(n,) bool: does each labelled camera frame (indices `frames` into `frame_t`) sit within half a camera
    period of an FE frame of any source, or is its label interpolated between FE frames?"""
    t = np.asarray(frame_t, float)
    fe_t = np.concatenate([np.asarray(src.times, float) for src in sources]) if sources else np.zeros(0)
    return near_times(t[np.asarray(frames, int)], fe_t, half_period(t))


def source_fields(view, sigma: float, ratios: np.ndarray, stress_scale: float, projector) -> np.ndarray:
    """(15, S, S) fields of one frame at FE parameter σ of a source (view = dataset.surface_view)."""
    from .fields import attribute_contacts
    from .resolve import interp_frames
    from .simreal import apply_ratios

    u = interp_frames(view.U, sigma)
    s = interp_frames(view.S, sigma) * stress_scale
    cn, cs = interp_frames(view.CNORMF, sigma), interp_frames(view.CSHEAR, sigma)
    owner = np.full(len(u), -1)
    touch = np.flatnonzero(np.linalg.norm(cn, axis=1) + np.linalg.norm(cs, axis=1) > 1e-9)
    if len(touch):
        K = ratios.shape[0]
        owner[touch] = 0 if K == 1 else attribute_contacts(view.xyz[touch], interp_frames(view.pose_position, sigma))
    return projector.project(u, s, apply_ratios(cn, owner, ratios), apply_ratios(cs, owner, ratios))


def session_samples_measured(session_dir: Path, calibration, sources: list, ratios: dict, dcfg,
                             lcfg: LabelConfig = LabelConfig(), rcfg=None, progress=None) -> dict:
    """All samples of one session from re-solved FE (same output as dataset.session_samples):
    {'input' (n,6,S,S) u8, 'target' (n,15,S,S) f32 physical, 'frame', 'baseline', 'poke' (n,)}."""
    from ...contracts.session import load_session
    from ...runtime.stages.preprocess import Preprocessor
    from ..scoring import measured_at
    from .dataset import FieldProjector, crops, select_frames, surface_view
    from .fields import FieldConfig
    from .resolve import PoseTrack
    from .simreal import slot_ratios

    ses = load_session(session_dir)
    frames = ses.table("frames")
    poses = ses.table("poses")
    tracks = {int(k): PoseTrack.from_table(poses, int(k)) for k in np.unique(poses[:, 1])}
    measured = None
    if lcfg.sigma == "pose+ft" or lcfg.frames == "checked":
        measured = {k: v["force"] for k, v in measured_at(ses, frames[:, 0]).items()}
    lab, sig = frame_labels(frames[:, 0], sources, tracks, ses.table("wrench"), rcfg, lcfg, measured, ratios)
    picks = [pk for pk in select_frames(lab, dcfg) if pk[2] < BUSY_ID]
    contact = [pk for pk in picks if pk[2] >= 0]
    rest = [pk for pk in picks if pk[2] < 0]
    n_rest = min(len(rest), int(round(dcfg.rest_fraction * len(contact))))   # busy picks inflated the count
    rest = [rest[i] for i in np.linspace(0, len(rest) - 1, n_rest).round().astype(int)] if n_rest else []
    picks = sorted(contact + rest)
    cx, cy = calibration.gel_center_px
    pre = Preprocessor(cx, cy, calibration.gel_radius_px, calibration.model_size)
    images = crops(ses, pre, sorted({i for i, _, _ in picks} | {b for _, b, _ in picks}))
    gel = calibration.meta.get("gel", {})
    fcfg = FieldConfig(center_mm=(0.0, 0.0, float(gel.get("center_z_mm", 0.0))))
    tables = {"theta": calibration.theta, "phi": calibration.phi, "pixel_area": calibration.pixel_area}
    stress_scale = float(np.mean([v["magnitude"] for v in ratios.values()] or [1.0]))
    S = calibration.model_size
    inp = np.zeros((len(picks), 6) + tuple(S), np.uint8)
    tgt = np.zeros((len(picks), N_CHANNELS) + tuple(S), np.float32)
    views, projectors = {}, {}
    for n, (i, b, p) in enumerate(picks):
        inp[n, :3] = images[b].transpose(2, 0, 1)
        inp[n, 3:] = images[i].transpose(2, 0, 1)
        if p >= 0:
            if p not in views:
                views[p] = v = surface_view(sources[p].result)
                key = (len(v.xyz), float(np.round(v.xyz.sum(), 6)))
                if key not in projectors:
                    projectors[key] = FieldProjector(v.xyz, v.area, tables, fcfg)
                v.projector = projectors[key]
            tgt[n] = source_fields(views[p], float(sig[i]), slot_ratios(ratios, sources[p].slots), stress_scale,
                                   views[p].projector)
        if progress:
            progress(n + 1, len(picks))
    arr = np.array(picks, int).reshape(-1, 3)
    share = keypoint_frame_share(frames[:, 0], lab, sources)
    log.info("%s: %d samples (%d contact); labelled frames %s", Path(session_dir).name, len(picks),
             int((arr[:, 2] >= 0).sum()), share)
    return {"input": inp, "target": tgt, "frame": arr[:, 0], "baseline": arr[:, 1], "poke": arr[:, 2]}
