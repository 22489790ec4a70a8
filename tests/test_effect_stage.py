"""The runtime applies the calibration's enabled effects to cluster forces (DESIGN §4), in order,
before the force correction; a covariate the runtime lacks gives a status flag, not a crash."""
import numpy as np
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.pipeline import SensorPipeline
from tensortouch.runtime.stages.effects import EffectChain
from tensortouch.runtime.stages.model import FieldModel, load_package
from tensortouch.tools.bench.models import write_difference_package

from tests.conftest import dome_calibration
from tests.test_e2e_runtime import SENSOR, SIZE, H, W


def frames(n=60, poke_from=35):
    yy, xx = np.mgrid[0:H, 0:W]
    rest = np.full((H, W, 3), 120.0)
    out = []
    for k in range(n):
        img = rest.copy()
        if k >= poke_from:
            img += 90 * np.exp(-((xx - W / 2 - 20) ** 2 + (yy - H / 2) ** 2) / 72.0)[..., None]
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out


def run(tmp_path, effects, temperature=None):
    store = CalibrationStore(tmp_path / "calib")
    if not store.sensors():
        dome_calibration(store.root, SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    store.derive(SENSOR, {"effects": effects})
    pkg = load_package(write_difference_package(tmp_path / "m" / "d", SIZE))
    pipe = SensorPipeline(SENSOR, FieldModel(pkg, "fp32"), store.load(SENSOR))
    if temperature is not None:
        pipe.set_temperature(temperature)
    results = [pipe.process(f, k / 30.0) for k, f in enumerate(frames())]
    return results[-1]


def test_temperature_softening_applied_when_temperature_known(tmp_path):
    plain = run(tmp_path / "a", [])
    assert plain.clusters and "effects" in plain.timings
    eff = [{"name": "temperature_softening", "params": {"alpha": 0.02, "t_ref": 20.0}}]
    hot = run(tmp_path / "b", eff, temperature=35.0)
    f0 = np.array([c.force_n for c in plain.clusters])
    f1 = np.array([c.force_n for c in hot.clusters])
    chain = EffectChain.from_list(eff)
    expect = chain.apply(f0, {"temperature": np.full(len(f0), 35.0)})
    assert np.allclose(f1, expect, rtol=1e-6) and not np.allclose(f1, f0)


def test_missing_covariate_flags_and_keeps_forces(tmp_path):
    plain = run(tmp_path / "a", [])
    eff = [{"name": "temperature_softening", "params": {"alpha": 0.02, "t_ref": 20.0}}]
    r = run(tmp_path / "b", eff)
    assert "effect_covariate_missing" in r.flags
    assert np.allclose([c.force_n for c in r.clusters], [c.force_n for c in plain.clusters])


def test_depth_covariate_is_the_clusters_indentation():
    from tensortouch.runtime.stages.contacts import Cluster
    from tensortouch.runtime.stages.effects.stage import EffectStage

    class Cal:
        meta = {"gel": {"radius_mm": 16.0, "center_z_mm": 0.0, "skirt_mm": 2.0}}
        sensor_id, version, effects = "X", "v0001", []

    stage = EffectStage(Cal())
    stage.t0 = 0.0
    on_cap = Cluster(1, (0, 0), (0.0, 0.0, 15.9), (0, 0, 1), 1.0, (0, 0, -1.0), 1.0, 5, 8.0, 0.9, indentation_mm=0.8)
    flat = Cluster(2, (0, 0), (0.0, 0.0, 15.5), (0, 0, 1), 1.0, (0, 0, -1.0), 1.0, 5, 8.0, 0.9)
    cov = stage.frame_covariates([on_cap, flat], 0.1)
    # the deepest point when the displacement field gave one, else the centroid's depth below the cap
    assert np.allclose(cov["depth"], [0.8, 0.5]) and np.allclose(cov["max_depth"], [0.8, 0.5])
    # max_depth is the session's (docs/effects.md): it outlasts the contact, and a new contact
    # shallower than that starts below it
    assert stage.frame_covariates([], 0.2) == {}
    later = Cluster(7, (0, 0), (0.0, 0.0, 15.9), (0, 0, 1), 1.0, (0, 0, -1.0), 1.0, 5, 8.0, 0.9, indentation_mm=0.3)
    cov = stage.frame_covariates([later], 0.3)
    assert np.allclose(cov["depth"], [0.3]) and np.allclose(cov["max_depth"], [0.8])
    deeper = Cluster(8, (0, 0), (0.0, 0.0, 15.9), (0, 0, 1), 1.0, (0, 0, -1.0), 1.0, 5, 8.0, 0.9, indentation_mm=1.1)
    assert np.allclose(stage.frame_covariates([deeper], 0.4)["max_depth"], [1.1])
    assert np.allclose(stage.frame_covariates([later], 0.5)["max_depth"], [1.1])


def test_gel_memory_is_kept_without_effects_and_across_a_calibration_swap(tmp_path):
    """max_depth (Mullins) is the gel's: tracked while no effect is enabled, and a new calibration
    version with Mullins softening (hot swap, docs/runtime.md) starts from the depth already reached."""
    store = CalibrationStore(tmp_path / "calib")
    dome_calibration(store.root, SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    pkg = load_package(write_difference_package(tmp_path / "m" / "d", SIZE))
    pipe = SensorPipeline(SENSOR, FieldModel(pkg, "fp32"), store.load(SENSOR))
    res = [pipe.process(f, k / 30.0) for k, f in enumerate(frames())]
    assert res[-1].clusters and not pipe.effects.enabled
    reached = pipe.effects.max_depth
    assert reached > 0.0
    store.derive(SENSOR, {"effects": [{"name": "mullins_softening", "params": {"r": 0.3, "m": 0.5}}]})
    pipe.set_calibration(store.load(SENSOR))
    assert pipe.effects.enabled and pipe.effects.max_depth == reached
