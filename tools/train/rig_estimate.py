"""What a rig estimates from its own recording before labels are made: the F/T bias, the clock offsets of
the mocap and F/T streams against the camera, and a correction of the mocap-to-sensor extrinsic.

A recording from the rig (or the twin's world "rig", tools/twin/world.py) carries a calibrated but
imperfect mocap extrinsic, an F/T with a bias, and three clocks. Nothing here reads truth/:

- **F/T bias**: the median reading of each indenter's F/T while its tip is at least `rest_clearance_mm`
  above the gel's rest surface (mocap), i.e. the tare a rig does at rest.
- **Clock offsets** by least-squares alignment (`clock_lag`, cross-correlation generalised to a curved
  monotone relation): the image's change from the first frame against the F/T's |F| and a low-passed
  |F| (the gel skin's slow part, `image_slow_tau_s`) gives the F/T clock; each indenter's normal load
  against its tip's signed penetration of the rest surface gives the mocap clock against the F/T.
  Sub-sample lag by a parabola through the best three.
- **Extrinsic translation, lateral** from contact onsets (`fit_translation`): where |F| first rises
  above `onset_n`, the tip touches the rest surface; the lateral shift (δx, δy) and the mean onset
  depth b that put these points on the cap's sphere. Not estimated: δz (near the apex it moves the
  onsets exactly as the onset depth does) and the extrinsic's rotation (a rotation about the cap
  sphere's centre leaves the dome unchanged; it would need image correspondences); what the shift
  cannot absorb stays as a residual error. An onset whose tip lies farther than `onset_gate_mm` from the
  rest surface as recorded is no first touch (F/T noise or a second module's load) and is left out; the
  fit is robust (soft-L1, `ONSET_FSCALE_MM`) and bounded (|δ| ≤ `max_shift_mm`, b within
  `onset_depth_bounds_mm`), and a fit that ends on a bound leaves the extrinsic as recorded (one such
  outlier onset, 4 mm above the gel, had thrown an unbounded fit 32 mm sideways).
- **Not estimated**: F/T cross-talk (needs a reference load), the unit's gel geometry and stiffness
  (the calibration stage's and the label budget's business).

`estimate(session)` returns the residuals; `write(session_dir, est)` folds them into the session's
manifest (`streams.<name>.clock_offset_s`, `streams.wrench.bias`, `streams.poses.mocap_to_sensor`,
applied by contracts.session.Session.table) and keeps the record in `provenance.rig_estimate`.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ...contracts.errors import SessionError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RigEstimateConfig:
    rest_clearance_mm: float = 2.0       # a tip this far above the rest surface is at rest (F/T tare)
    onset_n: float = 0.1                 # |F| above this (after the tare) = in contact
    onset_quiet_s: float = 0.2           # ... after at least this long below it
    max_lag_s: float = 0.1               # clock offsets searched within ± this
    image_slow_tau_s: float = 1.0        # the gel skin's slow recovery (a regressor of the image change)
    grid_s: float = 0.001                # common time grid of the cross-correlations
    min_onsets: int = 6                  # fewer contact onsets: the extrinsic is left as recorded
    onset_gate_mm: float = 1.5           # an onset tip farther than this from the rest surface is no first touch
    max_shift_mm: float = 2.0            # |δx|, |δy| bound: a larger extrinsic error is a rig fault, not a residual
    onset_depth_bounds_mm: tuple = (-1.0, 1.0)   # the mean onset depth b's bounds (mm inward)


# ------------------------------------------------------------------------------------- pure cores

def clock_lag(groups: list, max_lag_s: float = 0.1, grid_s: float = 0.001) -> float:
    """δ (s) by which a signal's stamps run late: each group (t_ref, ref, t_sig, [sig, ...]) says that
    ref(t) ≈ a + Σ_i (b_i x_i + c_i x_i²) with x_i = sig_i(t + δ) (linear interpolation). δ minimises the
    summed least-squares residual of the groups (each with its own coefficients) over lags on a grid of
    `grid_s` within ±max_lag_s, refined by a parabola through the best three. For one regressor and
    no quadratic term this is the peak of the normalised cross-correlation; the quadratic term and a
    group per indenter let a monotone but curved relation (force against penetration) align too."""
    steps = int(round(max_lag_s / grid_s))
    lags = np.arange(-steps, steps + 1) * grid_s
    sse = np.zeros(len(lags))
    for t_ref, ref, t_sig, sigs in groups:
        t_ref, ref, t_sig = (np.asarray(v, np.float64) for v in (t_ref, ref, t_sig))
        if len(t_ref) < 8:
            continue
        for i, L in enumerate(lags):
            cols = [np.ones(len(t_ref))]
            for sg in sigs:
                x = np.interp(t_ref + L, t_sig, np.asarray(sg, np.float64))
                cols += [x, x * x]
            A = np.stack(cols, 1)
            coef = np.linalg.lstsq(A, ref, rcond=None)[0]
            sse[i] += float(np.sum((A @ coef - ref) ** 2))
    if not np.any(sse):
        raise ValueError("clock_lag: no group with at least 8 samples")
    i = int(np.argmin(sse))
    frac = 0.0
    if 0 < i < len(sse) - 1:
        den = sse[i - 1] - 2 * sse[i] + sse[i + 1]
        frac = 0.5 * (sse[i - 1] - sse[i + 1]) / den if den > 0 else 0.0
    return float(lags[i] + frac * grid_s)


def lowpass(x: np.ndarray, dt: float, tau: float) -> np.ndarray:
    """First-order low-pass (time constant tau, samples dt apart), starting at x[0]."""
    from scipy.signal import lfilter

    a = np.exp(-dt / tau)
    x = np.asarray(x, np.float64)
    return lfilter([1.0 - a], [1.0, -a], x, zi=[a * x[0]])[0]


ONSET_FSCALE_MM = 0.1   # soft-L1 scale of the onset fit's residuals (mm)


def near_surface(points: np.ndarray, center_z: float, radius: float, gate_mm: float) -> np.ndarray:
    """(N,) bool: onset tips within gate_mm of the cap sphere (centre (0, 0, center_z), radius ρ)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    return np.abs(np.linalg.norm(p - [0.0, 0.0, center_z], axis=1) - radius) <= gate_mm


