"""The eight canonical physical effects: specs (units, bounds, covariates) and truth forward forms."""
from pathlib import Path

import numpy as np
import pytest
from tensortouch.tools.twin.effect_specs import CANONICAL, COVARIATES, SPECS, parse_effect_arg
from tensortouch.tools.twin.effects import EFFECTS, build_effects

T = np.linspace(0, 10, 201)


def _cov(depth=None, temperature=None):
    n = len(T)
    depth = np.full(n, 1.0) if depth is None else depth
    return {"time": T, "temperature": np.full(n, 25.0) if temperature is None else temperature,
            "depth": depth, "max_depth": np.maximum.accumulate(depth), "gel_height": np.full(n, 8.0),
            "rim_distance": np.full(n, 5.0), "normal": np.tile([0.0, 0.0, 1.0], (n, 1)),
            "force_n": np.ones(n), "force_t": np.zeros(n)}


def _wrench(fz=-2.0, fx=0.0):
    x = np.zeros((len(T), 6))
    x[:, 2], x[:, 0], x[:, 3] = fz, fx, 5.0
    return x


def test_canonical_set_is_complete_and_documented():
    assert set(CANONICAL) <= set(SPECS) and set(CANONICAL) <= set(EFFECTS)
    doc = (Path(__file__).resolve().parents[1] / "docs" / "effects.md").read_text()
    for name in CANONICAL:
        spec = SPECS[name]
        assert spec.equation and spec.params and set(spec.covariates) <= set(COVARIATES)
        assert f"`{name}`" in doc
        for p in spec.params:
            assert p.lo <= p.default <= p.hi and p.unit
            assert f"`{p.name}`" in doc


@pytest.mark.parametrize("name", CANONICAL)
def test_off_parameters_are_identity(name):
    spec = SPECS[name]
    e = EFFECTS[name](**spec.off)
    x = _wrench(fx=0.3)
    y = e.forward(np.ones(len(T)) if spec.stage == "image" else x, _cov())
    np.testing.assert_allclose(y, np.ones(len(T)) if spec.stage == "image" else x, atol=1e-12)


def test_temperature_softening_direction():
    e = EFFECTS["temperature_softening"](alpha=0.02, t_ref=25.0)
    y = e.forward(_wrench(), _cov(temperature=np.linspace(20, 30, len(T))))
    assert y[0, 2] < -2.0 < y[-1, 2] < 0  # colder -> stiffer, warmer -> softer
    np.testing.assert_allclose(y[-1, 2], -2.0 * (1 - 0.02 * 5), rtol=1e-9)


def test_viscoelastic_step_relaxes_with_tau():
    e = EFFECTS["viscoelastic_relaxation"](g1=0.3, tau=1.0)
    x = np.zeros((len(T), 6))
    x[T >= 1.0, 2] = -2.0  # step at t = 1 s
    y = e.forward(x, _cov())
    i1 = np.searchsorted(T, 1.0)
    assert y[i1, 2] == pytest.approx(-2.0, rel=0.05)            # instantaneous modulus
    assert y[-1, 2] == pytest.approx(-2.0 * 0.7, rel=0.01)      # relaxed to g_inf
    i2 = np.searchsorted(T, 2.0)                                # one tau later: 1/e of the relaxing part left
    assert y[i2, 2] == pytest.approx(-2.0 * (0.7 + 0.3 * np.exp(-1.0)), rel=0.03)


def test_viscoelastic_gel_does_not_pull_after_a_fast_release():
    """Unilateral contact: a held press released faster than the gel recovers loses contact (force 0)
    instead of pulling on the indenter; no elastic force, no force."""
    e = EFFECTS["viscoelastic_relaxation"](g1=0.4, tau=1.0)
    x = np.zeros((len(T), 6))
    x[(T >= 0.5) & (T < 2.5), 2] = -2.0                   # press held 2 s, released within one sample
    y = e.forward(x, _cov())
    assert np.all(y[:, 2] <= 0.0)                          # never tensile (the push is negative z here)
    assert np.all(y[x[:, 2] == 0.0] == 0.0)                # off the gel: exactly zero
    held = (T > 2.0) & (T < 2.5)
    assert np.all(y[held, 2] > -2.0) and np.all(y[held, 2] < -2.0 * 0.6)   # relaxing while held


def test_mullins_softer_on_reloading():
    depth = np.concatenate([np.linspace(0, 2, 67), np.linspace(2, 0, 67), np.linspace(0, 1.5, 67)])
    e = EFFECTS["mullins_softening"](r=0.2, m=0.5)
    y = e.forward(_wrench(), _cov(depth=depth))
    assert y[66, 2] == pytest.approx(-2.0)          # first loading at the maximum: virgin
    assert y[-1, 2] > -2.0 * 0.95                   # reloading below the maximum: softer


def test_strain_stiffening_and_rim():
    y = EFFECTS["strain_stiffening"](k=4.0).forward(_wrench(), _cov(depth=np.linspace(0, 4, len(T))))
    assert y[0, 2] == pytest.approx(-2.0) and y[-1, 2] == pytest.approx(-2.0 * (1 + 4 * 0.25))
    cov = _cov()
    cov["rim_distance"] = np.linspace(0, 10, len(T))
    y = EFFECTS["rim_stiffening"](a=1.0, w=2.0).forward(_wrench(), cov)
    assert y[0, 2] == pytest.approx(-4.0) and abs(y[-1, 2]) < 2.02


def test_friction_mismatch_clips_shear_only():
    e = EFFECTS["friction_mismatch"](mu=0.5)
    y = e.forward(_wrench(fz=-2.0, fx=1.5), _cov())
    np.testing.assert_allclose(y[:, 2], -2.0)
    np.testing.assert_allclose(np.abs(y[:, 0]), 1.0)            # mu * |Fn|
    assert np.all(e.shear_ratio(_wrench(fz=-2.0, fx=1.5), _cov()) == pytest.approx(1.0 / 1.5))


def test_ft_bias_and_led_drift_linear_in_time():
    y = EFFECTS["ft_bias_drift"](bx=0.0, by=0.0, bz=0.01).forward(np.zeros((len(T), 6)), _cov())
    np.testing.assert_allclose(y[:, 2], 0.01 * T)
    g = EFFECTS["led_drift"](c=-0.01, beta=0.0).forward(np.ones(len(T)), _cov())
    np.testing.assert_allclose(g, 1 - 0.01 * T)


def test_parse_and_bounds():
    name, p = parse_effect_arg("temperature_softening:alpha=0.03")
    assert name == "temperature_softening" and p == {"alpha": 0.03, "t_ref": 25.0}
    assert parse_effect_arg("ft_bias_drift:bx=0.001,bz=0.002")[1]["bz"] == 0.002
    with pytest.raises(ValueError, match="unknown effect"):
        parse_effect_arg("magic:x=1")
    with pytest.raises(ValueError, match="outside"):
        parse_effect_arg("temperature_softening:alpha=5")
    with pytest.raises(ValueError, match="unknown parameter"):
        build_effects([("led_drift", {"gamma": 1.0})])
