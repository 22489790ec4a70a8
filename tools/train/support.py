"""The package's contact support: how far a contact's force reaches beyond its core, measured at export.

The runtime grows each cluster core onto weaker pixels nearby (ContactConfig.support_radius_px /
support_floor_n) so the cluster's force includes the tails the core threshold cuts off. How far those
tails reach depends on the network: the shipped model paints a sliding contact's shear as a broad, low
haze, and with the default 10 px / 0.0001 N the matched cluster held 0.73 N of a 0.97 N image-integral
shear (F/T: 1.20 N) on held-out slide units (docs/BENCHMARKS.md "Contact support").

So the support is measured per package, in the same pass as the core threshold (tools/train/threshold.py):
on training-session frames where exactly one indenter touches (measured |F| > `contact_n`, every other
below the rest level), each candidate (radius, floor) clusters the package's own fields with the
package's threshold and light-touch rule; the cluster nearest the indenter's tip is compared with the
F/T (|F_cluster − F_measured|, a missed contact counts its whole force). The first candidate (smallest
reach) whose mean error is within `margin` of the best wins. Pure core: `support_sample`, `score`, `choose_support`.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class SupportConfig:
    # (radius px, floor N per pixel), smallest reach first; the first is ContactConfig's default
    candidates: tuple = ((10.0, 1e-4), (15.0, 0.0), (20.0, 0.0), (30.0, 0.0), (40.0, 0.0))
    contact_n: float = 0.2          # a support frame: one indenter above this (N) ...
    frames_per_session: int = 150   # ... every `stride`-th such frame, at most this many per session
    stride: int = 2
    margin: float = 0.02            # relative: a farther reach must lower the mean error by more than this


def support_sample(fp: np.ndarray, tips: np.ndarray, forces: np.ndarray, rest_n: float,
                   cfg: SupportConfig = SupportConfig()) -> dict | None:
    """One frame's sample (pixel forces (3, H, W) N, tip mm, measured force N) when exactly one indenter
    touches, else None."""
    mags = np.linalg.norm(np.asarray(forces, dtype=np.float64), axis=1)
    on = mags > cfg.contact_n
    if on.sum() != 1 or (mags > rest_n).sum() != 1:
        return None
    j = int(np.argmax(mags))
    return {"fp": np.asarray(fp, dtype=np.float32), "tip": np.asarray(tips[j], float), "force": np.asarray(forces[j], float)}


def score(samples: list[dict], calibrations: list, contacts, radius: float, floor: float) -> float:
    """Mean |F_cluster − F_measured| (N) over samples with the given support; samples[i] uses calibrations[i]."""
    from runtime.contacts import find_clusters

    cc = replace(contacts, support_radius_px=float(radius), support_floor_n=float(floor))
    errs = []
    for s, cal in zip(samples, calibrations):
        cl = find_clusters(s["fp"], cal.surface_xyz, cal.normals, cal.pixel_area, cal.mask, cfg=cc)
        if not cl:
            errs.append(float(np.linalg.norm(s["force"])))
            continue
        c = min(cl, key=lambda c: float(np.linalg.norm(np.asarray(c.centroid_mm) - s["tip"])))
        errs.append(float(np.linalg.norm(np.asarray(c.force_n) - s["force"])))
    return float(np.mean(errs)) if errs else float("nan")


def choose_support(samples: list[dict], calibrations: list, contacts, cfg: SupportConfig = SupportConfig()) -> dict:
    """{"contact_support_radius_px", "contact_support_floor_n", "measured": {...}}; both None (runtime
    default) when there are no samples."""
    if not samples:
        return {"contact_support_radius_px": None, "contact_support_floor_n": None,
                "measured": {"support_frames": 0}}
    errs = [score(samples, calibrations, contacts, r, f) for r, f in cfg.candidates]
    best = float(np.nanmin(errs))
    k = next(i for i, e in enumerate(errs) if e <= best * (1.0 + cfg.margin))
    r, f = cfg.candidates[k]
    return {"contact_support_radius_px": float(r), "contact_support_floor_n": float(f),
            "measured": {"support_rule": f"smallest reach whose mean |F_cluster - F_measured| over single-contact "
                                         f"frames (|F| > {cfg.contact_n} N) is within {100 * cfg.margin:.0f} % of the best",
                         "support_candidates": [list(c) for c in cfg.candidates],
                         "support_error_n": [round(e, 5) for e in errs], "support_frames": len(samples)}}
