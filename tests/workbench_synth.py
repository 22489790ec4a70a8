"""Synthetic sample tables for the workbench's fast tests, and an INDEPENDENT alteration script.

The "truth" forms below are written separately from both runtime/effects (the model side) and
tools/twin/effects.py (the twin): e.g. viscoelasticity is simulated as a linear system with
scipy.signal.lsim instead of the recursive Prony update, so the tests do not check code against
itself. Poke plans imitate a human demonstrator: press / hold / (slide) / release at random
places on a dome, with temperature drifting during the session.
"""
from __future__ import annotations

import numpy as np
from scipy import signal
from scipy.special import erf
from tensortouch.tools.workbench.table import SampleTable

GEL_RADIUS = 12.0     # mm (dome radius of the synthetic gel)
SKIRT = 2.0
GEL_HEIGHT = 14.0


def _minjerk(s):
    s = np.clip(s, 0, 1)
    return s ** 3 * (10 - 15 * s + 6 * s * s)


def plan(seed: int, n_pokes: int = 40, rate: float = 50.0, theta_max: float = 1.35):
    """Per-sample depth, slide and position of one indenter following random pokes."""
    rng = np.random.default_rng(seed)
    segs = []
    t = 1.0
    for _ in range(n_pokes):
        th = np.arccos(1 - rng.random() * (1 - np.cos(theta_max)))
        ph = rng.uniform(-np.pi, np.pi)
        D = rng.uniform(0.4, 2.2)
        tp, th_, tr = rng.uniform(0.3, 0.8), rng.uniform(0.3, 1.5), rng.uniform(0.25, 0.5)
        slide = rng.uniform(0.4, 1.2) if rng.random() < 0.4 else 0.0
        tm = rng.uniform(0.4, 0.9) if slide else 0.0
        segs.append((t, th, ph, D, tp, th_, tm, tr, slide, rng.uniform(0, 2 * np.pi)))
        t += tp + th_ + tm + tr + rng.uniform(0.5, 1.2)
    T = t + 0.5
    time = np.arange(0.0, T, 1.0 / rate)
    depth = np.zeros_like(time)
    slip = np.zeros_like(time)
    theta = np.full_like(time, np.nan)
    phi = np.full_like(time, np.nan)
    sdir = np.zeros_like(time)
    for (t0, th, ph, D, tp, thd, tm, tr, sl, ang) in segs:
        m = (time >= t0) & (time <= t0 + tp + thd + tm + tr)
        u = time[m] - t0
        d = np.where(u < tp, D * _minjerk(u / tp), D)
        rel = u - tp - thd - tm
        d = np.where(rel > 0, D * (1 - _minjerk(rel / tr)), d)
        s = np.where(u > tp + thd, sl * _minjerk((u - tp - thd) / max(tm, 1e-9)), 0.0) if sl else 0 * u
        depth[m], slip[m], theta[m], phi[m], sdir[m] = d, s, th, ph, ang
    last_t, last_p = 0.3, 0.0
    for i in range(len(time)):  # park position between pokes: the last contact position
        if np.isnan(theta[i]):
            theta[i], phi[i] = last_t, last_p
        else:
            last_t, last_p = theta[i], phi[i]
    return time, depth, slip, theta, phi, sdir


def synth_table(seed: int = 0, n_pokes: int = 40, rate: float = 50.0, truth: list | None = None,
                noise: float = 0.004, bright_noise: float = 0.002, k: float = 0.35) -> SampleTable:
    """A table whose 'model' is a Hertz-like law and whose 'measurement' is truth + noise."""
    rng = np.random.default_rng(10_000 + seed)
    time, depth, slip, theta, phi, sdir = plan(seed, n_pokes, rate)
    n = len(time)
    normal = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    helper = np.where(np.abs(normal[:, 2:3]) < 0.9, [[0, 0, 1.0]], [[1.0, 0, 0]])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)
    tdir = np.cos(sdir)[:, None] * e1 + np.sin(sdir)[:, None] * e2
    fn = k * np.clip(depth, 0, None) ** 1.5
    ft = np.minimum(0.9 * np.sqrt(np.clip(depth, 0, None)) * slip, 2.2 * fn)
    model = -fn[:, None] * normal + ft[:, None] * tdir
    tip = tip_track(time, depth, normal, slip[:, None] * tdir)
    vel = np.gradient(tip, time, axis=0)
    acc = np.gradient(vel, time, axis=0)
    temperature = 24.0 + 7.0 * time / time[-1] + 0.5 * np.sin(time / 7.0)
    max_depth = np.maximum.accumulate(depth)
    rim = GEL_RADIUS * (np.pi / 2 - np.clip(theta, 0, np.pi / 2)) + SKIRT
    cols = {"t": time, "series": np.zeros(n), "time": time, "temperature": temperature,
            "depth": depth, "max_depth": max_depth, "rate": np.gradient(depth, time), "slip": slip,
            "rim_distance": rim, "gel_height": np.full(n, GEL_HEIGHT), "theta": theta, "phi": phi}
    cols.update({f"vel_{a}": vel[:, j] for j, a in enumerate("xyz")})
    cols.update({f"acc_{a}": acc[:, j] for j, a in enumerate("xyz")})
    meas, bright = alter(model, dict(cols, normal=normal), truth or [])
    meas = meas + rng.normal(0, noise, size=meas.shape)
    contact = depth > 0
    cols["brightness"] = np.where(contact, np.nan, bright + rng.normal(0, bright_noise, n))
    cols["bright_ok"] = (~contact).astype(float)
    return SampleTable(cols, meas, model, {"normal": normal}, {"synthetic": True})


