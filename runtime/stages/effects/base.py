"""The effect plugin API (model side): one small class per piece of physics.

An effect names a piece of physics the sensor model does not know by itself, with a few
parameters in physical units and bounds, the per-sample covariates it needs, and a cheap numpy
`forward` that turns the model's *nominal* prediction into what the real sensor would show:

    stage "force"        forward(F (N,3) N, cov, p) -> corrected contact force (N,3) N.
                         The runtime applies it to every predicted contact force.
    stage "measurement"  forward(F, cov, p) -> what the *reference instrument* reads for force F
                         (e.g. a drifting F/T bias). The workbench applies it to the model side of
                         the comparison (equivalently: corrects the reference); the runtime never
                         changes published forces for it.
    stage "image"        gain(cov, p) -> (N,) image intensity gain (1 = calibration brightness);
                         forward(x, cov, p) = x * gain. The runtime divides frames by the gain
                         before inference; the workbench compares it with frame brightness.

Parameter names, units and bounds are shared with the digital twin's specs of the same effect
(docs/effects-model.md). A user plugin subclasses `Effect`; see docs/workbench.md.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ....contracts.errors import TensorTouchError

log = logging.getLogger(__name__)


class EffectError(TensorTouchError, ValueError):
    """An effect, its parameters, a plugin or an effect list is wrong (names the culprit)."""


class MissingCovariate(EffectError, KeyError):
    """An effect needs a covariate the caller did not provide."""

STAGES = ("force", "measurement", "image")

# Per-sample covariates the workbench and the runtime know how to provide (name -> unit).
COVARIATES = {
    "time": "s",                 # since session (or runtime) start
    "temperature": "degC",
    "depth": "mm",               # indentation normal to the rest surface (0 out of contact)
    "max_depth": "mm",           # largest depth reached earlier by the same indenter/contact
    "rate": "mm/s",              # d(depth)/dt
    "slip": "mm",                # tangential travel of the contact since touch-down
    "force_n": "N",              # normal force magnitude of the model prediction
    "force_t": "N",              # tangential force magnitude of the model prediction
    "rim_distance": "mm",        # arc length from the contact point to the gel rim
    "gel_height": "mm",
    "theta": "rad",              # contact position on the gel (angle from the axis)
    "phi": "rad",                # contact azimuth
    "brightness": "-",           # mean frame intensity / baseline intensity
    "normal": "unit (N,3)",      # outward rest-surface normal at the contact
    "ft_rotation": "(N,3,3)",    # rotation taking the F/T frame into the sensor frame
    "series": "-",               # integer id of the time series a sample belongs to (indenter)
    # the indenter's own motion from mocap, in and out of contact: the workbench only (the runtime has
    # no mocap), so for "measurement"-stage effects (what the reference instrument reads)
    "vel_x": "mm/s", "vel_y": "mm/s", "vel_z": "mm/s",
    "acc_x": "mm/s^2", "acc_y": "mm/s^2", "acc_z": "mm/s^2",
}


@dataclass(frozen=True)
class Param:
    """One effect parameter in physical units with its allowed range."""

    name: str
    unit: str
    default: float
    lo: float
    hi: float
    doc: str = ""
    symbol: str = ""             # how the parameter is written in words (default: its name)

    def check(self, value: float, effect: str) -> float:
        value = float(value)
        if not np.isfinite(value) or not (self.lo <= value <= self.hi):
            raise EffectError(f"effect {effect}: parameter {self.name}={value} {self.unit} outside "
                             f"[{self.lo}, {self.hi}]")
        return value


class Effect:
    """Base class of every effect. Subclasses set the class attributes and write `forward`."""

    name: str = ""
    summary: str = ""            # one line: what physics
    words: str = ""              # how diagnosis states it, e.g. "force relaxes after loading: viscoelastic"
    equation: str = ""
    stage: str = "force"
    params: tuple[Param, ...] = ()
    covariates: tuple[str, ...] = ()
    off: dict = {}               # parameter values for which the effect is the identity
    sequential: bool = False     # forward needs one series (indenter) in time order per call
    fixed: tuple[str, ...] = ()  # parameters held at their default when fitting (not identifiable)
    linear: bool = False         # hint: output is affine in the free parameters (exact linear fit)
    zero_in_zero_out: bool = False  # a series of zero forces stays exactly zero (lets fits skip it)
    family: str = ""             # the library effect this is a flexible member of (flexible.py); "" = itself

    # ----- to be written by subclasses -------------------------------------------------------
    def forward(self, x: np.ndarray, cov: dict, p: dict) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError(f"effect {self.name}: forward not written")

    def step(self, state: dict, t: float, x: np.ndarray, p: dict) -> np.ndarray:  # sequential only
        """Streaming form of a sequential effect: one sample (3,) of one track at time t; `state`
        is the track's dict, kept by the caller between calls (see EffectChain.stream)."""
        raise NotImplementedError(f"effect {self.name}: sequential effect without a streaming step()")

    def gain(self, cov: dict, p: dict) -> np.ndarray:  # image effects only
        raise NotImplementedError(f"effect {self.name}: stage {self.stage} has no image gain")

    # ----- shared helpers ---------------------------------------------------------------------
    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise EffectError(f"effect {self.name}: no parameter {name!r} (has {self.param_names})")

    @property
    def param_names(self) -> list[str]:
        return [p.name for p in self.params]

    @property
    def free_params(self) -> list[Param]:
        return [p for p in self.params if p.name not in self.fixed]

    def resolve(self, values: dict | None = None) -> dict[str, float]:
        """Defaults overridden by `values`, each checked against its bounds."""
        values = dict(values or {})
        unknown = set(values) - set(self.param_names)
        if unknown:
            raise EffectError(f"effect {self.name}: unknown parameter(s) {sorted(unknown)} "
                             f"(has {self.param_names})")
        return {p.name: p.check(values.get(p.name, p.default), self.name) for p in self.params}

    def identity_params(self) -> dict[str, float]:
        return self.resolve(self.off)

    def apply(self, x: np.ndarray, cov: dict, p: dict) -> np.ndarray:
        """forward(), run per series (indenter) in time order when the effect is sequential."""
        if not self.sequential or "series" not in cov:
            return self.forward(x, cov, p)
        series = np.asarray(cov["series"])
        out = np.empty_like(np.asarray(x, dtype=np.float64))
        for s in np.unique(series):
            idx = np.flatnonzero(series == s)
            sub = {k: (v[idx] if isinstance(v, np.ndarray) and len(v) == len(series) else v)
                   for k, v in cov.items()}
            out[idx] = self.forward(np.asarray(x)[idx], sub, p)
        return out

    def describe(self, p: dict) -> str:
        """The effect in words with its parameters and units."""
        parts = []
        for q in self.params:
            if q.name in self.fixed:
                continue
            unit = "" if q.unit in ("-", "") else f" {q.unit}"
            parts.append(f"{q.symbol or q.name} = {p[q.name]:.3g}{unit}")
        head = self.words or self.summary or self.name
        return f"{head}: {self.name}, " + ", ".join(parts) if parts else f"{head}: {self.name}"

    def spec(self) -> dict:
        """JSON-able description (for `effects list --json`)."""
        return {"name": self.name, "summary": self.summary, "equation": self.equation,
                "stage": self.stage, "covariates": list(self.covariates), "off": dict(self.off),
                "fixed": list(self.fixed),
                "params": [{"name": q.name, "unit": q.unit, "default": q.default, "lo": q.lo,
                            "hi": q.hi, "doc": q.doc} for q in self.params]}


def need(cov: dict, name: str, effect: str) -> np.ndarray:
    """A covariate as a float array, or a clear error naming the effect that needs it."""
    if name not in cov:
        raise MissingCovariate(f"effect {effect}: covariate {name!r} missing (have {sorted(cov)})")
    return np.asarray(cov[name], dtype=np.float64)


def scale_rows(x: np.ndarray, factor: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    f = np.asarray(factor, dtype=np.float64)
    return x * f.reshape((-1,) + (1,) * (x.ndim - 1))