def fit_translation(points: np.ndarray, center_z: float, radius: float, max_shift: float = np.inf,
                    depth_bounds: tuple = (-np.inf, np.inf)) -> tuple[np.ndarray, float, bool]:
    """(δ (3,), b, on_bound): the lateral shift (δx, δy; δz = 0) and the mean inward depth b that put
    contact-onset points on the cap sphere (centre (0, 0, center_z), radius ρ): robust (soft-L1) least
    squares of |p − δ − c| − (ρ − b), with |δx|, |δy| ≤ max_shift and b within depth_bounds; on_bound
    says the solution sits on one of the bounds (then it is not an estimate). The corrected positions
    are p − δ. δz is not fitted: onsets near the apex move with δz exactly as with the onset depth b,
    so the two cannot be told apart."""
    from scipy.optimize import least_squares

    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 3:
        raise ValueError(f"fit_translation: expected (N >= 3, 3) points, got {p.shape}")
    c = np.array([0.0, 0.0, center_z])

    def res(x):
        return np.linalg.norm(p - [x[0], x[1], 0.0] - c, axis=1) - (radius - x[2])

    lo = np.array([-max_shift, -max_shift, depth_bounds[0]], float)
    hi = np.array([max_shift, max_shift, depth_bounds[1]], float)
    x0 = np.clip(np.zeros(3), lo + 1e-9, hi - 1e-9)
    sol = least_squares(res, x0, bounds=(lo, hi), loss="soft_l1", f_scale=ONSET_FSCALE_MM)
    width = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    on_bound = bool(np.any((np.isfinite(lo) & (sol.x - lo < 1e-6 * width)) | (np.isfinite(hi) & (hi - sol.x < 1e-6 * width))))
    return np.array([sol.x[0], sol.x[1], 0.0]), float(sol.x[2]), on_bound