def tip_track(time: np.ndarray, depth: np.ndarray, normal: np.ndarray, slide: np.ndarray,
              lift: float = 3.0) -> np.ndarray:
    """Indenter tip positions (N, 3) mm: on the poke's normal at radius R - depth (+ slide) in
    contact; between pokes it lifts by `lift` mm and travels to the next place (min-jerk)."""
    n = normal.copy()
    up = np.zeros(len(time))
    change = np.flatnonzero(np.any(np.abs(np.diff(normal, axis=0)) > 1e-9, axis=1)) + 1
    on = depth > 0
    for i in change:
        before = np.flatnonzero(on[:i])
        g0 = before[-1] + 1 if len(before) else 0
        if i - g0 < 3:
            continue
        s = _minjerk((np.arange(g0, i) - g0) / (i - g0))[:, None]
        v = (1 - s) * normal[g0 - 1 if g0 else 0] + s * normal[i]
        n[g0:i] = v / np.linalg.norm(v, axis=1, keepdims=True)
        up[g0:i] = lift * np.sin(np.pi * s[:, 0])
    return (GEL_RADIUS + up - depth)[:, None] * n + slide


def alter(force: np.ndarray, cov: dict, truth: list) -> tuple[np.ndarray, np.ndarray]:
    """Apply hidden 'truth' effects [(name, params)] to forces; also returns the brightness ratio.
    Independent implementations (see module docstring)."""
    f = np.array(force, dtype=np.float64)
    t = cov["time"]
    bright = np.ones(len(f))
    for name, p in truth:
        if name == "temperature_softening":
            f *= (1 - p["alpha"] * (cov["temperature"] - p["t_ref"]))[:, None]
        elif name == "viscoelastic_relaxation":
            g, tau = p["g1"], p["tau"]
            sys_ = signal.lti([tau, 1 - g], [tau, 1.0])
            out = np.empty_like(f)
            for j in range(3):  # plans start out of contact (force 0): zero initial state
                _, y, _ = signal.lsim(sys_, f[:, j], t, interp=True)
                out[:, j] = y
            out[np.einsum("ij,ij->i", out, f) <= 0] = 0.0   # no contact, or it would pull: contact lost
            f = out
        elif name == "mullins_softening":
            gap = np.clip(cov["max_depth"] - cov["depth"], 0, None)
            f *= (1 - p["r"] * erf(gap / p["m"]))[:, None]
        elif name == "strain_stiffening":
            f *= (1 + p["k"] * (cov["depth"] / cov["gel_height"]) ** 2)[:, None]
        elif name == "friction_mismatch":
            n = cov["normal"]
            fnv = np.einsum("ij,ij->i", f, n)[:, None] * n
            ftv = f - fnv
            lim = p["mu"] * np.linalg.norm(fnv, axis=1)
            mag = np.linalg.norm(ftv, axis=1)
            f = fnv + ftv * np.minimum(1.0, lim / np.maximum(mag, 1e-12))[:, None]
        elif name == "rim_stiffening":
            f *= (1 + p["a"] * np.exp(-cov["rim_distance"] / p["w"]))[:, None]
        elif name == "ft_bias_drift":
            f += np.outer(t, [p["bx"], p["by"], p["bz"]])
        elif name == "led_drift":
            g = 1 + p["c"] * t + p["beta"] * (cov["temperature"] - p["t_ref"])
            bright = bright * g / g[0]
        elif name == "velocity_drag":      # NOT in the library: a drag on the indenter, in and out of contact
            f -= p["c"] * np.column_stack([cov["vel_x"], cov["vel_y"], cov["vel_z"]])
        elif name == "azimuth_stiffness":  # NOT in the library: the 'unknown effect'
            f *= (1 + p["a"] * np.cos(cov["phi"] - p["phi0"]))[:, None]
        else:
            raise ValueError(name)
    return f, bright
