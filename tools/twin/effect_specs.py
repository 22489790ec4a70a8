"""Physical-effect *specifications* for the twin, taken from the runtime's canonical definitions.

The effect vocabulary -- names, parameters (units, bounds, defaults), identity values, stages,
covariates and equations -- is defined once, in `runtime/stages/effects/builtin.py` (the model side the
runtime applies and the workbench fits; docs/effects-model.md). The twin (which switches effects on
in "truth", tools/twin/effects.py) reads it from there through the small `EffectSpec` view below, so
the two sides cannot drift apart. Only the truth *forward forms* are written separately in the twin
(so a test can check two independent implementations of the same physics against each other).

Covariate names and units are `runtime.stages.effects.COVARIATES`; the twin provides, per sample: time (s
since session start), temperature (degC), depth (mm), max_depth (mm), normal (unit vectors),
force_n / force_t (N), rim_distance (mm), gel_height (mm). Equations: docs/effects.md.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

from ...runtime.stages.effects import BUILTIN, CANONICAL, COVARIATES, STAGES, Param

log = logging.getLogger(__name__)

__all__ = ["CANONICAL", "COVARIATES", "STAGES", "Param", "EffectSpec", "SPECS", "register_spec",
           "parse_effect_arg"]


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

    @classmethod
    def from_effect(cls, effect) -> "EffectSpec":
        """The spec view of a runtime `Effect` class or instance (the canonical definition)."""
        return cls(effect.name, effect.summary, effect.equation, effect.stage, tuple(effect.params),
                   tuple(effect.covariates), dict(effect.off))

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
    """Add an effect spec (twin plugins call this); names are unique."""
    if spec.stage not in STAGES:
        raise ValueError(f"effect {spec.name}: stage {spec.stage!r} not in {STAGES}")
    bad = [c for c in spec.covariates if c not in COVARIATES]
    if bad:
        raise ValueError(f"effect {spec.name}: unknown covariates {bad} (known: {sorted(COVARIATES)})")
    SPECS[spec.name] = spec
    return spec


for _cls in BUILTIN:
    register_spec(EffectSpec.from_effect(_cls))


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
