"""Gel temperature reaches the effect stage on replays: the session's temperature.csv, read at each
frame's recording time (looping replays folded back), drives `temperature_softening` in the loop."""
import json

import numpy as np
import pytest
from tensortouch.contracts.errors import SessionError
from tensortouch.contracts.session import write_table
from tensortouch.contracts.store import CalibrationStore
from tensortouch.drivers.camera.replay import ReplayCamera, ReplayCameraConfig
from tensortouch.runtime.apps.loop import LoopConfig, SensorLoop
from tensortouch.runtime.pipeline import SensorPipeline
from tensortouch.runtime.stages.effects import EffectChain
from tensortouch.runtime.stages.model import FieldModel, load_package
from tensortouch.runtime.stages.temperature import TemperatureTrack
from tensortouch.tools.bench.models import write_difference_package

from tests.conftest import dome_calibration
from tests.hand_util import make_session
from tests.test_e2e_runtime import SENSOR, SIZE, H, W
from tests.test_effect_stage import frames


def test_track_interpolates_and_holds_ends():
    tr = TemperatureTrack([0.0, 1.0, 3.0], [20.0, 22.0, 21.0])
    assert tr(0.5) == pytest.approx(21.0)
    assert tr(2.0) == pytest.approx(21.5)
    assert tr(-5.0) == 20.0 and tr(10.0) == 21.0


@pytest.mark.parametrize("t,c,match", [([], [], "non-empty"), ([0, 1], [20.0], "equal"),
                                       ([0, 0], [20, 21], "increasing"), ([0, 1], [20, np.nan], "finite")])
def test_track_rejects_bad_columns(t, c, match):
    with pytest.raises(SessionError, match=match):
        TemperatureTrack(t, c)


def _session_with_temperature(tmp_path, n=60, fps=30.0, celsius=None):
    folder = make_session(tmp_path / "s", SENSOR, frames(n), fps=fps)
    t = np.arange(0, n / fps + 0.5, 0.5)
    c = np.full_like(t, 35.0) if celsius is None else celsius(t)
    write_table(folder / "temperature.csv", ["t", "celsius"], np.stack([t, c], 1))
    m = json.loads((folder / "session.json").read_text())
    m["streams"]["temperature"] = {"file": "temperature.csv", "rows": len(t), "rate_hz": 2}
    (folder / "session.json").write_text(json.dumps(m))
    return folder


def test_from_session_reads_stream_or_none(tmp_path):
    folder = _session_with_temperature(tmp_path, celsius=lambda t: 20 + t)
    tr = TemperatureTrack.from_session(folder)
    assert tr(1.0) == pytest.approx(21.0)
    bare = make_session(tmp_path / "bare", SENSOR, frames(5))
    assert TemperatureTrack.from_session(bare) is None


def test_looping_replay_folds_frame_times_back(tmp_path):
    folder = make_session(tmp_path / "s", SENSOR, frames(10), fps=10.0)
    with ReplayCamera(ReplayCameraConfig(folder, realtime=False, loop=True)) as cam:
        got = [cam.read() for _ in range(25)]
    assert got[12].t == pytest.approx(1.2)                       # second pass: shifted clock
    assert cam.recording_time(got[12].t) == pytest.approx(0.2)   # ... folded back
    assert cam.recording_time(got[3].t) == pytest.approx(0.3)


def test_loop_feeds_session_temperature_to_effects(tmp_path):
    """Real replay camera + real onnxruntime pipeline + SensorLoop: with the temperature source the
    softening effect changes the forces exactly as the effect chain says; without it, a flag."""
    folder = _session_with_temperature(tmp_path)
    eff = [{"name": "temperature_softening", "params": {"alpha": 0.02, "t_ref": 20.0}}]
    pkg = load_package(write_difference_package(tmp_path / "m" / "d", SIZE))

    def last_result(effects, temperature):
        store = CalibrationStore(tmp_path / f"calib{len(effects)}{temperature is None}")
        dome_calibration(store.root, SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
        store.derive(SENSOR, {"effects": effects})
        pipe = SensorPipeline(SENSOR, FieldModel(pkg, "fp32"), store.load(SENSOR))
        out = []
        with ReplayCamera(ReplayCameraConfig(folder, realtime=False)) as cam:
            loop = SensorLoop(cam, pipe, None, LoopConfig(), on_result=out.append,
                              temperature=temperature)
            loop.run()
        return out[-1]

    plain = last_result([], None)
    hot = last_result(eff, TemperatureTrack.from_session(folder))
    blind = last_result(eff, None)
    f0 = np.array([c.force_n for c in plain.clusters])
    assert len(f0) > 0
    f1 = np.array([c.force_n for c in hot.clusters])
    expect = EffectChain.from_list(eff).apply(f0, {"temperature": np.full(len(f0), 35.0)})
    assert np.allclose(f1, expect, rtol=1e-6) and not np.allclose(f1, f0)
    assert "effect_covariate_missing" in blind.flags and "effect_covariate_missing" not in hot.flags
