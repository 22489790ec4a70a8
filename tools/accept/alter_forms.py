"""Hidden effects in forms that are NOT the library's, put into a recorded session's F/T stream
(written independently of runtime/effects and tools/twin/effects.py; frames untouched).

Each form takes an amplitude `amp`; the harness scales it so the effect's own contribution has a
chosen size. Quantities come from the session's own streams (mocap tip, temperature) and the gel's
nominal geometry (params "radius", "center_z", "skirt" of the cap sphere, mm):

  saturating_stiffening  F (1 + amp tanh((d / 1 mm)²))             library: 1 + k (d/h)² (no saturation)
                         d = indentation of the mocap tip below the rest cap sphere
  two_term_relaxation    e - amp (½ L_0.4s(e) + ½ L_6s(e)) on the change e from the unloaded reading,
                         L_τ a first-order low-pass (a two-term Prony kernel); where the relaxed
                         force points against e the contact is lost (no pull)   library: one term
  rim_profile            F (1 + amp (1 - s / 12 mm)²₊), s = arc length from the tip down to the rim
                                                                   library: 1 + a exp(-s / w)
  temperature_onset      F (1 - amp ((T - 24 °C)₊ / 5 °C)²)          library: 1 - α (T - T_ref)
  velocity_drag          F - amp v: v the indenter's velocity (smoothed mocap, sensor frame, mm/s)
                         turned into the F/T frame, in and out of contact   not in the library
  log_stiffening         F (1 + amp ln(1 + d / 0.5 mm))              library: 1 + k (d/h)²
  exp_temperature        F exp(-amp (T - T_start) / 5 °C), T_start the session's first reading
                                                                   library: 1 - α (T - T_ref)
  ft_offset_ramp         f_FT + amp (t / 100 s)^1.5 (0.4, -0.3, 1) N, a reference offset creeping
                         in the F/T frame, in and out of contact     library: linear in time
  sector_stiffening      F (1 + amp max(cos(φ - 0.7), 0)²), φ the tip's azimuth   not in the library
  cubic_stiffening       F (1 + amp (d / 1 mm)³)                      library: 1 + k (d/h)²
  logistic_temperature   F (1 - amp σ((T - T_mid) / 0.5 °C)), σ the logistic, T_mid the middle of the
                         session's temperature range                 library: 1 - α (T - T_ref)
  ft_offset_sqrt         f_FT + amp (t / 100 s)^0.5 (-0.5, 0.6, 0.8) N, a reference offset that
                         settles, in the F/T frame, in and out of contact   library: linear in time
  rim_linear             F (1 + amp (1 - s / 9 mm)₊), s as rim_profile   library: 1 + a exp(-s / w)
(the last eight are used by `tensortouch accept workbench-paths` only: log_stiffening ..
sector_stiffening for tuning its method, cubic_stiffening .. rim_linear for scoring it)
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.signal import savgol_filter

from ...contracts.files import atomic_write_json
from ...contracts.session import Session, as_written, load_session, write_stream
from .alter import _quat_matrix, copy_without_truth

FORMS = ("saturating_stiffening", "two_term_relaxation", "rim_profile", "temperature_onset", "velocity_drag",
         "log_stiffening", "exp_temperature", "ft_offset_ramp", "sector_stiffening",
         "cubic_stiffening", "logistic_temperature", "ft_offset_sqrt", "rim_linear")


def _lowpass(x: np.ndarray, t: np.ndarray, tau: float) -> np.ndarray:
    """First-order low-pass of each column of x (exact for a piecewise-constant input)."""
    out = np.empty_like(x)
    y = np.zeros(x.shape[1])
    prev = t[0]
    for i in range(len(t)):
        a = 1.0 - np.exp(-(t[i] - prev) / tau)
        y = y + a * (x[i] - y)
        out[i] = y
        prev = t[i]
    return out


def _tip(poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(t, poses[:, 0], poses[:, 2 + j]) for j in range(3)])


def _velocity(poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Indenter velocity (mm/s, sensor frame) at times t from the mocap track (smoothed over ~0.1 s)."""
    tp = poses[:, 0]
    win = max(5, int(round(0.1 / max(np.median(np.diff(tp)), 1e-6))) | 1)
    v = np.column_stack([savgol_filter(poses[:, 2 + j], win, 2, deriv=1, delta=float(np.median(np.diff(tp))))
                         for j in range(3)])
    return np.column_stack([np.interp(t, tp, v[:, j]) for j in range(3)])


