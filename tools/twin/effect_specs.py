"""Physical-effect *specifications*: names, parameters (units, bounds), covariates, equations.

This module is the shared vocabulary between the digital twin (which switches effects on in
"truth", tools/twin/effects.py) and the model/workbench side (which fits them from measurements).
It is pure (stdlib only) and imports nothing from tools/, so it can move under runtime/ unchanged.
Equations and units are documented in docs/effects.md.

Covariate names (what an effect needs to be evaluated), all per sample:
  time (s since session start), temperature (degC), depth (mm, indentation normal to the rest
  surface), max_depth (mm, largest depth reached earlier in the session by that indenter),
  force_n (N, normal force magnitude), force_t (N, tangential force magnitude),
  rim_distance (mm, arc length from the contact point to the gel rim), gel_height (mm).
"""
from __future__ import annotations

from dataclasses import dataclass, field

COVARIATES = {
    "time": "s", "temperature": "degC", "depth": "mm", "max_depth": "mm", "force_n": "N",
    "force_t": "N", "rim_distance": "mm", "gel_height": "mm",
}
STAGES = ("force", "measurement", "image")  # where an effect acts (see docs/effects.md)


@dataclass(frozen=True)
class Param:
    """One effect parameter in physical units with its allowed range."""

    name: str
    unit: str
    default: float
    lo: float
    hi: float
    doc: str = ""

    def check(self, value: float, effect: str) -> float:
        value = float(value)
        if not (self.lo <= value <= self.hi):
            raise ValueError(f"effect {effect}: parameter {self.name}={value} {self.unit} outside "
                             f"[{self.lo}, {self.hi}]")
        return value


@dataclass(frozen=True)
class EffectSpec:
    """Name, parameters, covariates, stage and equation of one physical effect."""

    name: str
    summary: str
    equation: str
    stage: str
    params: tuple[Param, ...]
    covariates: tuple[str, ...]
    off: dict = field(default_factory=dict)  # parameter values for which the effect is the identity

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(f"effect {self.name}: no parameter {name!r} "
                       f"(has {[p.name for p in self.params]})")

    def resolve(self, values: dict | None = None) -> dict[str, float]:
        """Defaults overridden by `values`, each checked against its bounds."""
        values = dict(values or {})
        unknown = set(values) - {p.name for p in self.params}
        if unknown:
            raise ValueError(f"effect {self.name}: unknown parameter(s) {sorted(unknown)} "
                             f"(has {[p.name for p in self.params]})")
        return {p.name: p.check(values.get(p.name, p.default), self.name) for p in self.params}


SPECS: dict[str, EffectSpec] = {}


def register_spec(spec: EffectSpec) -> EffectSpec:
    """Add an effect spec (plugins call this); names are unique."""
    if spec.stage not in STAGES:
        raise ValueError(f"effect {spec.name}: stage {spec.stage!r} not in {STAGES}")
    bad = [c for c in spec.covariates if c not in COVARIATES]
    if bad:
        raise ValueError(f"effect {spec.name}: unknown covariates {bad} (known: {sorted(COVARIATES)})")
    SPECS[spec.name] = spec
    return spec


register_spec(EffectSpec(
    "temperature_softening", "gel stiffness falls linearly with temperature",
    "F = F0 * (1 - alpha * (T - T_ref))", "force",
    (Param("alpha", "1/degC", 0.01, 0.0, 0.05, "relative stiffness loss per degree"),
     Param("t_ref", "degC", 25.0, 0.0, 60.0, "temperature at which the model material holds")),
    ("temperature",), {"alpha": 0.0}))
register_spec(EffectSpec(
    "viscoelastic_relaxation", "one-term Prony series (quasi-linear viscoelasticity) on the force",
    "F(t) = g_inf*F0(t) + g1 * int_0^t exp(-(t-s)/tau) dF0(s),  g_inf = 1 - g1", "force",
    (Param("g1", "-", 0.2, 0.0, 0.8, "relaxing fraction of the instantaneous modulus"),
     Param("tau", "s", 1.0, 0.02, 30.0, "relaxation time")),
    ("time",), {"g1": 0.0}))
