"""The tare (PipelineConfig.tare): the network's fields for the baseline against itself are subtracted from
every frame's, so an untouched gel reads zero; recomputed when the baseline changes; read from a package's
manifest. A random-weight net (nonzero output at rest) through the real pipeline."""
import json
from dataclasses import replace

import numpy as np
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.pipeline import PipelineConfig, SensorPipeline
from tensortouch.runtime.stages.baseline import BaselineConfig
from tensortouch.runtime.stages.model import FieldModel, load_package
from tensortouch.tools.bench.models import write_package

from tests.conftest import dome_calibration
from tests.test_e2e_runtime import SENSOR, SIZE, H, W

STARTUP = 4


def _pipe(tmp_path, tare: bool) -> SensorPipeline:
    store = CalibrationStore(tmp_path / "calib")
    if not store.sensors():
        dome_calibration(store.root, SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    folder = tmp_path / "m" / "net"
    if not folder.is_dir():
        write_package(folder, size=SIZE, width=4, depth=2, seed=3, int8=False)
    pkg = load_package(folder)
    cfg = replace(PipelineConfig.for_package(pkg), tare=tare, baseline=BaselineConfig(startup_frames=STARTUP))
    return SensorPipeline(SENSOR, FieldModel(pkg, "fp32"), store.load(SENSOR), cfg)


def _flat(level: float) -> np.ndarray:
    return np.full((H, W, 3), level, np.uint8)


def _poke(level: float) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    img = level + 90 * np.exp(-((xx - W / 2 - 10) ** 2 + (yy - H / 2) ** 2) / 50.0)[..., None]
    return np.clip(np.broadcast_to(img, (H, W, 3)), 0, 255).astype(np.uint8)


def _fields(pipe, frames, t0=0.0):
    out = []
    for k, f in enumerate(frames):
        r = pipe.process(f, t0 + k / 30.0)
        out.append(None if r.fields is None else r.fields.copy())
    return out


def test_an_untouched_gel_reads_zero_with_the_tare_and_the_net_offset_without(tmp_path):
    rest = [_flat(120)] * (STARTUP + 3)
    raw = _fields(_pipe(tmp_path, tare=False), rest)[-1]
    tared = _fields(_pipe(tmp_path, tare=True), rest)[-1]
    assert np.abs(raw).max() > 1e-4                  # the random net reads an offset at rest
    assert np.array_equal(tared, np.zeros_like(tared))


def test_a_press_reads_its_fields_minus_the_rest_fields(tmp_path):
    frames = [_flat(120)] * (STARTUP + 2) + [_poke(120)]
    raw = _fields(_pipe(tmp_path, tare=False), frames)
    tared = _fields(_pipe(tmp_path, tare=True), frames)[-1]
    np.testing.assert_allclose(tared, raw[-1] - raw[-2], rtol=0, atol=1e-6)
    assert np.abs(tared).max() > 1e-4


def test_the_tare_follows_a_new_baseline(tmp_path):
    pipe = _pipe(tmp_path, tare=True)
    _fields(pipe, [_flat(100)] * (STARTUP + 2))
    first = pipe._zero.copy()
    pipe.baseline.reset()                            # a new startup: another rest image becomes the baseline
    after = _fields(pipe, [_flat(160)] * (STARTUP + 2), t0=10.0)[-1]
    assert not np.allclose(pipe._zero, first)        # recomputed for the new baseline ...
    assert np.array_equal(after, np.zeros_like(after))   # ... so the new rest reads zero


def test_package_manifest_turns_the_tare_on(tmp_path):
    folder = write_package(tmp_path / "p", size=SIZE, width=4, depth=2, int8=False)
    assert PipelineConfig.for_package(load_package(folder)).tare is False
    man = json.loads((folder / "manifest.json").read_text())
    man["runtime"] = {**(man.get("runtime") or {}), "tare": True}
    (folder / "manifest.json").write_text(json.dumps(man))
    assert PipelineConfig.for_package(load_package(folder)).tare is True
