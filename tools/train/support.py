"""The package's contact support and merging: how far a contact's force reaches beyond its core, and
which cores are one contact; measured at export.

The runtime grows each cluster core onto weaker pixels nearby (ContactConfig.support_radius_px /
support_floor_n) so the cluster's force includes the tails the core threshold cuts off. How far those
tails reach depends on the network: the shipped model paints a sliding contact's shear as a broad, low
haze, and with the default 10 px / 0.0001 N the matched cluster held 0.73 N of a 0.97 N image-integral
shear (F/T: 1.20 N) on held-out slide units (docs/history/BENCHMARKS-sessions-1-16.md "Contact support and merging"). Measured
only on request (ThresholdConfig.measure_support, `--support`): a farther support moved the
recalibration's errors under the nominal crop (docs/model_package.md "Support").

With `--support` it is measured per package, in the same pass as the core threshold (tools/train/threshold.py):
on training-session frames where exactly one indenter touches (measured |F| > `contact_n`, every other
below the rest level), each candidate (radius, floor) clusters the package's own fields with the
package's threshold and light-touch rule; the cluster nearest the indenter's tip is compared with the
F/T (|F_cluster − F_measured|, a missed contact counts its whole force). The first candidate (smallest
reach) whose mean error is within `margin` of the best wins.

Merging (ContactConfig.merge_n): while sliding, the shipped model splits one contact's field into two
peaks, and the runtime published a second, phantom contact ~3.1 mm from the first on 11 % of single-contact
frames of slide units (docs/history/BENCHMARKS-sessions-1-16.md "Contact support and merging"). Cores joined by pixels above merge_n are one
cluster. Chosen first, on the same frames plus the frames where two indenters touch: among `merge_fractions`
of the core threshold (0 = off), the one with the fewest phantom frames (an extra cluster above
`phantom_n`) that keeps two real contacts apart (each tip's nearest cluster its own) on at least as many
two-contact frames as no merging does, less `separation_slack`.
Splitting (ContactConfig.split_dip): two presses close together join into one core whose field dips between
their peaks, at any threshold that still finds light touches. Chosen after merging, on the same frames: among
`split_dips` (0 = off), the one keeping the most two-contact frames apart while single-contact frames with a
phantom rise by at most `split_phantom_slack`.
Pure core: `support_sample`, `two_sample`, `score`, `merge_counts`, `choose_merge`, `choose_split`,
`choose_support`.
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
    merge_fractions: tuple = (0.0, 0.6, 0.4)   # merge_n candidates as fractions of the core threshold (0 = off)
    phantom_n: float = 0.05         # an extra cluster above this (N) on a single-contact frame is a phantom
    separation_slack: float = 0.01  # two-contact frames kept apart may drop by at most this fraction
    split_dips: tuple = (0.0, 0.8, 0.7, 0.6, 0.5, 0.4)   # split_dip candidates, least splitting first (0 = off)
    split_phantom_slack: float = 0.005  # single-contact frames with a phantom may rise by at most this fraction


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


def two_sample(fp: np.ndarray, tips: np.ndarray, forces: np.ndarray, cfg: SupportConfig = SupportConfig()) -> dict | None:
    """One frame's sample when exactly two indenters touch (> contact_n), else None."""
    mags = np.linalg.norm(np.asarray(forces, dtype=np.float64), axis=1)
    on = np.flatnonzero(mags > cfg.contact_n)
    if len(on) != 2:
        return None
    return {"fp": np.asarray(fp, dtype=np.float32), "tips": np.asarray(tips, float)[on]}


def _clusters(fp, cal, cc):
    from ...runtime.stages.contacts import find_clusters

    return find_clusters(fp, cal.surface_xyz, cal.normals, cal.pixel_area, cal.mask, cfg=cc)


def _nearest(cl, tip) -> int:
    return min(range(len(cl)), key=lambda j: float(np.linalg.norm(np.asarray(cl[j].position_mm) - tip)))


def merge_counts(single: list[dict], single_cals: list, two: list[dict], two_cals: list, contacts,
                 cfg: SupportConfig = SupportConfig()) -> tuple[int, int]:
    """(single-contact frames with a phantom cluster, two-contact frames whose tips own distinct clusters)."""
    phantom = 0
    for s, cal in zip(single, single_cals):
        cl = _clusters(s["fp"], cal, contacts)
        if len(cl) > 1:
            j = _nearest(cl, s["tip"])
            phantom += any(c.force_mag_n > cfg.phantom_n for i, c in enumerate(cl) if i != j)
    apart = 0
    for s, cal in zip(two, two_cals):
        cl = _clusters(s["fp"], cal, contacts)
        apart += len(cl) > 1 and _nearest(cl, s["tips"][0]) != _nearest(cl, s["tips"][1])
    return phantom, apart


