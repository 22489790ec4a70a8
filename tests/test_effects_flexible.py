"""The flexible effect members (runtime/stages/effects/flexible.py): identities when off, streaming equals
batch."""
import numpy as np
import pytest
from tensortouch.runtime.stages.effects import Registry


@pytest.fixture(scope="module")
def registry():
    return Registry.default(entry_points=False)


def test_flexible_members_are_identities_when_off_and_stream_like_they_filter(registry):
    rng = np.random.default_rng(0)
    n = 300
    t = np.cumsum(rng.uniform(0.01, 0.03, n))
    x = np.abs(rng.normal(1, 0.3, (n, 3)))
    cov = {"time": t, "depth": rng.uniform(0, 2, n), "max_depth": np.full(n, 2.0), "gel_height": np.full(n, 10.0),
           "rim_distance": rng.uniform(0, 10, n), "temperature": rng.uniform(18, 35, n)}
    for name in ("strain_stiffening_spline", "rim_stiffening_spline", "temperature_softening_spline",
                 "mullins_softening_spline", "viscoelastic_relaxation_2"):
        e = registry.get(name)
        assert e.family and e.family in registry
        assert np.allclose(e.forward(x, cov, e.identity_params()), x), name
        assert not np.allclose(e.forward(x, cov, e.resolve({})), x), name
    e = registry.get("viscoelastic_relaxation_2")
    p = e.resolve({"g1": 0.3, "tau1": 0.2, "g2": 0.2, "tau2": 4.0})
    state = {}
    streamed = np.array([e.step(state, ti, xi, p) for ti, xi in zip(t, x)])
    assert np.allclose(streamed, e.forward(x, cov, p), atol=1e-9)
