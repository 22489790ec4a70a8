"""Replaying recordings through the runtime once and re-applying corrections (twin recalibration bench).

`collect_frames` replays a recording through the runtime (runtime.offline.replay_session, its effects
on, the correction off) and keeps each frame's clusters (its network-pass cache optional); `corrected_frames` applies a
calibration's correction to them exactly as the pipeline's correction stage does; `held_out_pokes`
pairs them with a reference force stream, one row per poke of the reference (as
tools.recalib.evaluate.measure_pokes).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def collect_frames(session_dir: Path, cal, package, precision: str, cache: Path | None = None) -> list:
    """(t, clusters) of every frame of a replayed recording as `tensortouch run` publishes them with the
    correction off: the raw model force after the calibration's enabled effects
    (runtime.offline.replay_session; `cache`: its network-pass cache folder)."""
    from ...runtime.offline import replay_session
    from ...runtime.stages.correction import ForceCorrection

    return [(r.t, r.clusters) for r in replay_session(session_dir, package, cal, cache=cache, precision=precision,
                                                      correction=ForceCorrection(None, None))]


def mae(m: dict) -> float:
    return float(np.mean(np.abs(m["pred"] - m["ref"]))) if len(m["ref"]) else float("nan")


def corrected_frames(frames: list, cal, corr=None) -> list:
    """The runtime's correction stage (runtime.pipeline.apply_correction with `corr`, default the
    ForceCorrection of `cal`) applied to recorded raw-model clusters; frames are copied."""
    from dataclasses import replace as dc_replace

    from ...runtime.pipeline import apply_correction
    from ...runtime.stages.correction import ForceCorrection

    corr = corr if corr is not None else ForceCorrection.from_calibration(cal)
    out = []
    for t, clusters in frames:
        clusters = [dc_replace(c) for c in clusters]
        apply_correction(clusters, corr, cal)
        out.append((t, clusters))
    return out


def held_out_pokes(frames: list, reference, rules, by: str = "gauge") -> dict:
    """The reference's pokes with the sensor's force in them (tools.recalib.evaluate.gauge_pokes), or
    with by="detected" the single-contact pokes the sensor detected (pair_pokes)."""
    from .evaluate import gauge_pokes, pair_pokes

    return gauge_pokes(frames, reference, rules) if by == "gauge" else pair_pokes(frames, reference, rules)
