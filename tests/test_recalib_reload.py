"""A running SensorLoop picks up a recalibration without a restart (runtime/apps/loop.py polls CURRENT).

Real parts: replay camera on a synthetic recording, onnxruntime pipeline, calibration store; the new
version is written by tools.recalib.store_ops while the loop runs (from its on_result callback)."""
import numpy as np
import pytest
from tensortouch.drivers.camera import camera_from_uri
from tensortouch.runtime.apps.loop import LoopConfig, SensorLoop
from tensortouch.runtime.pipeline import SensorPipeline
from tensortouch.runtime.stages.contacts import find_clusters, pixel_forces
from tensortouch.runtime.stages.model import FieldModel
from tensortouch.tools.recalib.fit import PokeSet, fit_correction
from tensortouch.tools.recalib.store_ops import store_recalibration

from tests.recalib_util import SENSOR, setup_env, write_recording

GAIN = 2.0


def constant_gain_fit():
    rng = np.random.default_rng(1)
    pred = np.column_stack([np.zeros(6), np.zeros(6), -rng.uniform(0.5, 3, 6)])
    return fit_correction(PokeSet(pred, GAIN * np.abs(pred[:, 2]), rng.uniform(0.2, 0.8, (6, 2)), np.zeros((6, 2))))


def test_loop_reloads_new_calibration_version_without_restart(tmp_path):
    package, store = setup_env(tmp_path)
    # long gaps: the pipeline re-forms its baseline after a calibration swap (30 startup frames)
    session, _, _ = write_recording(tmp_path / "session", package, store, n_pokes=3, gap=60)
    cal = store.load(SENSOR)
    pipeline = SensorPipeline(SENSOR, FieldModel(package, "fp32"), cal)
    fit = constant_gain_fit()
    seen = []                      # (frame, calibration version, reported |F|, raw |F| from the fields)
    state = {"written": None}

    def on_result(r):
        cal_now = pipeline.cal
        raw = 0.0
        if r.fields is not None:
            cl = find_clusters(pixel_forces(r.fields, cal_now.pixel_area), cal_now.surface_xyz, cal_now.normals,
                               cal_now.pixel_area, cal_now.mask, disp=r.fields[0:3], cfg=pipeline.cfg.contacts)
            raw = float(np.linalg.norm(np.sum([c.force_n for c in cl], axis=0))) if cl else 0.0
        seen.append((r.seq, cal_now.version, float(np.linalg.norm(r.force_n)), raw))
        if len(seen) == 40 + 30 + 5 and state["written"] is None:     # first poke over, in the gap
            state["written"] = store_recalibration(store, cal, {"pokes": 6}, correction=(fit.spec, fit.onnx_bytes))

    cam = camera_from_uri(f"replay:{session}", realtime=False)
    loop = SensorLoop(cam, pipeline, None, LoopConfig(calibration_poll_s=0.0), store=store, on_result=on_result)
    with cam:
        n = loop.run()
    assert n == len(seen) and state["written"] == "v0002"
    versions = [v for _, v, _, _ in seen]
    switch = versions.index("v0002")
    assert set(versions[:switch]) == {"v0001"} and set(versions[switch:]) == {"v0002"}
    assert switch <= 40 + 30 + 5 + 2              # picked up at the next poll, no restart
    before = [(f, raw) for _, v, f, raw in seen if v == "v0001" and raw > 0.3]
    after = [(f, raw) for _, v, f, raw in seen if v == "v0002" and raw > 0.3]
    assert before and after, "pokes before and after the swap should produce contacts"
    assert all(f == pytest.approx(raw, rel=1e-5) for f, raw in before)
    assert all(f == pytest.approx(GAIN * raw, rel=1e-3) for f, raw in after)
    assert "calibration_invalid" not in loop.flags