def choose_merge(single, single_cals, two, two_cals, contacts, cfg: SupportConfig = SupportConfig()) -> dict:
    """{"merge_n", "measured": {...}}; None (off) without single-contact samples."""
    if not single:
        return {"merge_n": None, "measured": {}}
    values = [round(f * contacts.threshold_n, 6) for f in cfg.merge_fractions]
    counts = [merge_counts(single, single_cals, two, two_cals, replace(contacts, merge_n=v), cfg) for v in values]
    off_apart = counts[0][1]
    ok = [i for i, (_, a) in enumerate(counts) if a >= off_apart - cfg.separation_slack * len(two)]
    best = min(ok, key=lambda i: (counts[i][0], i))          # fewest phantoms; ties: the earlier (less merging)
    return {"merge_n": float(values[best]) if values[best] > 0 else None,
            "measured": {"merge_rule": f"fewest single-contact frames with an extra cluster > {cfg.phantom_n} N, keeping "
                                       f"two-contact frames apart within {100 * cfg.separation_slack:.0f} % of no merging",
                         "merge_candidates_n": values, "merge_phantom_frames": [c[0] for c in counts],
                         "merge_two_apart_frames": [c[1] for c in counts], "merge_single_frames": len(single),
                         "merge_two_frames": len(two)}}


def choose_split(single, single_cals, two, two_cals, contacts, cfg: SupportConfig = SupportConfig()) -> dict:
    """{"split_dip", "measured": {...}}; None (off) without two-contact samples. With the merging already
    chosen (in `contacts`): among `split_dips`, the one keeping the most two-contact frames apart whose
    single-contact frames with a phantom stay within `split_phantom_slack` of no splitting; ties: the
    earlier (less splitting)."""
    if not two:
        return {"split_dip": None, "measured": {}}
    counts = [merge_counts(single, single_cals, two, two_cals, replace(contacts, split_dip=d), cfg)
              for d in cfg.split_dips]
    off_phantom = counts[0][0]
    ok = [i for i, (ph, _) in enumerate(counts) if ph <= off_phantom + cfg.split_phantom_slack * len(single)]
    best = max(ok, key=lambda i: (counts[i][1], -i))
    return {"split_dip": float(cfg.split_dips[best]) if cfg.split_dips[best] > 0 else None,
            "measured": {"split_rule": f"most two-contact frames kept apart, single-contact frames with an extra "
                                       f"cluster > {cfg.phantom_n} N within {100 * cfg.split_phantom_slack:.3g} % of "
                                       f"no splitting",
                         "split_candidates": list(cfg.split_dips), "split_phantom_frames": [c[0] for c in counts],
                         "split_two_apart_frames": [c[1] for c in counts]}}


def score(samples: list[dict], calibrations: list, contacts, radius: float, floor: float) -> float:
    """Mean |F_cluster − F_measured| (N) over samples with the given support; samples[i] uses calibrations[i]."""
    cc = replace(contacts, support_radius_px=float(radius), support_floor_n=float(floor))
    errs = []
    for s, cal in zip(samples, calibrations):
        cl = _clusters(s["fp"], cal, cc)
        if not cl:
            errs.append(float(np.linalg.norm(s["force"])))
            continue
        c = cl[_nearest(cl, s["tip"])]
        errs.append(float(np.linalg.norm(np.asarray(c.force_n) - s["force"])))
    return float(np.mean(errs)) if errs else float("nan")


def choose_support(samples: list[dict], calibrations: list, contacts, cfg: SupportConfig = SupportConfig()) -> dict:
    """{"support_radius_px", "support_floor_n", "measured": {...}}; both None (runtime
    default) when there are no samples."""
    if not samples:
        return {"support_radius_px": None, "support_floor_n": None,
                "measured": {"support_frames": 0}}
    errs = [score(samples, calibrations, contacts, r, f) for r, f in cfg.candidates]
    best = float(np.nanmin(errs))
    k = next(i for i, e in enumerate(errs) if e <= best * (1.0 + cfg.margin))
    r, f = cfg.candidates[k]
    return {"support_radius_px": float(r), "support_floor_n": float(f),
            "measured": {"support_rule": f"smallest reach whose mean |F_cluster - F_measured| over single-contact "
                                         f"frames (|F| > {cfg.contact_n} N) is within {100 * cfg.margin:.0f} % of the best",
                         "support_candidates": [list(c) for c in cfg.candidates],
                         "support_error_n": [round(e, 5) for e in errs], "support_frames": len(samples)}}
