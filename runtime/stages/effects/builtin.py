"""The eight library effects, model side (cheap numpy forms).

These classes are the canonical definitions of the library effects (names, parameters, units,
bounds, covariates); the digital twin reads its specs from them (tools/twin/effect_specs.py). The
forward forms are written here independently of the twin's truth forms (docs/effects-model.md);
tests/test_effects_builtin.py checks that the two agree.
"""
from __future__ import annotations

import logging
import math

import numpy as np
from scipy.special import erf

from .base import Effect, Param, need, scale_rows

log = logging.getLogger(__name__)

MIN_GAIN = 0.05          # a multiplicative correction never goes below this (no sign flips)
UNIFORM_DT_TOL = 1e-6    # relative spread of sample spacing below which the fast filter is used


class TemperatureSoftening(Effect):
    name = "temperature_softening"
    summary = "gel stiffness falls linearly with temperature"
    words = "force falls as the gel warms"
    equation = "F = F0 * max(0.05, 1 - alpha * (T - t_ref))"
    params = (Param("alpha", "1/degC", 0.01, 0.0, 0.05, "relative stiffness loss per degree", "α"),
              Param("t_ref", "degC", 25.0, 0.0, 60.0, "temperature at which the model holds", "T_ref"))
    covariates = ("temperature",)
    off = {"alpha": 0.0}

    def forward(self, x, cov, p):
        temp = need(cov, "temperature", self.name)
        return scale_rows(x, np.maximum(MIN_GAIN, 1.0 - p["alpha"] * (temp - p["t_ref"])))


