"""Held-out evaluation on a recording: every poke's force magnitude, with and without a correction.

Replays a session (real or twin) through the runtime pipeline with a given calibration version,
detects pokes (tools.recalib.pokes, no acceptance rules beyond single contact) and pairs each with
the recording's force stream. Used by the twin end-to-end test and benchmark.
"""
from __future__ import annotations

import logging

import numpy as np

from runtime.calibration import Calibration
from runtime.correction import ForceCorrection
from runtime.model import FieldModel, ModelPackage
from runtime.pipeline import SensorPipeline
from runtime.session import load_session
from tools.recalib.pokes import PokeDetector, PokeRules
from tools.recalib.session import StreamReference

log = logging.getLogger(__name__)


def measure_pokes(session_dir, cal: Calibration, package: ModelPackage, corrected: bool,
                  rules: PokeRules = PokeRules(), precision: str = "int8") -> dict:
    """{'pred': (N,) |F| the runtime reports, 'ref': (N,) reference |F|} for the single-contact pokes."""
    from drivers.camera import camera_from_uri

    session = load_session(session_dir)
    ref = StreamReference.from_session(session, rules)
    corr = None if corrected else ForceCorrection(None, None)
    pipe = SensorPipeline(cal.sensor_id, FieldModel(package, precision), cal, correction=corr)
    with camera_from_uri(f"replay:{session_dir}", realtime=False) as cam:
        from drivers.camera.camera import EndOfStream

        def frames():
            while True:
                try:
                    frame = cam.read()
                except EndOfStream:
                    return
                yield frame.t, pipe.process(frame.image, frame.t).clusters

        return pair_pokes(frames(), ref, rules)


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
