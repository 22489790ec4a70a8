"""Stage 4 — sim-to-real force calibration (seed §III.I).

The FE runs the nominal gel; the real (or twin) sensor's gel is stiffer or softer, so the measured
force differs from the FE reaction by a ratio. Per session, per indenter and per force component,

    r_i = F_meas,i / F_FE,i             (F_meas: the measured force the indenter applies to the gel,
                                          tools.scoring.measured_at; F_FE: FE reaction RF, the
                                          force the indenter applies)

fitted by least squares over the keypoint frames in contact (Σ F_m·F_FE / Σ F_FE²), and applied to
the contact normal/shear force of the nodes each indenter touches. A component whose FE force is too
small to define a ratio (e.g. x of a straight press) takes the indenter's magnitude ratio.

Pure cores: `fit_ratios`, `slot_ratios`, `apply_ratios`. Shell: `session_ratios`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ...contracts.errors import SessionError, TensorTouchError
from ..scoring import measured_at

log = logging.getLogger(__name__)


class SimRealError(TensorTouchError):
    """Sim-to-real ratios cannot be computed (no contact, mismatched arrays)."""


@dataclass(frozen=True)
class SimRealConfig:
    min_force_n: float = 1.5              # seed §III.C contact threshold: only frames above it count
    min_component_share: float = 0.15     # component needs ≥ this share of the RMS FE force
    ratio_range: tuple[float, float] = (0.5, 2.0)   # physically plausible stiffness ratios


def fit_ratios(measured: np.ndarray, rf_fe: np.ndarray, cfg: SimRealConfig = SimRealConfig()) -> dict:
    """Per-component ratios (3,) and the magnitude ratio from matched samples (T, 3) of one indenter:
    `measured` the force it applies to the gel (tools.scoring.measured_at's sign, = RF's sign)."""
    fs = np.asarray(measured, float).reshape(-1, 3)
    fe = np.asarray(rf_fe, float).reshape(-1, 3)
    if fs.shape != fe.shape:
        raise SimRealError(f"fit_ratios: measured {fs.shape} and FE {fe.shape} samples differ")
    sel = np.linalg.norm(fe, axis=1) >= cfg.min_force_n
    if sel.sum() == 0:
        raise SimRealError(f"fit_ratios: no sample with FE force ≥ {cfg.min_force_n} N")
    fs, fe = fs[sel], fe[sel]
    lo, hi = cfg.ratio_range
    mag = float(np.clip(np.sum(np.linalg.norm(fs, axis=1) * np.linalg.norm(fe, axis=1))
                        / np.sum(np.linalg.norm(fe, axis=1) ** 2), lo, hi))
    rms = np.sqrt(np.mean(np.sum(fe ** 2, axis=1)))
    comp = np.full(3, mag)
    used = np.zeros(3, bool)
    for c in range(3):
        if np.sqrt(np.mean(fe[:, c] ** 2)) >= cfg.min_component_share * rms:
            comp[c] = float(np.clip(np.sum(fs[:, c] * fe[:, c]) / np.sum(fe[:, c] ** 2), lo, hi))
            used[c] = True
    return {"ratio": comp.tolist(), "magnitude": mag, "component_fitted": used.tolist(), "samples": int(sel.sum())}


def slot_ratios(ratios: dict | None, slots: list) -> np.ndarray:
    """(K, 3) ratios of the indenters `slots` from {slot: {"ratio": (3,)}}; 1 where a slot has none."""
    return np.array([(ratios or {}).get(int(sl), {"ratio": [1.0] * 3})["ratio"] for sl in slots], float)


def apply_ratios(force: np.ndarray, owner: np.ndarray, ratios: np.ndarray) -> np.ndarray:
    """Scale per-node contact forces (N, 3) by the ratios (K, 3) of the indenter that owns each node
    (owner (N,) ∈ [0, K) or −1 for no contact: unchanged, which is zero force anyway)."""
    force = np.asarray(force, float)
    owner = np.asarray(owner, int)
    ratios = np.asarray(ratios, float).reshape(-1, 3)
    scale = np.ones_like(force)
    ok = (owner >= 0) & (owner < len(ratios))
    scale[ok] = ratios[owner[ok]]
    return force * scale


def session_ratios(session, plan, slot_of_poke, rf_fe_per_poke, cfg: SimRealConfig = SimRealConfig()) -> dict:
    """Ratios per indentation module (session indenter id) of one session.

    session: contracts.session.Session; plan: list of twin Poke (keypoint times); slot_of_poke[p][k]:
    the session indenter id of the poke's k-th indenter; rf_fe_per_poke[p]: (J, K, 3) FE reactions at the
    poke's keypoints. The measured force at each keypoint time is tools.scoring.measured_at's."""
    per_slot: dict[int, tuple[list, list]] = {}
    for poke, slots, rf in zip(plan, slot_of_poke, rf_fe_per_poke):
        t = np.asarray(poke.times, float)
        for k, slot in enumerate(slots):
            try:
                fs = measured_at(session, t, indenters=[slot])[int(slot)]["force"]
            except SessionError:      # an indenter without enough wrench/pose samples
                continue
            a, b = per_slot.setdefault(int(slot), ([], []))
            a.append(fs)
            b.append(np.asarray(rf)[:, k])
    out, failed = {}, []
    for slot, (a, b) in sorted(per_slot.items()):
        try:
            out[slot] = fit_ratios(np.concatenate(a), np.concatenate(b), cfg)
        except SimRealError as exc:
            failed.append((slot, str(exc)))
    # an indenter without usable contacts takes the session's mean magnitude ratio (same gel), else 1
    mean = float(np.mean([v["magnitude"] for v in out.values()])) if out else 1.0
    for slot, why in failed:
        log.warning("sim-to-real: indenter %d: %s; using the session's mean ratio %.3f", slot, why, mean)
        out[slot] = {"ratio": [mean] * 3, "magnitude": mean, "component_fitted": [False] * 3, "samples": 0,
                     "fallback": "session mean"}
    return dict(sorted(out.items()))