def contact_onsets(t: np.ndarray, force: np.ndarray, threshold: float, quiet_s: float) -> np.ndarray:
    """Times where |F| (T,) rises above `threshold` after at least `quiet_s` below it (linear
    interpolation of the crossing between samples)."""
    t, f = np.asarray(t, np.float64), np.asarray(force, np.float64)
    above = f > threshold
    out, last_above = [], -np.inf
    for i in range(1, len(t)):
        if above[i] and not above[i - 1]:
            if t[i - 1] - last_above >= quiet_s:
                s = (threshold - f[i - 1]) / max(f[i] - f[i - 1], 1e-12)
                out.append(t[i - 1] + s * (t[i] - t[i - 1]))
        if above[i]:
            last_above = t[i]
    return np.asarray(out)


# ------------------------------------------------------------------------------------- the shell

def _per_indenter(table: np.ndarray) -> dict[int, np.ndarray]:
    return {int(k): table[table[:, 1] == k] for k in np.unique(table[:, 1])}


def image_activity(session) -> tuple[np.ndarray, np.ndarray]:
    """(t, mean |grey − first grey|) of the camera frames: how much the gel image has changed."""
    import cv2

    from ..sessions.writer import read_frames

    t = session.table("frames")[:, 0]
    first, act = None, []
    for _, img in read_frames(session):
        g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32) if img.ndim == 3 else img.astype(np.float32)
        first = g if first is None else first
        act.append(float(np.mean(np.abs(g - first))))
    return t[:len(act)], np.asarray(act)


def estimate(session, cfg: RigEstimateConfig = RigEstimateConfig(), gel=None) -> dict:
    """Residual rig calibration of a session (read as Session.table gives it, i.e. with the calibration
    its manifest already holds): {"bias": {indenter: 6}, "clock_offset_s": {"wrench", "poses"},
    "mocap_translation_mm": 3 or None, "onset_depth_mm", "onsets"}."""
    from ..twin.geometry import GelSurface

    gel = gel or GelSurface()
    prof = gel.profile
    c = np.array([0.0, 0.0, prof.center_z_mm])
    if not (session.has("poses") and session.has("wrench")):
        raise SessionError(f"{session.path}: a rig estimate needs the poses and wrench streams")
    poses, wrench = _per_indenter(session.table("poses")), _per_indenter(session.table("wrench"))

    def clearance(rows):
        return np.linalg.norm(rows[:, 2:5] - c, axis=1) - prof.radius_mm

    bias = {}
    for k, w in wrench.items():
        p = poses[k]
        rest = np.interp(w[:, 0], p[:, 0], clearance(p)) > cfg.rest_clearance_mm
        if rest.sum() < 10:
            raise SessionError(f"{session.path}: indenter {k} is never {cfg.rest_clearance_mm} mm clear of the gel; "
                               "no rest readings to tare its F/T")
        bias[k] = np.median(w[rest, 2:8], axis=0)
    # F/T against the camera: the image's change from the first frame against |F| and its slow part (the
    # gel skin recovers slowly, image_slow_tau_s), all indenters together
    t_w = wrench[min(wrench)][:, 0]
    f_abs = sum(np.linalg.norm(w[:, 2:5] - bias[k][:3], axis=1) for k, w in wrench.items())
    dt = float(np.median(np.diff(t_w)))
    t_c, img = image_activity(session)
    d_ft = clock_lag([(t_c, img, t_w, [f_abs, lowpass(f_abs, dt, cfg.image_slow_tau_s)])], cfg.max_lag_s, cfg.grid_s)
    # mocap against the F/T, per indenter: the normal load (F/T z = the indenter's axis) in contact against
    # the tip's signed penetration of the rest surface
    groups = []
    for k, w in wrench.items():
        fz = np.abs(w[:, 4] - bias[k][2])
        sel = fz > cfg.onset_n
        groups.append((w[sel, 0], fz[sel], poses[k][:, 0], [-clearance(poses[k])]))
    d_pm = clock_lag(groups, cfg.max_lag_s, cfg.grid_s)
    clocks = {"wrench": d_ft, "poses": d_ft + d_pm}
    # contact onsets on the camera clock: F/T crossing time → tip position from the mocap
    pts = []
    for k, w in wrench.items():
        tk = w[:, 0] - d_ft
        for t0 in contact_onsets(tk, np.linalg.norm(w[:, 2:5] - bias[k][:3], axis=1), cfg.onset_n, cfg.onset_quiet_s):
            p = poses[k]
            tp = p[:, 0] - clocks["poses"]
            q = np.array([np.interp(t0, tp, p[:, j]) for j in (2, 3, 4)])
            if q[2] > gel.skirt and near_surface(q, prof.center_z_mm, prof.radius_mm, cfg.onset_gate_mm)[0]:
                pts.append(q)
    shift, depth = None, None
    if len(pts) >= cfg.min_onsets:
        shift, depth, on_bound = fit_translation(np.asarray(pts), prof.center_z_mm, prof.radius_mm,
                                                 cfg.max_shift_mm, tuple(cfg.onset_depth_bounds_mm))
        if on_bound:
            log.warning("%s: the onset fit ended on a bound (shift %s mm, onset depth %.2f mm): mocap extrinsic "
                        "left as recorded", session.path, np.round(shift[:2], 2).tolist(), depth)
            shift, depth = None, None
    else:
        log.warning("%s: %d contact onsets (< %d): mocap extrinsic left as recorded", session.path, len(pts),
                    cfg.min_onsets)
    return {"bias": {str(k): [float(v) for v in b] for k, b in bias.items()},
            "clock_offset_s": {k: float(v) for k, v in clocks.items()},
            "mocap_translation_mm": None if shift is None else [float(v) for v in shift],
            "onset_depth_mm": depth, "onsets": len(pts), "config": asdict(cfg)}