def prony_history(x: np.ndarray, t: np.ndarray, tau: float) -> np.ndarray:
    """h(t) = int exp(-(t-s)/tau) dx(s) for x piecewise linear between samples, with x held at
    x[0] before the first sample (so h[0] = x[0]). Exact recursion; a linear filter when the
    spacing is uniform."""
    x = np.asarray(x, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if len(t) < 2:
        return x.copy()
    dt = np.diff(t)
    if np.all(dt > 0) and np.ptp(dt) <= UNIFORM_DT_TOL * max(float(np.median(dt)), 1e-12):
        d = float(np.mean(dt))
        e = math.exp(-d / tau)
        b = tau * (1.0 - e) / d
        zi = ((1.0 - b) * x[:1]).reshape((1,) + x.shape[1:])
        from scipy.signal import lfilter  # here, not at module import: scipy.signal costs 1.3 s to import

        h, _ = lfilter([b, -b], [1.0, -e], x, axis=0, zi=zi)
        return h
    h = np.empty_like(x)
    h[0] = x[0]
    for i in range(1, len(t)):
        step = max(t[i] - t[i - 1], 1e-12)
        e = math.exp(-step / tau)
        h[i] = e * h[i - 1] + (x[i] - x[i - 1]) * (tau * (1.0 - e) / step)
    return h


def unilateral(out: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A gel does not pull on the indenter: rows without elastic contact force (x = 0) or whose
    relaxed force points against it (out . x <= 0 over the force part) are 0 (contact lost)."""
    out = np.asarray(out, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    keep = np.sum(out[..., :3] * x[..., :3], axis=-1) > 0.0
    return out * np.asarray(keep, dtype=np.float64)[..., None]


class ViscoelasticRelaxation(Effect):
    name = "viscoelastic_relaxation"
    summary = "one-term Prony series (quasi-linear viscoelasticity) on the force, unilateral contact"
    words = "force relaxes after loading"
    equation = "F(t) = (1 - g1) F0(t) + g1 * int exp(-(t-s)/tau) dF0(s); F = 0 where F . F0 <= 0"
    params = (Param("g1", "-", 0.2, 0.0, 0.8, "relaxing fraction of the instantaneous modulus", "g"),
              Param("tau", "s", 1.0, 0.02, 30.0, "relaxation time", "τ"))
    covariates = ("time",)
    off = {"g1": 0.0}
    sequential = True
    zero_in_zero_out = True      # linear in the force history, held at x[0] before the first sample

    def step(self, state: dict, t: float, x: np.ndarray, p: dict) -> np.ndarray:
        """One new sample of one contact track (runtime, frame by frame); same recursion as forward."""
        x = np.asarray(x, dtype=np.float64)
        if "h" not in state:
            state["h"] = x.copy()
        else:
            dt = max(t - state["t"], 1e-12)
            e = math.exp(-dt / p["tau"])
            state["h"] = e * state["h"] + (x - state["x"]) * (p["tau"] * (1.0 - e) / dt)
        state["t"], state["x"] = t, x
        return unilateral((1.0 - p["g1"]) * x + p["g1"] * state["h"], x)

    def forward(self, x, cov, p):
        t = need(cov, "time", self.name)
        x = np.asarray(x, dtype=np.float64)
        if p["g1"] == 0.0:
            return x.copy()
        return unilateral((1.0 - p["g1"]) * x + p["g1"] * prony_history(x, t, p["tau"]), x)


class MullinsSoftening(Effect):
    name = "mullins_softening"
    summary = "softer reloading below the largest past depth (Ogden-Roxburgh style)"
    words = "gel is softer below its largest past indentation"
    equation = "F = F0 * (1 - r * erf((max_depth - depth) / m))"
    params = (Param("r", "-", 0.15, 0.0, 0.6, "largest relative softening", "r"),
              Param("m", "mm", 0.5, 0.05, 5.0, "depth scale of the softening", "m"))
    covariates = ("depth", "max_depth")
    off = {"r": 0.0}

    def forward(self, x, cov, p):
        gap = np.clip(need(cov, "max_depth", self.name) - need(cov, "depth", self.name), 0.0, None)
        return scale_rows(x, 1.0 - p["r"] * erf(gap / p["m"]))


class StrainStiffening(Effect):
    name = "strain_stiffening"
    summary = "extra stiffening at large strain beyond the model's hyperelastic terms"
    words = "force grows faster than the model at deep indentation"
    equation = "F = F0 * (1 + k * (depth / gel_height)^2)"
    params = (Param("k", "-", 4.0, 0.0, 50.0, "quadratic stiffening coefficient", "k"),)
    covariates = ("depth", "gel_height")
    off = {"k": 0.0}

    def forward(self, x, cov, p):
        d = np.clip(need(cov, "depth", self.name), 0.0, None)
        return scale_rows(x, 1.0 + p["k"] * (d / need(cov, "gel_height", self.name)) ** 2)


class FrictionMismatch(Effect):
    name = "friction_mismatch"
    summary = "true Coulomb friction is lower than the model's: shear force saturates"
    words = "shear force saturates (friction lower than modelled)"
    equation = "F_t = F0_t * min(1, mu * |F_n| / |F0_t|), F_n unchanged"
    params = (Param("mu", "-", 0.6, 0.05, 3.0, "true friction coefficient", "μ"),)
    covariates = ("normal",)
    off = {"mu": 3.0}

    def forward(self, x, cov, p):
        x = np.asarray(x, dtype=np.float64)
        n = need(cov, "normal", self.name).reshape(-1, 3)
        fn = np.sum(x * n, axis=1, keepdims=True) * n
        ft = x - fn
        ft_mag = np.linalg.norm(ft, axis=1)
        cap = p["mu"] * np.linalg.norm(fn, axis=1)
        ratio = np.where(ft_mag > cap, cap / np.maximum(ft_mag, 1e-12), 1.0)
        return fn + ft * ratio[:, None]


class RimStiffening(Effect):
    name = "rim_stiffening"
    summary = "gel-skin / bonding stiffening near the rim"
    words = "gel is stiffer near the rim"
    equation = "F = F0 * (1 + a * exp(-rim_distance / w))"
    params = (Param("a", "-", 0.5, 0.0, 3.0, "relative stiffening at the rim", "a"),
              Param("w", "mm", 2.0, 0.2, 10.0, "decay length from the rim", "w"))
    covariates = ("rim_distance",)
    off = {"a": 0.0}

    def forward(self, x, cov, p):
        s = np.clip(need(cov, "rim_distance", self.name), 0.0, None)
        return scale_rows(x, 1.0 + p["a"] * np.exp(-s / p["w"]))


class FTBiasDrift(Effect):
    name = "ft_bias_drift"
    summary = "force/torque reference bias drifting linearly in time (F/T frame)"
    words = "the force reference drifts in time"
    equation = "F_meas = F + R_ft * (bx, by, bz) * t"
    stage = "measurement"
    params = (Param("bx", "N/s", 0.0, -0.02, 0.02, "x bias drift rate (F/T frame)", "b_x"),
              Param("by", "N/s", 0.0, -0.02, 0.02, "y bias drift rate (F/T frame)", "b_y"),
              Param("bz", "N/s", 0.004, -0.02, 0.02, "z bias drift rate (F/T frame)", "b_z"))
    covariates = ("time",)
    off = {"bx": 0.0, "by": 0.0, "bz": 0.0}
    linear = True

    def forward(self, x, cov, p):
        t = need(cov, "time", self.name)
        b = np.array([p["bx"], p["by"], p["bz"]])
        rot = cov.get("ft_rotation")
        drift = b[None, :] * t[:, None] if rot is None else np.einsum("nij,j->ni", rot, b) * t[:, None]
        return np.asarray(x, dtype=np.float64) + drift


class LEDDrift(Effect):
    name = "led_drift"
    summary = "LED brightness drifting in time and with temperature"
    words = "image brightness drifts"
    equation = "g = 1 + c * t + beta * (T - t_ref)  (image intensity gain)"
    stage = "image"
    params = (Param("c", "1/s", -0.002, -0.02, 0.02, "brightness change per second", "c"),
              Param("beta", "1/degC", 0.0, -0.05, 0.05, "brightness change per degree", "β"),
              Param("t_ref", "degC", 25.0, 0.0, 60.0, "reference temperature", "T_ref"))
    covariates = ("time", "temperature")
    off = {"c": 0.0, "beta": 0.0}
    fixed = ("t_ref",)   # only the gain relative to the baseline frames is observable
    linear = True

    def gain(self, cov, p):
        t = need(cov, "time", self.name)
        temp = np.asarray(cov.get("temperature", np.full_like(t, p["t_ref"])), dtype=np.float64)
        return np.maximum(MIN_GAIN, 1.0 + p["c"] * t + p["beta"] * (temp - p["t_ref"]))

    def forward(self, x, cov, p):
        return scale_rows(x, self.gain(cov, p))


BUILTIN = (TemperatureSoftening, ViscoelasticRelaxation, MullinsSoftening, StrainStiffening,
           FrictionMismatch, RimStiffening, FTBiasDrift, LEDDrift)
CANONICAL = tuple(cls.name for cls in BUILTIN)
