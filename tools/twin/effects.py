"""Physical effects in *truth*: the forward forms the digital twin applies (numpy).

Specs (names, parameters, units, bounds, covariates, equations) are the runtime's canonical
definitions (runtime/stages/effects/builtin.py, seen through effect_specs.py); this module only holds the
twin's own forward functions, written independently of the runtime's. The model never sees
which effects are on except through the measurements they change. See docs/effects.md.

Stages (where in the twin's signal chain an effect acts):
  force        on the true contact wrench of one indenter, sensor frame: x (T,6) = [F N, M N*mm]
  measurement  on the F/T reading of one indenter, F/T frame: x (T,6)
  image        returns the LED intensity gain (T,) applied to rendered frames

A twin plugin adds an effect with one class: subclass TruthEffect, set `spec` (an EffectSpec
registered with effect_specs.register_spec, or EffectSpec.from_effect(<runtime Effect plugin>))
and write `forward`; decorate with @register.
"""
from __future__ import annotations

import logging

import numpy as np
from scipy.special import erf

from .effect_specs import SPECS, EffectSpec

log = logging.getLogger(__name__)

EFFECTS: dict[str, type["TruthEffect"]] = {}


def register(cls):
    """Class decorator: make a TruthEffect available by its spec name."""
    EFFECTS[cls.spec.name] = cls
    return cls


class TruthEffect:
    """One effect with resolved parameters. `forward(x, cov)` returns the changed signal."""

    spec: EffectSpec

    def __init__(self, **params):
        self.params = self.spec.resolve(params)

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def stage(self) -> str:
        return self.spec.stage

    def forward(self, x: np.ndarray, cov: dict[str, np.ndarray]) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def to_dict(self) -> dict:
        return {"name": self.name, "params": dict(self.params)}


def _scale(x: np.ndarray, factor: np.ndarray) -> np.ndarray:
    return x * np.asarray(factor, dtype=np.float64).reshape(-1, 1)


@register
class TemperatureSoftening(TruthEffect):
    spec = SPECS["temperature_softening"]

    def forward(self, x, cov):
        p = self.params
        return _scale(x, np.clip(1.0 - p["alpha"] * (cov["temperature"] - p["t_ref"]), 0.05, None))


@register
class ViscoelasticRelaxation(TruthEffect):
    """Exact recursive evaluation of the one-term Prony hereditary integral for piecewise-linear
    input (the recording's force at its own time stamps). Unilateral contact: the gel cannot pull,
    so where the elastic force is zero (no contact) or the relaxed force would point against it
    (an unloading faster than the gel recovers), the contact is lost and the force is zero; the
    gel's history keeps relaxing meanwhile."""

    spec = SPECS["viscoelastic_relaxation"]

    def forward(self, x, cov):
        g1, tau = self.params["g1"], self.params["tau"]
        t = np.asarray(cov["time"], dtype=np.float64)
        out = np.empty_like(x, dtype=np.float64)
        h = np.zeros(x.shape[1])
        out[0] = (1.0 - g1) * x[0] + g1 * x[0]
        h[:] = x[0]  # assume the signal was at x[0] for a long time before the first sample
        for i in range(1, len(t)):
            dt = max(t[i] - t[i - 1], 1e-12)
            e = np.exp(-dt / tau)
            slope = (x[i] - x[i - 1]) / dt
            h = e * h + slope * tau * (1.0 - e)
            out[i] = (1.0 - g1) * x[i] + g1 * h
        pulling = np.einsum("ij,ij->i", out[:, :3], np.asarray(x, dtype=np.float64)[:, :3]) <= 0.0
        out[pulling] = 0.0
        return out


@register
class MullinsSoftening(TruthEffect):
    spec = SPECS["mullins_softening"]

    def forward(self, x, cov):
        r, m = self.params["r"], self.params["m"]
        gap = np.clip(np.asarray(cov["max_depth"]) - np.asarray(cov["depth"]), 0.0, None) / m
        return _scale(x, 1.0 - r * erf(gap))


@register
class StrainStiffening(TruthEffect):
    spec = SPECS["strain_stiffening"]

    def forward(self, x, cov):
        d = np.clip(np.asarray(cov["depth"]), 0.0, None)
        return _scale(x, 1.0 + self.params["k"] * (d / np.asarray(cov["gel_height"])) ** 2)


@register
class FrictionMismatch(TruthEffect):
    """Clip the tangential force to mu*|F_n| (normal = cov['normal'], unit vectors (T,3));
    the moment is scaled by the same ratio as |F|."""

    spec = SPECS["friction_mismatch"]

    def forward(self, x, cov):
        n = np.asarray(cov["normal"], dtype=np.float64)
        f = x[:, :3]
        fn = np.sum(f * n, axis=1, keepdims=True) * n
        ft = f - fn
        ftn = np.linalg.norm(ft, axis=1)
        cap = self.params["mu"] * np.linalg.norm(fn, axis=1)
        ratio = np.where(ftn > cap, cap / np.maximum(ftn, 1e-12), 1.0)
        f_new = fn + ft * ratio[:, None]
        fmag, fnew_mag = np.linalg.norm(f, axis=1), np.linalg.norm(f_new, axis=1)
        m_ratio = np.where(fmag > 1e-12, fnew_mag / np.maximum(fmag, 1e-12), 1.0)
        return np.concatenate([f_new, x[:, 3:] * m_ratio[:, None]], axis=1)

    def shear_ratio(self, x, cov) -> np.ndarray:
        """Per-sample factor applied to the tangential force (used to scale in-plane displacement)."""
        y = self.forward(x, cov)
        n = np.asarray(cov["normal"])
        t0 = x[:, :3] - np.sum(x[:, :3] * n, 1, keepdims=True) * n
        t1 = y[:, :3] - np.sum(y[:, :3] * n, 1, keepdims=True) * n
        a = np.linalg.norm(t0, axis=1)
        return np.where(a > 1e-12, np.linalg.norm(t1, axis=1) / np.maximum(a, 1e-12), 1.0)


@register
class RimStiffening(TruthEffect):
    spec = SPECS["rim_stiffening"]

    def forward(self, x, cov):
        s = np.clip(np.asarray(cov["rim_distance"]), 0.0, None)
        return _scale(x, 1.0 + self.params["a"] * np.exp(-s / self.params["w"]))


@register
class FTBiasDrift(TruthEffect):
    spec = SPECS["ft_bias_drift"]

    def forward(self, x, cov):
        p = self.params
        b = np.array([p["bx"], p["by"], p["bz"], 0.0, 0.0, 0.0])
        return x + np.asarray(cov["time"]).reshape(-1, 1) * b


@register
class LEDDrift(TruthEffect):
    spec = SPECS["led_drift"]

    def forward(self, x, cov):
        p = self.params
        g = 1.0 + p["c"] * np.asarray(cov["time"]) + p["beta"] * (np.asarray(cov["temperature"]) - p["t_ref"])
        return np.asarray(x, dtype=np.float64) * np.clip(g, 0.05, None)


def build_effects(items: list[tuple[str, dict]] | None) -> list[TruthEffect]:
    """[(name, params)] -> effect instances (unknown names/params raise ValueError)."""
    out = []
    for name, params in items or []:
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r}; known: {sorted(EFFECTS)}")
        out.append(EFFECTS[name](**params))
    return out


def apply_stage(effects: list[TruthEffect], stage: str, x: np.ndarray, cov: dict) -> np.ndarray:
    """Apply every effect of `stage` in the order given."""
    for e in effects:
        if e.stage == stage:
            x = e.forward(x, cov)
    return x