register_spec(EffectSpec(
    "mullins_softening", "softer reloading below the largest past depth (Ogden-Roxburgh style)",
    "F = F0 * (1 - r * erf((d_max - d) / m)),  d_max = largest earlier depth", "force",
    (Param("r", "-", 0.15, 0.0, 0.6, "largest relative softening"),
     Param("m", "mm", 0.5, 0.05, 5.0, "depth scale of the softening")),
    ("depth", "max_depth"), {"r": 0.0}))
register_spec(EffectSpec(
    "strain_stiffening", "extra stiffening at large strain beyond the model's Yeoh terms",
    "F = F0 * (1 + k * (d / h)^2),  h = gel height", "force",
    (Param("k", "-", 4.0, 0.0, 50.0, "quadratic stiffening coefficient"),),
    ("depth", "gel_height"), {"k": 0.0}))
register_spec(EffectSpec(
    "friction_mismatch", "true Coulomb friction differs from the model's mu: shear saturates",
    "F_t = F0_t * min(1, mu * |F_n| / |F0_t|);  F_n unchanged", "force",
    (Param("mu", "-", 0.6, 0.05, 3.0, "true friction coefficient"),),
    ("force_n", "force_t"), {"mu": 3.0}))
register_spec(EffectSpec(
    "rim_stiffening", "gel-skin / bonding stiffening near the rim",
    "F = F0 * (1 + a * exp(-s_rim / w)),  s_rim = arc distance of the contact to the rim", "force",
    (Param("a", "-", 0.5, 0.0, 3.0, "relative stiffening at the rim"),
     Param("w", "mm", 2.0, 0.2, 10.0, "decay length from the rim")),
    ("rim_distance",), {"a": 0.0}))
register_spec(EffectSpec(
    "ft_bias_drift", "force/torque sensor bias drifting linearly in time (F/T frame)",
    "F_meas = F + b * t,  b = (bx, by, bz)", "measurement",
    (Param("bx", "N/s", 0.0, -0.02, 0.02, "x bias drift rate"),
     Param("by", "N/s", 0.0, -0.02, 0.02, "y bias drift rate"),
     Param("bz", "N/s", 0.004, -0.02, 0.02, "z bias drift rate")),
    ("time",), {"bx": 0.0, "by": 0.0, "bz": 0.0}))
register_spec(EffectSpec(
    "led_drift", "LED brightness drifting in time and with temperature",
    "g(t) = 1 + c * t + beta * (T - T_ref)  (image intensity gain)", "image",
    (Param("c", "1/s", -0.002, -0.02, 0.02, "brightness change per second"),
     Param("beta", "1/degC", 0.0, -0.05, 0.05, "brightness change per degree"),
     Param("t_ref", "degC", 25.0, 0.0, 60.0, "reference temperature")),
    ("time", "temperature"), {"c": 0.0, "beta": 0.0}))

CANONICAL = ("temperature_softening", "viscoelastic_relaxation", "mullins_softening",
             "strain_stiffening", "friction_mismatch", "rim_stiffening", "ft_bias_drift", "led_drift")


def parse_effect_arg(text: str) -> tuple[str, dict[str, float]]:
    """'name:p=v,q=w' (or 'name:p=v:q=w', or 'name') -> (name, {p: v, q: w}) checked against SPECS."""
    name, _, rest = text.partition(":")
    name = name.strip()
    if name not in SPECS:
        raise ValueError(f"unknown effect {name!r}; known: {sorted(SPECS)}")
    values = {}
    for item in rest.replace(":", ",").split(","):
        if not item.strip():
            continue
        key, eq, val = item.partition("=")
        if not eq:
            raise ValueError(f"effect {name}: expected param=value, got {item!r}")
        try:
            values[key.strip()] = float(val)
        except ValueError:
            raise ValueError(f"effect {name}: parameter {key.strip()} needs a number, got {val!r}") from None
    return name, SPECS[name].resolve(values)
