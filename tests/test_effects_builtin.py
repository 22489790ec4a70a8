"""The built-in effect library (runtime/stages/effects/builtin.py): identity values, agreement with the
twin, Prony filter, bounds."""
import numpy as np
import pytest
from tensortouch.runtime.stages.effects import CANONICAL, Registry
from tensortouch.runtime.stages.effects.builtin import prony_history


def _cov(n=200, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.02
    depth = np.clip(np.sin(t * 2) * 2, 0, None)
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return {"time": t, "temperature": 24 + t, "depth": depth, "max_depth": np.maximum.accumulate(depth),
            "gel_height": np.full(n, 8.0), "rim_distance": rng.uniform(0, 10, n), "normal": normal,
            "force_n": np.ones(n), "force_t": np.ones(n)}


def test_library_has_the_canonical_eight_with_identity_values():
    reg = Registry.default(entry_points=False)
    assert set(CANONICAL) <= set(reg.names())
    assert len(CANONICAL) == 8
    cov = _cov()
    x = 2.0 * cov["normal"] + 0.5 * np.random.default_rng(1).normal(size=(200, 3))  # shear < 3 x normal
    for name in CANONICAL:
        e = reg.get(name)
        if e.stage == "image":
            assert np.allclose(e.gain(cov, e.identity_params()), 1.0)
            continue
        assert np.allclose(e.apply(x, cov, e.identity_params()), x), name
        off = e.identity_params()
        far = {p.name: (p.lo if abs(p.lo - off[p.name]) > abs(p.hi - off[p.name]) else p.hi) for p in e.free_params}
        assert not np.allclose(e.apply(x, cov, e.resolve(far)), x), name


@pytest.mark.parametrize("name,params", [
    ("temperature_softening", {"alpha": 0.03, "t_ref": 22.0}), ("viscoelastic_relaxation", {"g1": 0.4, "tau": 0.3}),
    ("mullins_softening", {"r": 0.3, "m": 0.4}), ("strain_stiffening", {"k": 12.0}),
    ("friction_mismatch", {"mu": 0.3}), ("rim_stiffening", {"a": 1.5, "w": 3.0}),
    ("ft_bias_drift", {"bx": 0.01, "by": -0.005, "bz": 0.002})])
def test_model_forward_agrees_with_the_twin_truth_forward(name, params):
    """Same physics written twice (model side here, truth side in the twin): must agree."""
    twin = pytest.importorskip("tensortouch.tools.twin.effects")
    cov = _cov()
    x = np.random.default_rng(2).normal(size=(200, 6))
    truth = twin.build_effects([(name, params)])[0].forward(x, cov)
    e = Registry.default(entry_points=False).get(name)
    ours = e.apply(x[:, :3], cov, e.resolve(params))
    if name == "friction_mismatch":  # the twin rescales the moment too; forces must agree
        assert np.allclose(ours, truth[:, :3], atol=1e-9)
    else:
        assert np.allclose(ours, truth[:, :3], atol=1e-9)


def test_prony_fast_filter_equals_the_recursion_and_the_step_response():
    t = np.arange(500) * 0.01
    x = np.where(t > 1.0, 1.0, 0.0)[:, None] * np.array([[1.0, 2.0, 0.0]])
    fast = prony_history(x, t, 0.5)
    t2 = t.copy()
    t2[100:] += 1e-4  # non-uniform spacing -> exact recursion path
    slow = prony_history(x, t2, 0.5)
    assert np.allclose(fast, slow, atol=2e-3)
    # a unit step decays as exp(-(t - t_step)/tau) after the ramp sample
    i = 300
    assert fast[i, 0] == pytest.approx(np.exp(-(t[i] - 1.005) / 0.5), rel=0.02)


def test_viscoelastic_contact_is_unilateral_in_batch_and_streaming():
    """A press, a partial unload faster than the gel recovers, a reload, a release: where the relaxed
    force would turn into a pull the contact is lost (0), with no elastic force there is none, and the
    runtime's frame-by-frame step gives the same forces as the batch form."""
    e = Registry.default(entry_points=False).get("viscoelastic_relaxation")
    p = {"g1": 0.5, "tau": 2.0}
    t = np.arange(0, 8, 1 / 30)
    fz = np.interp(t, [0, 0.5, 3.0, 3.1, 4.0, 4.5, 6.0, 6.1], [0, 2.0, 2.0, 0.5, 0.5, 2.0, 2.0, 0.0])
    x = np.stack([0.1 * fz, 0.0 * fz, fz], 1)
    y = e.forward(x, {"time": t}, p)
    assert np.all(np.sum(y * x, axis=1) >= 0.0)
    assert np.all(y[fz == 0.0] == 0.0)
    lost = (t > 3.1) & (t < 4.0)                 # unloaded to 25 % after a 2.5 s hold: below g1's share
    assert np.all(y[lost] == 0.0)
    assert np.all(y[(t > 0.6) & (t < 3.0), 2] > 0.0)
    state = {}
    z = np.array([e.step(state, ti, xi, p) for ti, xi in zip(t, x)])
    np.testing.assert_allclose(z, y, atol=1e-9)


def test_bounds_are_enforced_and_unknown_parameters_named():
    e = Registry.default(entry_points=False).get("viscoelastic_relaxation")
    with pytest.raises(ValueError, match="tau"):
        e.resolve({"tau": 100.0})
    with pytest.raises(ValueError, match="gamma"):
        e.resolve({"gamma": 1.0})


def test_describe_states_the_physics_with_units():
    e = Registry.default(entry_points=False).get("viscoelastic_relaxation")
    text = e.describe({"g1": 0.24, "tau": 1.9})
    assert "relaxes" in text and "τ = 1.9 s" in text and "g = 0.24" in text


