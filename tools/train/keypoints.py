"""Stage 1 — contact detection and keypoint extraction (seed §III.C).

Pure cores (arrays in, arrays out):

- `detect_contacts`      dual-threshold (hysteresis) contact intervals from a force magnitude trace,
                         each extended backwards by the pre-contact period;
- `merge_intervals`      union of per-indenter intervals into periods of (possibly simultaneous) contact;
- `relative_pose`        6 pose signals: Δp = p(t) − p(t0) (mm) and Euler angles of R(t0)⁻¹·R(t) (rad);
- `smooth`               order-1 Butterworth low-pass with fc = fs/3, zero phase;
- `find_keypoints`       prominent peaks/troughs on the 6 signals with minimum spacing ≈ 1.5 / f_image,
                         start and end always kept, close keypoints thinned and the count capped,
                         preferring large motion;
- `extract_keypoints`    the whole chain for one session's arrays (several indenters).

Quaternions follow the session contract: scalar first (qw, qx, qy, qz).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import signal
from scipy.spatial.transform import Rotation, Slerp

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KeypointConfig:
    """Seed §III.C numbers as named defaults."""

    contact_force_n: float = 1.5          # contact starts when |F| rises above this
    detach_force_n: float = 1.1           # ... and ends when |F| falls below this
    pre_contact_s: float = 0.3            # each interval is extended backwards by this
    butter_order: int = 1                 # "order 1 to avoid over-smoothing"
    cutoff_fraction_of_fs: float = 1.0 / 3.0   # fc = fs / 3
    image_rate_hz: float = 30.0           # camera frame rate f_image
    peak_spacing_frames: float = 1.5      # minimum peak spacing = this / f_image (s)
    prominence_fraction: float = 0.05     # a peak must stand out by this fraction of the signal's range ...
    min_prominence_mm: float = 0.05       # ... and by at least this (position signals)
    min_prominence_rad: float = np.deg2rad(0.5)   # ... or this (rotation signals)
    max_keypoints: int = 12               # cap per contact period (start and end included)
    rotation_weight_mm_per_rad: float = 10.0       # motion magnitude = |Δp| + w·|Δrot|
    euler_order: str = "xyz"              # Euler convention for the rotation signals
    min_interval_s: float = 0.0           # drop contact periods shorter than this

    @property
    def min_spacing_s(self) -> float:
        return self.peak_spacing_frames / self.image_rate_hz


@dataclass
class ContactPeriod:
    """A period of contact (after pre-contact extension and merging), times in s."""

    t_start: float                 # includes the pre-contact extension
    t_end: float
    indenters: tuple[int, ...]     # indenters in contact at some point of the period
    t_contact: float = float("nan")   # first threshold crossing (before extension)


@dataclass
class Keypoints:
    """Keypoints of one contact period. Arrays are indexed [keypoint, indenter, ...]."""

    period: ContactPeriod
    t: np.ndarray                  # (K,) s
    position: np.ndarray           # (K, I, 3) mm, absolute
    quaternion: np.ndarray         # (K, I, 4) scalar first, absolute
    rel_pose: np.ndarray           # (K, I, 6) Δp mm + Euler rad relative to the period's first sample
    force: np.ndarray              # (K, I, 3) N (F/T frame), interpolated at t
    torque: np.ndarray             # (K, I, 3) N·mm
    frame_index: np.ndarray        # (K,) nearest camera frame number (-1 without frames)
    indenter_ids: tuple[int, ...] = field(default=())


def detect_contacts(t: np.ndarray, force_mag: np.ndarray, cfg: KeypointConfig = KeypointConfig()
                    ) -> list[tuple[float, float, float]]:
    """Dual-threshold contact intervals [(t_start, t_end, t_contact)] in s.

    Contact begins at the first sample with |F| > contact_force_n and ends at the first later sample
    with |F| < detach_force_n (or the end of the trace). t_start = t_contact − pre_contact_s, clipped
    to the trace start.
    """
    t = np.asarray(t, dtype=float)
    f = np.asarray(force_mag, dtype=float)
    if t.shape != f.shape or t.ndim != 1:
        raise ValueError(f"detect_contacts: t {t.shape} and force_mag {f.shape} must be equal 1-D shapes")
    if cfg.detach_force_n > cfg.contact_force_n:
        raise ValueError("detect_contacts: detach threshold must not exceed the contact threshold")
    out = []
    in_contact = False
    t_on = 0.0
    for i in range(f.size):
        if not in_contact and f[i] > cfg.contact_force_n:
            in_contact, t_on = True, t[i]
        elif in_contact and f[i] < cfg.detach_force_n:
            in_contact = False
            out.append((max(t[0], t_on - cfg.pre_contact_s), t[i], t_on))
    if in_contact:
        out.append((max(t[0], t_on - cfg.pre_contact_s), t[-1], t_on))
    return [iv for iv in out if iv[1] - iv[2] >= cfg.min_interval_s]


def merge_intervals(per_indenter: dict[int, list[tuple[float, float, float]]]) -> list[ContactPeriod]:
    """Union of overlapping intervals across indenters -> periods listing every indenter involved."""
    items = sorted((s, e, c, k) for k, ivs in per_indenter.items() for (s, e, c) in ivs)
    periods: list[ContactPeriod] = []
    for s, e, c, k in items:
        if periods and s <= periods[-1].t_end:
            p = periods[-1]
            p.t_end = max(p.t_end, e)
            p.t_contact = min(p.t_contact, c)
            if k not in p.indenters:
                p.indenters = tuple(sorted(p.indenters + (k,)))
        else:
            periods.append(ContactPeriod(s, e, (k,), c))
    return periods


def relative_pose(position: np.ndarray, quaternion: np.ndarray, cfg: KeypointConfig = KeypointConfig()
                  ) -> np.ndarray:
    """(N, 6): Δp (mm) and Euler angles (rad) of R(t0)⁻¹·R(t), t0 = first sample."""
    position = np.asarray(position, dtype=float)
    rot = Rotation.from_quat(np.asarray(quaternion, dtype=float), scalar_first=True)
    d_rot = (rot[0].inv() * rot).as_euler(cfg.euler_order)
    return np.concatenate([position - position[0], d_rot], axis=1)


def smooth(signals: np.ndarray, fs: float, cfg: KeypointConfig = KeypointConfig()) -> np.ndarray:
    """Zero-phase Butterworth low-pass (order cfg.butter_order, fc = fs·cutoff_fraction) along axis 0."""
    x = np.asarray(signals, dtype=float)
    wn = cfg.cutoff_fraction_of_fs * fs / (fs / 2.0)   # normalised to Nyquist: 2/3 for fc = fs/3
    sos = signal.butter(cfg.butter_order, wn, btype="low", output="sos")
    padlen = min(3 * (2 * len(sos) + 1), x.shape[0] - 1)
    if x.shape[0] < 2:
        return x.copy()
    return signal.sosfiltfilt(sos, x, axis=0, padlen=max(padlen, 0))


def motion_magnitude(rel_pose: np.ndarray, cfg: KeypointConfig = KeypointConfig()) -> np.ndarray:
    """|Δp| + w·|Δrot| per sample (mm-equivalent), rel_pose (..., 6)."""
    rel_pose = np.asarray(rel_pose, dtype=float)
    return (np.linalg.norm(rel_pose[..., :3], axis=-1)
            + cfg.rotation_weight_mm_per_rad * np.linalg.norm(rel_pose[..., 3:], axis=-1))


def _peaks_one(x: np.ndarray, distance: int, floor: float, cfg: KeypointConfig) -> np.ndarray:
    span = float(np.ptp(x)) if x.size else 0.0
    prom = max(cfg.prominence_fraction * span, floor)
    if span < prom:
        return np.zeros(0, dtype=int)
    hi, _ = signal.find_peaks(x, distance=distance, prominence=prom)
    lo, _ = signal.find_peaks(-x, distance=distance, prominence=prom)
    return np.concatenate([hi, lo])


def find_keypoints(t: np.ndarray, signals: np.ndarray, cfg: KeypointConfig = KeypointConfig(),
                   magnitude: np.ndarray | None = None) -> np.ndarray:
    """Sample indices of keypoints on (N, 6·I) smoothed pose signals (Δp mm, Euler rad per indenter).

    Peaks and troughs of each signal (a motion reversal is a peak of one sign or the other), at least
    cfg.min_spacing_s apart, prominence ≥ max(fraction·range, floor); start and end always kept;
    candidates closer than the spacing are thinned keeping the larger motion; at most
    cfg.max_keypoints, keeping the largest motion. `magnitude` (N,) ranks candidates (default: the
    motion magnitude of the first six signals).
    """
    t = np.asarray(t, dtype=float)
    x = np.asarray(signals, dtype=float)
    if x.ndim != 2 or x.shape[1] % 6 or x.shape[0] != t.size:
        raise ValueError(f"find_keypoints: signals {x.shape} must be (N={t.size}, 6·I)")
    n = t.size
    if n <= 2:
        return np.arange(n)
    fs = (n - 1) / (t[-1] - t[0])
    distance = max(1, int(round(cfg.min_spacing_s * fs)))
    cand = [0, n - 1]
    for j in range(x.shape[1]):
        floor = cfg.min_prominence_mm if j % 6 < 3 else cfg.min_prominence_rad
        cand.extend(_peaks_one(x[:, j], distance, floor, cfg).tolist())
    cand = np.unique(cand)
    mag = motion_magnitude(x[:, :6], cfg) if magnitude is None else np.asarray(magnitude, dtype=float)
    # Thin: visit candidates by decreasing magnitude, keep those far enough from everything kept.
    order = sorted(cand.tolist(), key=lambda i: (i not in (0, n - 1), -mag[i]))
    kept: list[int] = []
    for i in order:
        if i in (0, n - 1) or all(abs(t[i] - t[k]) >= cfg.min_spacing_s for k in kept):
            kept.append(i)
        if len(kept) >= cfg.max_keypoints:
            break
    return np.array(sorted(kept), dtype=int)


def _interp_rows(t_src: np.ndarray, values: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t_dst, t_src, values[:, j]) for j in range(values.shape[1])], axis=1)


def extract_keypoints(poses: np.ndarray, wrench: np.ndarray, frames: np.ndarray | None = None,
                      cfg: KeypointConfig = KeypointConfig()) -> list[Keypoints]:
    """Run the whole stage on session tables (columns of contracts.session.STREAM_COLUMNS).

    poses (M, 9): t, indenter, x, y, z, qw, qx, qy, qz; wrench (L, 8): t, indenter, fx, fy, fz, tx, ty, tz;
    frames (F, 2): t, index (optional). Every indenter needs both streams. Returns one Keypoints per
    merged contact period; keypoint times are the union over the indenters in contact.
    """
    poses = np.asarray(poses, dtype=float)
    wrench = np.asarray(wrench, dtype=float)
    ids = sorted(int(k) for k in np.unique(poses[:, 1]))
    pose_by, wr_by, per = {}, {}, {}
    for k in ids:
        p = poses[poses[:, 1] == k]
        w = wrench[wrench[:, 1] == k]
        if w.shape[0] < 2 or p.shape[0] < 2:
            raise ValueError(f"extract_keypoints: indenter {k} needs ≥ 2 pose and wrench samples")
        pose_by[k], wr_by[k] = p, w
        per[k] = detect_contacts(w[:, 0], np.linalg.norm(w[:, 2:5], axis=1), cfg)
    periods = merge_intervals(per)
    log.info("%d contact period(s) from %d indenter(s)", len(periods), len(ids))
    out = []
    for period in periods:
        # Common time base: the densest pose clock of the involved indenters, inside the period.
        ref = max(period.indenters, key=lambda k: pose_by[k].shape[0])
        tp = pose_by[ref][:, 0]
        tt = tp[(tp >= period.t_start) & (tp <= period.t_end)]
        if tt.size < 2:
            continue
        fs = (tt.size - 1) / (tt[-1] - tt[0])
        sig, pos, quat = [], [], []
        for k in ids:
            p = pose_by[k]
            pk = _interp_rows(p[:, 0], p[:, 2:5], tt)
            qk = _slerp_rows(p[:, 0], p[:, 5:9], tt)
            pos.append(pk)
            quat.append(qk)
            if k in period.indenters:
                sig.append(smooth(relative_pose(pk, qk, cfg), fs, cfg))
        sig = np.concatenate(sig, axis=1)
        mag = sum(motion_magnitude(sig[:, 6 * i:6 * i + 6], cfg) for i in range(sig.shape[1] // 6))
        idx = find_keypoints(tt, sig, cfg, magnitude=mag)
        pos, quat = np.stack(pos, 1), np.stack(quat, 1)
        rel = np.stack([relative_pose(pos[:, i], quat[:, i], cfg) for i in range(len(ids))], 1)
        tk = tt[idx]
        force = np.stack([_interp_rows(wr_by[k][:, 0], wr_by[k][:, 2:5], tk) for k in ids], 1)
        torque = np.stack([_interp_rows(wr_by[k][:, 0], wr_by[k][:, 5:8], tk) for k in ids], 1)
        if frames is not None and len(frames):
            fr = np.asarray(frames, dtype=float)
            j = np.clip(np.searchsorted(fr[:, 0], tk), 1, len(fr) - 1)
            j = np.where(np.abs(fr[j - 1, 0] - tk) <= np.abs(fr[j, 0] - tk), j - 1, j)
            frame_index = fr[j, 1].astype(int)
        else:
            frame_index = np.full(tk.size, -1)
        out.append(Keypoints(period, tk, pos[idx], quat[idx], rel[idx], force, torque, frame_index,
                             tuple(ids)))
    return out


def _slerp_rows(t_src: np.ndarray, quat: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    rot = Rotation.from_quat(quat, scalar_first=True)
    t_dst = np.clip(t_dst, t_src[0], t_src[-1])
    return Slerp(t_src, rot)(t_dst).as_quat(scalar_first=True)


def keypoints_doc(session, kps: list[Keypoints], cfg: KeypointConfig, session_path: str = "") -> dict:
    """The stage-1 output document (`tensortouch.keypoints` v1, docs/train.md) of one session."""
    return {"schema": "tensortouch.keypoints", "schema_version": 1, "session": session_path,
            "sensor_id": session.sensor_id, "units": {"t": "s", "position": "mm", "angle": "rad", "force": "N",
                                                      "torque": "N*mm"},
            "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__},
            "periods": [{"t_start": float(k.period.t_start), "t_end": float(k.period.t_end),
                         "t_contact": float(k.period.t_contact), "indenters": list(k.period.indenters),
                         "indenter_ids": list(k.indenter_ids), "t": k.t.tolist(),
                         "position": k.position.tolist(), "quaternion_wxyz": k.quaternion.tolist(),
                         "rel_pose": k.rel_pose.tolist(), "force": k.force.tolist(), "torque": k.torque.tolist(),
                         "frame_index": k.frame_index.tolist()} for k in kps]}
