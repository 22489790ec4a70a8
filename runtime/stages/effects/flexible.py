"""Flexible members of the library's effect families: the same physics, a shape the data choose.

Each named library form (builtin.py) has a fixed equation; a real gel's curve need not follow it.
A flexible member keeps the physical meaning (the covariate, the sign, the stage) and lets the
shape be any monotone piecewise-linear function of the covariate on fixed knots (non-negative
increments, so the fit is an exact bounded linear least squares), or, for relaxation, a Prony
series with two terms. Diagnosis scores both members of a family on the same held-out blocks and
keeps the one with the lower held-out error (`family` names the library form).

    gain(c) = 1 + b + s * sum_k a_k ramp_k(c),   ramp_k(c) = clip((c - c_{k-1}) / (c_k - c_{k-1}), 0, 1)

s = +1 (grows with c) or -1 (falls with c); b only where the reference point is not known (temperature).
"""
from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from .base import Effect, Param, need, scale_rows
from .builtin import MIN_GAIN, MullinsSoftening, RimStiffening, StrainStiffening, TemperatureSoftening, prony_history, unilateral


def ramps(c: np.ndarray, knots: tuple) -> np.ndarray:
    """(N, K) ramp basis of c on K+1 knots."""
    k = np.asarray(knots, dtype=np.float64)
    return np.clip((np.asarray(c, dtype=np.float64)[:, None] - k[:-1]) / np.diff(k), 0.0, 1.0)


class MonotoneSpline(Effect):
    """Base of the spline members (not registered itself: no name).

    A member names its library form (`library`, whose name is its `family` and whose covariates it
    reads), its knots, the sign of its shape and the bound of each increment; its parameters
    (`lead`, then the increments a1..aK) and its identity (every parameter 0) follow from those."""

    library: type[Effect] | None = None
    knots: tuple = ()
    sign: float = 1.0
    increment_hi: float = 1.0    # upper bound of each increment a_k
    lead: tuple = ()             # parameters before the increments (temperature: the offset b)
    linear = True

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.library is not None:
            cls.family, cls.covariates = cls.library.name, cls.library.covariates
        cls.params = cls.lead + tuple(
            Param(f"a{k + 1}", "-", 0.05, 0.0, cls.increment_hi, f"gain change over knot interval {k + 1}")
            for k in range(len(cls.knots) - 1))
        cls.off = {p.name: 0.0 for p in cls.params}

    def covariate(self, cov: dict) -> np.ndarray:
        """The value the shape is a function of: by default the member's one covariate itself."""
        (name,) = self.covariates
        return need(cov, name, self.name)

    def increments(self, p: dict) -> np.ndarray:
        """(K,) the increments a1..aK of parameter values p."""
        return np.array([p[f"a{k + 1}"] for k in range(len(self.knots) - 1)])

    def shape(self, c: np.ndarray, p: dict) -> np.ndarray:
        """The gain as a function of the covariate value c."""
        return np.maximum(MIN_GAIN, 1.0 + p.get("b", 0.0) + self.sign * (ramps(c, self.knots) @ self.increments(p)))

    def forward(self, x, cov, p):
        return scale_rows(x, self.shape(self.covariate(cov), p))


class StrainStiffeningSpline(MonotoneSpline):
    name = "strain_stiffening_spline"
    library = StrainStiffening
    summary = "stiffening that grows with strain, any monotone shape (saturating, quadratic, ...)"
    words = "force grows faster than the model at deep indentation (free monotone shape)"
    equation = "F = F0 * (1 + sum_k a_k ramp_k(depth / gel_height)), a_k >= 0"
    knots = (0.0, 0.03, 0.06, 0.1, 0.15, 0.25)
    increment_hi = 3.0

    def covariate(self, cov):
        return np.clip(need(cov, "depth", self.name), 0.0, None) / need(cov, "gel_height", self.name)


class RimStiffeningSpline(MonotoneSpline):
    """The profile falls with the rim distance: each increment counts fully at the rim (1 - ramp)."""

    name = "rim_stiffening_spline"
    library = RimStiffening
    summary = "stiffening near the rim, any profile falling with the distance to it"
    words = "gel is stiffer near its rim (free profile)"
    equation = "F = F0 * (1 + sum_k a_k (1 - ramp_k(rim_distance))), a_k >= 0"
    knots = (0.0, 1.0, 2.0, 3.5, 5.5, 8.0)
    increment_hi = 3.0

    def shape(self, c, p):
        return np.maximum(MIN_GAIN, 1.0 + (1.0 - ramps(c, self.knots)) @ self.increments(p))