def write(session_dir: str | Path, est: dict) -> dict:
    """Fold a residual estimate into the session's manifest (each value composed with what it already
    holds) and record it under provenance.rig_estimate; returns the new manifest."""
    from ...contracts.session import load_session, write_manifest

    ses = load_session(session_dir, check_frames=False)
    man = dict(ses.manifest)
    streams = {k: dict(v) for k, v in man["streams"].items()}
    prev = {n: {k: streams[n].get(k) for k in ("clock_offset_s", "bias", "mocap_to_sensor") if k in streams[n]}
            for n in ("poses", "wrench")}
    for name in ("poses", "wrench"):
        streams[name]["clock_offset_s"] = float(streams[name].get("clock_offset_s", 0.0)) + est["clock_offset_s"][name]
    old = streams["wrench"].get("bias", {})
    streams["wrench"]["bias"] = {k: [float(x) for x in np.asarray(old.get(k, [0.0] * 6)) + np.asarray(b)]
                                 for k, b in est["bias"].items()}
    if est.get("mocap_translation_mm") is not None and streams["poses"].get("frame") == "mocap":
        ext = dict(streams["poses"]["mocap_to_sensor"])
        ext["translation_mm"] = [float(v) for v in np.asarray(ext["translation_mm"]) - est["mocap_translation_mm"]]
        streams["poses"]["mocap_to_sensor"] = ext
    man["streams"] = streams
    man["provenance"] = {**man.get("provenance", {}), "rig_estimate": {**est, "previous": prev}}
    write_manifest(Path(session_dir), man)
    return man


def prepare(session_dir: str | Path) -> dict:
    """A rig-world session, as a rig would prepare it: the estimate folded into its manifest once (a
    session that holds one is left as it is); returns the clock offsets, the extrinsic shift and the
    onset count."""
    from ...contracts.session import load_session

    ses = load_session(session_dir)
    done = ses.manifest.get("provenance", {}).get("rig_estimate")
    if done is None:
        done = estimate(ses)
        write(session_dir, done)
    return {k: done[k] for k in ("clock_offset_s", "mocap_translation_mm", "onsets")}


def add_arguments(p) -> None:
    p.add_argument("session", help="session folder (poses, wrench and frames)")
    p.add_argument("--write", action="store_true",
                   help="fold the estimate into the session's manifest (clock offsets, F/T bias, mocap extrinsic)")


def run(args) -> int:
    import json

    from ...contracts.session import load_session

    est = estimate(load_session(args.session))
    if args.write:
        write(args.session, est)
    print(json.dumps({k: v for k, v in est.items() if k != "config"}, indent=1))
    print(f"{'written into' if args.write else 'not written (--write)'}: {Path(args.session) / 'session.json'}")
    return 0
