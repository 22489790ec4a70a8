"""The effect chain (runtime/stages/effects/chain.py): built from a calibration store, streaming equals
batch."""
import json

import numpy as np
import pytest
from tensortouch.runtime.stages.effects import EffectChain, Registry


def test_chain_from_calibration_store(calib_store):
    store = calib_store
    sensor = store.sensors()[0]
    entries = [{"name": "strain_stiffening", "params": {"k": 10.0}},
               {"name": "ft_bias_drift", "params": {"bz": 0.01}}]
    store.derive(sensor, {"effects": entries})
    chain = EffectChain.from_calibration(store.load(sensor), Registry.default(entry_points=False))
    assert chain.names == ["strain_stiffening", "ft_bias_drift"]
    cov = {"depth": np.array([0.0, 4.0]), "gel_height": np.array([8.0, 8.0]), "time": np.array([0.0, 10.0])}
    f = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    runtime_force = chain.apply(f, cov)                                  # what the runtime publishes
    assert np.allclose(runtime_force[:, 2], [1.0, 1.0 + 10.0 * 0.25])
    vs_reference = chain.apply(f, cov, stages=("force", "measurement"))  # what an F/T would read
    assert np.allclose(vs_reference[:, 2], [1.0, 3.5 + 0.1])
    json.dumps(chain.to_list())
    with pytest.raises(ValueError, match="unknown effect"):
        EffectChain.from_list([{"name": "nope"}], Registry.default(entry_points=False))


def test_streaming_chain_equals_batch_for_sequential_effects():
    """The runtime applies effects frame by frame per contact track; must equal the batch form."""
    reg = Registry.default(entry_points=False)
    chain = EffectChain.from_list([{"name": "viscoelastic_relaxation", "params": {"g1": 0.3, "tau": 0.5}},
                                   {"name": "strain_stiffening", "params": {"k": 8.0}}], reg)
    t = np.cumsum(np.random.default_rng(3).uniform(0.01, 0.05, 300))   # irregular frame times
    depth = np.clip(np.sin(t * 3) * 2, 0, None)
    f = np.column_stack([0 * t, 0.1 * depth, depth ** 1.5])
    cov = {"time": t, "depth": depth, "gel_height": np.full(len(t), 8.0)}
    batch = chain.apply(f, cov)
    tracks = {}
    stream = np.vstack([chain.stream(tracks, [7], t[i], f[i:i + 1],
                                     {k: v[i:i + 1] for k, v in cov.items()}) for i in range(len(t))])
    assert np.allclose(stream, batch, atol=1e-9)
    chain.stream(tracks, [], t[-1] + 0.1, np.zeros((0, 3)), {})
    assert tracks == {}                                                   # lifted contacts forgotten
