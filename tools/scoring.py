"""Scoring the sensor against the rig: the one place tools line up what the runtime publishes with what
the rig measured. Train (evaluation, the error budget, cross-evaluation, the threshold measurement,
labels, sim-to-real ratios), the workbench, recalibration and the benchmarks score through it; the
deploy package (runtime/) needs none of it.

- `measured_at(session, t)`: per indenter, the mocap tip (mm) and the measured force at times `t`, with
  ONE sign: `force` is the force the indenter applies to the gel (N, sensor frame) = −(F/T reading
  rotated into the sensor frame), the sign the runtime publishes for a contact. Filtering is explicit:
  `average` F/T samples per value, `pose_cutoff_hz` a zero-phase low-pass of the mocap track.
- `ft_to_sensor`: F/T-frame vectors → sensor frame (F/T → indenter → sensor rotations).
- `match_contacts`: indenter tips ↔ cluster centroids, each cluster used once.
- `split_at_tips`: the field's force split at the measured tips (nearest tip per pixel), the clustering left out.
- `contact_config(package)` / `find_contacts(fields, calibration, contacts)`: the runtime's contact stage
  on a frame's fields with the package's OWN settings (manifest `runtime.contacts`: threshold,
  light-touch rule, support, merge), exactly as `tensortouch run` builds it.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import butter, filtfilt
from scipy.spatial.transform import Rotation, Slerp

from ..contracts.errors import SessionError
from ..contracts.session import load_session


# ----- what the rig measured ----------------------------------------------------------------------
def _rotation(q_wxyz) -> Rotation:
    q = np.asarray(q_wxyz, float).reshape(-1, 4)
    return Rotation.from_quat(q[:, [1, 2, 3, 0]])


def ft_to_sensor(force_ft: np.ndarray, pose_quat_wxyz: np.ndarray, ft_rotation_wxyz) -> np.ndarray:
    """F/T force (T, 3) in the F/T frame → sensor frame, through F/T → indenter → sensor rotations
    (pose_quat_wxyz (T, 4) or (4,): the indenter's pose; ft_rotation_wxyz (4,): F/T → indenter)."""
    f = np.asarray(force_ft, float).reshape(-1, 3)
    return _rotation(pose_quat_wxyz).apply(_rotation(ft_rotation_wxyz)[0].apply(f))


def ft_rotation_wxyz(session) -> list[float]:
    """The session's F/T → indenter rotation (streams.wrench.ft_to_indenter; identity when the wrench
    stream is already in the indenter's frame)."""
    info = session.streams.get("wrench", {})
    if info.get("frame", "ft") == "sensor":
        return [1.0, 0.0, 0.0, 0.0]
    return list((info.get("ft_to_indenter") or {}).get("rotation_wxyz", [1.0, 0.0, 0.0, 0.0]))


def lowpass(x: np.ndarray, fs: float, fc: float | None) -> np.ndarray:
    """Zero-phase 2nd-order Butterworth low-pass of x (T, ...) sampled at fs (Hz); unchanged when fc is
    None, at or above Nyquist, or the track is too short to filter."""
    if fc is None or len(x) < 16 or fc >= fs / 2:
        return x
    b, a = butter(2, fc / (fs / 2))
    return filtfilt(b, a, x, axis=0)


def window_mean(a: np.ndarray, n: int) -> np.ndarray:
    """Means of consecutive windows of n rows (a trailing partial window is dropped)."""
    if n <= 1:
        return np.asarray(a)
    m = (len(a) // n) * n
    return a[:m].reshape((m // n, n) + a.shape[1:]).mean(axis=1)


def _interp(t: np.ndarray, ts: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t, ts, v[:, c]) for c in range(v.shape[1])], 1)


def measured_at(session, t: np.ndarray | None = None, *, indenters=None, average: int = 1,
                pose_cutoff_hz: float | None = None) -> dict[int, dict]:
    """What the rig measured, per indenter id (session's wrench and poses streams).

    t: times (s), e.g. the frame times; None = at the indenter's own (averaged) F/T samples.
    indenters: ids to return (default every id of the wrench stream). average: F/T samples averaged
    per value (window means, before interpolation); pose_cutoff_hz: low-pass of the mocap tip track.
    Returns {id: {"t" (T,), "tip" (T, 3) mm, "force" (T, 3) N = the force the indenter applies to the
    gel (−F/T reading in the sensor frame), "rotation" (T, 3, 3) F/T frame → sensor frame}}."""
    session = load_session(session) if not hasattr(session, "table") else session
    wr, po = session.table("wrench"), session.table("poses")
    ft_rot = _rotation(ft_rotation_wxyz(session))[0]
    ids = sorted(set(wr[:, 1].astype(int))) if indenters is None else [int(k) for k in indenters]
    out = {}
    for k in ids:
        w, p = wr[wr[:, 1] == k], po[po[:, 1] == k]
        if len(w) < 2 or len(p) < 2:
            raise SessionError(f"{session.path}: indenter {k} has {len(w)} wrench and {len(p)} pose samples "
                               "(at least 2 of each needed)")
        tw, f_ft = window_mean(w[:, 0], average), window_mean(w[:, 2:5], average)
        tk = tw if t is None else np.asarray(t, float)
        tq = np.clip(tk, p[0, 0], p[-1, 0])
        fs = 1.0 / max(float(np.median(np.diff(p[:, 0]))), 1e-9)
        tip = _interp(tq, p[:, 0], lowpass(p[:, 2:5], fs, pose_cutoff_hz))
        _, first = np.unique(p[:, 0], return_index=True)          # Slerp needs strictly increasing times
        pose = Slerp(p[first, 0], _rotation(p[first, 5:9]))(tq) if len(first) > 1 else _rotation(p[:1, 5:9])
        rot = (pose * ft_rot).as_matrix().reshape(-1, 3, 3)
        rot = np.broadcast_to(rot, (len(tk), 3, 3)) if len(rot) == 1 else rot
        f = f_ft if t is None else _interp(tk, tw, f_ft)
        out[k] = {"t": tk, "tip": tip, "force": -np.einsum("nij,nj->ni", rot, f), "rotation": rot}
    return out


# ----- clusters ↔ indenters -----------------------------------------------------------------------
def match_contacts(tips: np.ndarray, centroids: np.ndarray, max_mm: float = np.inf,
                   order: np.ndarray | None = None) -> np.ndarray:
    """Indenter tips (K, 3) ↔ cluster centroids (N, 3), mm; each cluster used once. Returns (K,) the
    matched cluster index or -1. Without `order`: greedy nearest pairs first, within max_mm. With
    `order` (indenter indices, e.g. strongest first): each of those indenters in turn takes its nearest
    free cluster within max_mm (indenters not listed stay -1)."""
    tips = np.asarray(tips, float).reshape(-1, 3)
    centroids = np.asarray(centroids, float).reshape(-1, 3)
    out = np.full(len(tips), -1)
    if len(tips) == 0 or len(centroids) == 0:
        return out
    d = np.linalg.norm(tips[:, None, :] - centroids[None, :, :], axis=2)
    if order is not None:
        free = np.ones(len(centroids), bool)
        for k in order:
            dk = np.where(free, d[k], np.inf)
            c = int(np.argmin(dk))
            if free[c] and dk[c] <= max_mm:       # with every cluster taken, the indenter gets none
                out[k], free[c] = c, False
        return out
    for flat in np.argsort(d, axis=None, kind="stable"):
        k, c = np.unravel_index(flat, d.shape)
        if d[k, c] > max_mm:
            break
        if out[k] < 0 and c not in out:
            out[k] = c
    return out


def split_at_tips(force_px: np.ndarray, surface_xyz: np.ndarray, mask: np.ndarray, tips: np.ndarray) -> np.ndarray:
    """The field's force split at the measured tips, with no clustering: every masked pixel's force goes
    to the nearest tip (surface distance in mm, ties to the lower index). force_px (3, H, W) N per pixel,
    surface_xyz (H, W, 3) mm, mask (H, W) bool, tips (K, 3) mm → (K, 3) N. Beside the clusters' forces it
    tells the network's field from the contact stage's split of it."""
    fp = np.asarray(force_px, float)
    xyz = np.asarray(surface_xyz, float)
    m = np.asarray(mask, bool)
    tips = np.asarray(tips, float).reshape(-1, 3)
    if fp.ndim != 3 or fp.shape[0] != 3 or xyz.shape != fp.shape[1:] + (3,) or m.shape != fp.shape[1:]:
        raise ValueError(f"split_at_tips: force_px (3, H, W), surface_xyz (H, W, 3) and mask (H, W) expected; "
                         f"got {fp.shape}, {xyz.shape}, {m.shape}")
    out = np.zeros((len(tips), 3))
    if len(tips) == 0 or not m.any():
        return out
    p, f = xyz[m], fp[:, m].T
    near = np.argmin(np.linalg.norm(p[:, None, :] - tips[None], axis=2), axis=1)
    for k in range(3):
        out[:, k] = np.bincount(near, f[:, k], len(tips))
    return out


# ----- the package's contact stage ----------------------------------------------------------------
def contact_config(package):
    """The contact settings `tensortouch run` uses with `package` (its manifest's runtime.contacts:
    threshold, light-touch rule, support, merge; defaults where absent)."""
    from ..runtime.pipeline import PipelineConfig

    return PipelineConfig.for_package(package).contacts


def find_contacts(fields: np.ndarray, calibration, contacts) -> list:
    """One frame's (15, S, S) physical fields → the runtime's clusters (before tracking) with the
    contact settings `contacts` (`contact_config(package)` for what ships)."""
    from ..runtime.pipeline import contact_stage

    return contact_stage(fields, calibration, contacts)