class TemperatureSofteningSpline(MonotoneSpline):
    name = "temperature_softening_spline"
    library = TemperatureSoftening
    summary = "softening with temperature, any monotone law"
    words = "gel softens as it warms (free monotone law)"
    equation = "F = F0 * (1 + b - sum_k a_k ramp_k(temperature)), a_k >= 0"
    knots = (15.0, 20.0, 24.0, 27.0, 30.0, 34.0, 45.0)
    sign = -1.0
    increment_hi = 0.5
    lead = (Param("b", "-", 0.0, -0.5, 0.5, "gain at the coldest knot minus 1"),)


class MullinsSofteningSpline(MonotoneSpline):
    name = "mullins_softening_spline"
    library = MullinsSoftening
    summary = "softer reloading below the largest past depth, any monotone shape"
    words = "gel is softer below its largest past indentation (free shape)"
    equation = "F = F0 * (1 - sum_k a_k ramp_k(max_depth - depth)), a_k >= 0"
    knots = (0.0, 0.1, 0.25, 0.5, 1.0, 2.0)
    sign = -1.0
    increment_hi = 0.6

    def covariate(self, cov):
        return np.clip(need(cov, "max_depth", self.name) - need(cov, "depth", self.name), 0.0, None)


class ViscoelasticRelaxation2(Effect):
    name = "viscoelastic_relaxation_2"
    family = "viscoelastic_relaxation"
    summary = "two-term Prony series (fast and slow relaxation), unilateral contact"
    words = "force relaxes after loading (two time scales)"
    equation = ("F(t) = (1 - g1 - g2) F0(t) + sum_i g_i int exp(-(t-s)/tau_i) dF0(s); "
                "F = 0 where F . F0 <= 0")
    params = (Param("g1", "-", 0.1, 0.0, 0.6, "fast relaxing fraction", "g₁"),
              Param("tau1", "s", 0.3, 0.02, 2.0, "fast relaxation time", "τ₁"),
              Param("g2", "-", 0.1, 0.0, 0.6, "slow relaxing fraction", "g₂"),
              Param("tau2", "s", 5.0, 1.0, 40.0, "slow relaxation time", "τ₂"))
    covariates = ("time",)
    off: ClassVar[dict] = {"g1": 0.0, "g2": 0.0}
    sequential = True
    zero_in_zero_out = True

    @staticmethod
    def _g(p):
        g1, g2 = p["g1"], p["g2"]
        s = g1 + g2
        return (g1, g2) if s <= 0.95 else (0.95 * g1 / s, 0.95 * g2 / s)

    def step(self, state: dict, t: float, x: np.ndarray, p: dict) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        if "h1" not in state:
            state["h1"], state["h2"] = x.copy(), x.copy()
        else:
            dt = max(t - state["t"], 1e-12)
            for key, tau in (("h1", p["tau1"]), ("h2", p["tau2"])):
                e = math.exp(-dt / tau)
                state[key] = e * state[key] + (x - state["x"]) * (tau * (1.0 - e) / dt)
        state["t"], state["x"] = t, x
        g1, g2 = self._g(p)
        return unilateral((1.0 - g1 - g2) * x + g1 * state["h1"] + g2 * state["h2"], x)

    def forward(self, x, cov, p):
        t = need(cov, "time", self.name)
        x = np.asarray(x, dtype=np.float64)
        g1, g2 = self._g(p)
        if g1 == 0.0 and g2 == 0.0:
            return x.copy()
        out = (1.0 - g1 - g2) * x
        if g1:
            out = out + g1 * prony_history(x, t, p["tau1"])
        if g2:
            out = out + g2 * prony_history(x, t, p["tau2"])
        return unilateral(out, x)


FLEXIBLE = (StrainStiffeningSpline, RimStiffeningSpline, TemperatureSofteningSpline, MullinsSofteningSpline,
            ViscoelasticRelaxation2)