def contribution(session, kind: str, amp: float, gel: dict) -> np.ndarray:
    """(rows of wrench, 3): the altered F/T force for one hidden form at amplitude `amp`."""
    manifest = session.manifest
    mount = manifest["streams"]["wrench"]["ft_to_indenter"]
    r_mount = _quat_matrix(np.array([mount["rotation_wxyz"]], float))[0]
    noise = float(session.streams["wrench"].get("noise", {}).get("force_n", 0.02))
    w = session.table("wrench")
    poses = session.table("poses")
    out = w[:, 2:5].copy()
    for k in np.unique(w[:, 1]):
        m = w[:, 1] == k
        t, f = w[m, 0], w[m, 2:5]
        p = poses[poses[:, 1] == k]
        tip = _tip(p, t)
        v = tip - np.array([0.0, 0.0, gel["center_z"]])
        r = np.linalg.norm(v, axis=1)
        d = np.clip(gel["radius"] - r, 0.0, None)
        if kind == "saturating_stiffening":
            f = f * (1.0 + amp * np.tanh(d ** 2))[:, None]
        elif kind in ("rim_profile", "rim_linear"):
            polar = np.arccos(np.clip(v[:, 2] / np.maximum(r, 1e-9), -1, 1))
            edge = np.arccos(np.clip((gel["skirt"] - gel["center_z"]) / gel["radius"], -1, 1))
            arc = gel["radius"] * np.clip(edge - polar, 0.0, None) + gel["skirt"]
            if kind == "rim_profile":
                f = f * (1.0 + amp * np.clip(1.0 - arc / 12.0, 0.0, None) ** 2)[:, None]
            else:
                f = f * (1.0 + amp * np.clip(1.0 - arc / 9.0, 0.0, None))[:, None]
        elif kind == "temperature_onset":
            tt = session.table("temperature")
            T = np.interp(t, tt[:, 0], tt[:, 1])
            f = f * (1.0 - amp * (np.clip(T - 24.0, 0.0, None) / 5.0) ** 2)[:, None]
        elif kind == "two_term_relaxation":
            f0 = f[0].copy()
            e = f - f0
            q = e - amp * (0.5 * _lowpass(e, t, 0.4) + 0.5 * _lowpass(e, t, 6.0))
            touching = np.linalg.norm(e, axis=1) > 3.0 * noise
            lost = touching & (np.sum(q * e, axis=1) <= 0.0)
            f = np.where(touching[:, None], f0 + q, f)
            f[lost] = f0
        elif kind == "velocity_drag":
            j = np.clip(np.searchsorted(p[:, 0], t), 0, len(p) - 1)
            rot = _quat_matrix(p[j, 5:9]) @ r_mount                     # F/T frame -> sensor frame
            vel = _velocity(p, t)
            f = f - amp * np.einsum("nji,nj->ni", rot, vel)             # the drag, in the F/T frame
        elif kind == "log_stiffening":
            f = f * (1.0 + amp * np.log1p(d / 0.5))[:, None]
        elif kind == "exp_temperature":
            tt = session.table("temperature")
            T = np.interp(t, tt[:, 0], tt[:, 1])
            f = f * np.exp(-amp * (T - tt[0, 1]) / 5.0)[:, None]
        elif kind == "ft_offset_ramp":
            t0 = float(w[0, 0])
            f = f + amp * (np.clip(t - t0, 0.0, None) / 100.0)[:, None] ** 1.5 * np.array([0.4, -0.3, 1.0])
        elif kind == "cubic_stiffening":
            f = f * (1.0 + amp * d ** 3)[:, None]
        elif kind == "logistic_temperature":
            tt = session.table("temperature")
            T = np.interp(t, tt[:, 0], tt[:, 1])
            mid = 0.5 * (float(tt[:, 1].min()) + float(tt[:, 1].max()))
            f = f * (1.0 - amp / (1.0 + np.exp(-(T - mid) / 0.5)))[:, None]
        elif kind == "ft_offset_sqrt":
            t0 = float(w[0, 0])
            f = f + amp * np.sqrt(np.clip(t - t0, 0.0, None) / 100.0)[:, None] * np.array([-0.5, 0.6, 0.8])
        elif kind == "sector_stiffening":
            phi = np.arctan2(v[:, 1], v[:, 0])
            f = f * (1.0 + amp * np.clip(np.cos(phi - 0.7), 0.0, None) ** 2)[:, None]
        else:
            raise ValueError(f"hidden form {kind!r}: expected one of {FORMS}")
        out[m] = f
    return out


# Forms that scale the force by a gain (the others add an offset in the F/T frame).
MULTIPLICATIVE = frozenset({"saturating_stiffening", "rim_profile", "temperature_onset", "log_stiffening",
                            "exp_temperature", "cubic_stiffening", "logistic_temperature", "sector_stiffening",
                            "rim_linear"})


def gain_of(altered: np.ndarray, clean: np.ndarray) -> np.ndarray:
    """(N,) the gain a multiplicative form put on each row's force: altered = gain * clean (rows
    with no force get 1)."""
    altered, clean = np.asarray(altered, float), np.asarray(clean, float)
    if altered.shape != clean.shape or altered.ndim != 2:
        raise ValueError(f"gain_of: expected two (N, 3) force arrays, got {altered.shape} and {clean.shape}")
    cc = np.sum(clean * clean, axis=1)
    return np.where(cc > 1e-18, np.sum(altered * clean, axis=1) / np.maximum(cc, 1e-18), 1.0)


def altered_session(session: Session, kind: str, amp: float, gel: dict) -> Session:
    """In memory, the session `alter` writes and loading it gives back: `session` whose F/T force
    carries the hidden form (every wrench number as its file holds it; the frames, poses and
    temperature are the recording's own, read from `session`'s folder)."""
    w = session.table("wrench").copy()
    w[:, 2:5] = contribution(session, kind, amp, gel)
    return session.with_table("wrench", as_written(w))


def alter(src: Path, dst: Path, kind: str, amp: float, gel: dict) -> Path:
    """A copy of session `src` (without its truth) whose F/T force carries the hidden form."""
    dst = copy_without_truth(Path(src), Path(dst))
    s = load_session(dst, check_frames=False)
    w = s.table("wrench").copy()
    w[:, 2:5] = contribution(s, kind, amp, gel)
    write_stream(dst, "wrench", w)       # as read: a rig calibration of the stream is in the numbers now
    manifest = json.loads((dst / "session.json").read_text())
    manifest["provenance"] = {"source": "altered copy (tools/accept/alter_forms.py)"}
    atomic_write_json(dst / "session.json", manifest, indent=2)
    return dst
