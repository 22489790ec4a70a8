"""Held-out evaluation on a recording: every poke's force magnitude, with and without a correction.

Replays a session (real or twin) through the runtime (runtime.offline.replay_session) with a given calibration version and
pairs the sensor's force with the recording's force stream, one row per poke. Two pairings:
- `gauge_pokes` (the default): the pokes are the reference's (episodes of the gauge force), so every
  calibration is scored on the same pokes, and a poke the sensor missed or split counts with the
  force it reported (0 N when nothing);
- `pair_pokes`: the pokes the sensor detected (tools.recalib.pokes, single contact only), as the
  guided session sees them; a calibration that misses a poke is not charged for it.
Used by the twin end-to-end test and benchmark.
"""
from __future__ import annotations

import logging

import numpy as np

from ...contracts.session import load_session
from ...contracts.store import Calibration
from ...runtime.offline import replay_session
from ...runtime.stages.correction import ForceCorrection
from ...runtime.stages.model import ModelPackage
from .pokes import PokeDetector, PokeRules
from .session import StreamReference

log = logging.getLogger(__name__)


def measure_pokes(session_dir, cal: Calibration, package: ModelPackage, corrected: bool,
                  rules: PokeRules = PokeRules(), precision: str = "int8", by: str = "gauge") -> dict:
    """{'pred': (N,) |F| the runtime reports, 'ref': (N,) reference |F|} per poke; `by` "gauge" (the
    reference's pokes) or "detected" (the single-contact pokes the sensor detected)."""
    session = load_session(session_dir)
    ref = StreamReference.from_session(session, rules)
    corr = None if corrected else ForceCorrection(None, None)
    frames = [(r.t, r.clusters) for r in replay_session(session, package, cal, precision=precision, correction=corr)]
    return gauge_pokes(frames, ref, rules) if by == "gauge" else pair_pokes(frames, ref, rules)


def pair_pokes(frames, reference, rules: PokeRules) -> dict:
    """{'pred', 'ref'} for the single-contact pokes of a (t, clusters) sequence: each poke the detector
    closes, unless a second contact was too strong, paired with the reference |F| above min_force_n."""
    det, pred, refs = PokeDetector(rules), [], []
    for t, clusters in frames:
        poke = det.feed(t, clusters)
        if poke is None or poke.second_ratio > rules.second_contact_ratio:
            continue
        r = reference.for_poke(poke)
        if r is not None and r >= rules.min_force_n:
            pred.append(poke.pred_mag)
            refs.append(r)
    return {"pred": np.array(pred), "ref": np.array(refs)}


def gauge_episodes(reference, rules: PokeRules = PokeRules(), gap_s: float = 0.1) -> list[tuple]:
    """(plateau start s, plateau end s, plateau mean |F| N) of every poke in a reference stream
    (tools.recalib.session.StreamReference): per indenter, a run of readings at or above
    rules.contact_floor_n (runs closer than `gap_s` joined); its plateau is the readings within
    rules.plateau_fraction of the run's peak. Runs whose plateau mean is outside
    [min_force_n, max_force_n] are left out (too light to score, or out of range)."""
    out = []
    for k in np.unique(reference.ind):
        t, f = reference.t[reference.ind == k], reference.mag[reference.ind == k]
        on = np.flatnonzero(f >= rules.contact_floor_n)
        if not len(on):
            continue
        breaks = np.flatnonzero(np.diff(t[on]) > gap_s)
        for run in np.split(on, breaks + 1):
            ft, ff = t[run], f[run]
            top = ff >= rules.plateau_fraction * ff.max()
            ref = float(ff[top].mean())
            if rules.min_force_n <= ref <= rules.max_force_n:
                out.append((float(ft[top].min()), float(ft[top].max()), ref))
    return sorted(out)


def gauge_pokes(frames: list, reference, rules: PokeRules = PokeRules()) -> dict:
    """{'pred', 'ref'} per reference poke (`gauge_episodes`): pred = |plateau mean| of the sensor's main
    contact force (strongest cluster plus its parts within rules.merge_radius_mm, as the guided session
    merges them; 0 on frames without a cluster) over the frames inside the poke's plateau (the nearest
    frame when none is). frames: [(t, clusters)] in time order."""
    from .pokes import merge_main

    ts = np.array([t for t, _ in frames], float)
    pred, refs = [], []
    for t0, t1, ref in gauge_episodes(reference, rules):
        idx = np.flatnonzero((ts >= t0) & (ts <= t1))
        if not len(idx):
            idx = [int(np.argmin(np.abs(ts - 0.5 * (t0 + t1))))] if len(ts) else []
        forces = []
        for i in idx:
            strong = sorted((c for c in frames[i][1] if c.force_mag_n >= rules.contact_floor_n),
                            key=lambda c: c.force_mag_n, reverse=True)
            forces.append(merge_main(strong, rules.merge_radius_mm)[0] if strong else np.zeros(3))
        if len(forces):
            pred.append(float(np.linalg.norm(np.mean(forces, axis=0))))
            refs.append(ref)
    return {"pred": np.array(pred), "ref": np.array(refs)}
