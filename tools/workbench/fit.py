"""Fitting effect parameters to measurements (pure numpy/scipy core).

`Candidate` = the enabled chain (fixed parameters) followed by one effect whose free parameters
are fitted by bounded least squares (scipy.optimize.least_squares, dogbox) on a
subset of rows, started from the best point of a small grid over the bounds (robust to local
minima such as the relaxation time). Forward passes always run over the whole table (sequential
effects need the full series) but only the selected rows enter the cost; forward functions see
the model prediction and covariates only, never the measurements, so held-out rows cannot leak.
"""
from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, lsq_linear

from ...runtime.stages.effects import Effect, EffectChain
from .table import SampleTable

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FitConfig:
    grid_points: int = 3          # per free parameter (capped so the grid has <= max_grid points)
    max_grid: int = 27
    max_nfev: int = 40
    diff_step: float = 1e-3       # relative finite-difference step
    log_ratio: float = 20.0       # a positive range wider than this ratio is gridded in log


def deployed_prediction(model: np.ndarray, cov: dict, chain: EffectChain, post=None) -> np.ndarray:
    """Batch form of the deployed order on table rows: force-stage effects -> correction (`post`,
    the sensor's correction; None = none) -> measurement-stage effects (those model the reference
    instrument and are applied to the model side of the comparison)."""
    x = chain.apply(model, cov, stages=("force",))
    if post is not None:
        x = post(x)
    return chain.apply(x, cov, stages=("measurement",))


def channel_of(effect: Effect) -> str:
    """Which measurement an effect changes: 'force' or 'brightness'."""
    return "brightness" if effect.stage == "image" else "force"


class Channels:
    """Base prediction (model + enabled chain) and the measurements, per channel."""

    def __init__(self, table: SampleTable, chain: EffectChain, post=None):
        self.table = table
        self.cov = table.cov()
        self.chain = chain
        self.post = post
        self.pre = chain.apply(table.model, self.cov, stages=("force",))
        self.base_force = self.finish(self.pre)
        n = len(table)
        bright = self.cov.get("brightness")
        ok = self.cov.get("bright_ok")
        if bright is not None:
            mask = np.isfinite(bright) & (np.asarray(ok) > 0 if ok is not None else True)
        else:
            mask = np.zeros(n, bool)
        self.bright_rows = np.flatnonzero(mask)
        self.bright_meas = np.asarray(bright)[self.bright_rows] if bright is not None else np.zeros(0)
        self.base_gain = chain.image_gain(self.cov, n)[self.bright_rows]

    def apply(self, effect: Effect, x: np.ndarray, p: dict) -> np.ndarray:
        """effect.apply(x, cov, p), with a sequential effect's per-series split of the covariates
        computed once per table (same forward calls on the same arrays: identical numbers); series
        that are all zero are skipped for effects that declare `zero_in_zero_out`."""
        if not effect.sequential or "series" not in self.cov:
            return effect.apply(x, self.cov, p)
        if not hasattr(self, "_split"):
            series = np.asarray(self.cov["series"])
            n = len(series)
            self._split = []
            for s in np.unique(series):
                idx = np.flatnonzero(series == s)
                self._split.append((idx, {k: (v[idx] if isinstance(v, np.ndarray) and len(v) == n else v)
                                          for k, v in self.cov.items()}))
        x = np.asarray(x, dtype=np.float64)
        out = np.empty_like(x)
        skip = effect.zero_in_zero_out
        for idx, sub in self._split:
            xs = x[idx]
            if skip and not xs.any():
                out[idx] = 0.0
            else:
                out[idx] = effect.forward(xs, sub, p)
        return out

    def finish(self, x: np.ndarray) -> np.ndarray:
        """Force-stage output -> correction -> measurement-stage effects (the deployed order)."""
        if self.post is not None:
            x = self.post(x)
        return self.chain.apply(x, self.cov, stages=("measurement",))

    def rows(self, channel: str) -> np.ndarray:
        return np.arange(len(self.table)) if channel == "force" else self.bright_rows

    def base_residual(self, channel: str) -> np.ndarray:
        """(M, k) residual of the base prediction on the channel's rows."""
        if channel == "force":
            return self.table.meas - self.base_force
        return (self.bright_meas - self.base_gain)[:, None]


class Candidate:
    """One effect appended to the base chain; evaluates residuals for a parameter vector."""

    def __init__(self, effect: Effect, ch: Channels, cfg: FitConfig | None = None):
        self.effect, self.ch, self.cfg = effect, ch, cfg or FitConfig()
        self.channel = channel_of(effect)
        self.free = effect.free_params
        self.defaults = effect.resolve({})
        self.lo = np.array([p.lo for p in self.free])
        self.hi = np.array([p.hi for p in self.free])

    def params(self, theta: np.ndarray) -> dict:
        p = dict(self.defaults)
        p.update({q.name: float(v) for q, v in zip(self.free, np.clip(theta, self.lo, self.hi))})
        return p

    def residual(self, theta: np.ndarray) -> np.ndarray:
        """(M, k) residual on the channel's rows for parameters theta."""
        p = self.params(theta)
        ch = self.ch
        if self.channel == "force":
            if self.effect.stage == "force":   # inserted before the correction, as the runtime runs it
                return ch.table.meas - ch.finish(ch.apply(self.effect, ch.pre, p))
            return ch.table.meas - ch.apply(self.effect, ch.base_force, p)
        gain = self.effect.gain(ch.cov, p)[ch.bright_rows]
        return (ch.bright_meas - ch.base_gain * gain)[:, None]

    def _grid(self) -> list[np.ndarray]:
        k = len(self.free)
        per = max(2, min(self.cfg.grid_points, int(round(self.cfg.max_grid ** (1.0 / max(k, 1))))))
        axes = []
        for q in self.free:
            if q.lo > 0 and q.hi / q.lo > self.cfg.log_ratio:
                axes.append(np.geomspace(q.lo, q.hi, per + 2)[1:-1])
            else:
                axes.append(np.linspace(q.lo, q.hi, per + 2)[1:-1])
        off = self.effect.identity_params()
        start = [np.array([off[q.name] for q in self.free])]
        return start + [np.array(c) for c in itertools.product(*axes)]

    def scout(self, blk: np.ndarray) -> "Scout":
        """Evaluate the grid once: per grid point and block, the SSE; plus the rows the effect
        can change at all. Fold fits then pick their start from training-block sums only."""
        ids = np.unique(blk)
        if self.effect.linear:  # fitted exactly, no start point needed
            return Scout([], ids, np.zeros((0, len(ids))), np.ones(len(blk), bool))
        grid = self._grid() if self.free else [np.zeros(0)]
        r0 = self.residual(grid[0])
        costs = np.zeros((len(grid), len(ids)))
        active = np.zeros(len(r0), bool)
        for gi, g in enumerate(grid):
            r = r0 if gi == 0 else self.residual(g)
            if gi:
                active |= np.any(r != r0, axis=1)
            e = np.sum(r ** 2, axis=1)
            costs[gi] = [float(e[blk == b].sum()) for b in ids]
        return Scout(grid, ids, costs, active)

    def fit(self, rows: np.ndarray, scout: "Scout | None" = None, train_blocks=None) -> tuple[np.ndarray, float]:
        """Fit the free parameters on `rows` (indices into the channel's rows), started from the
        best grid point (`scout` + the training block ids, or a fresh grid over `rows`).
        Returns (theta, cost = sum of squared residuals on rows)."""
        if not self.free:
            return np.zeros(0), float(np.sum(self.residual(np.zeros(0))[rows] ** 2))
        if self.effect.linear:
            return self._fit_linear(rows)

        def cost(th):
            return float(np.sum(self.residual(th)[rows] ** 2))

        if scout is None:
            grid = self._grid()
            costs = np.array([cost(g) for g in grid])
            active = np.ones(len(self.residual(grid[0])), bool)
        else:
            grid = scout.grid
            cols = np.isin(scout.ids, train_blocks if train_blocks is not None else scout.ids)
            costs = scout.costs[:, cols].sum(axis=1)
            active = scout.active
        # rows the effect leaves unchanged at every grid point (e.g. zero force for a gain) only
        # add a constant to the cost: the optimizer works on the others
        sub = rows[active[rows]] if active[rows].any() else rows
        x0 = np.clip(grid[int(np.argmin(costs))], self.lo, self.hi)
        span = np.maximum(self.hi - self.lo, 1e-12)
        # least_squares needs x0 strictly inside the bounds
        x0 = np.clip(x0, self.lo + 1e-6 * span, self.hi - 1e-6 * span)
        try:
            sol = least_squares(lambda th: self.residual(th)[sub].ravel(), x0,
                                bounds=(self.lo, self.hi), x_scale=span, diff_step=self.cfg.diff_step,
                                max_nfev=self.cfg.max_nfev, method="dogbox")
            theta = sol.x
        except (ValueError, FloatingPointError) as exc:
            log.debug("least squares for %s failed (%s); keeping the grid point", self.effect.name, exc)
            theta = x0
        best = cost(theta)
        if best > float(np.min(costs)):  # never return something worse than the best grid point
            theta, best = grid[int(np.argmin(costs))], float(np.min(costs))
        return np.asarray(theta, dtype=np.float64), best


    def _fit_linear(self, rows: np.ndarray) -> tuple[np.ndarray, float]:
        """Affine effects: residual(θ) = r0 - J (θ - θ0) exactly; bounded linear least squares."""
        if not hasattr(self, "_lin"):
            th0 = np.array([self.effect.identity_params()[q.name] for q in self.free])
            r0 = self.residual(th0)
            span = np.maximum(self.hi - self.lo, 1e-12)
            J = np.stack([(r0 - self.residual(th0 + 0.1 * span * np.eye(len(th0))[i])).ravel() / (0.1 * span[i])
                          for i in range(len(th0))], axis=1)
            self._lin = (th0, r0, J)
        th0, r0, J = self._lin
        k = r0.shape[1]
        idx = (rows[:, None] * k + np.arange(k)).ravel()
        sol = lsq_linear(J[idx], r0.ravel()[idx], bounds=(self.lo - th0, self.hi - th0))
        theta = th0 + sol.x
        return theta, float(np.sum(self.residual(theta)[rows] ** 2))


@dataclass
class Scout:
    grid: list
    ids: np.ndarray
    costs: np.ndarray      # (grid points, blocks) SSE
    active: np.ndarray     # rows some grid point changes


def refit_chain(table: SampleTable, chain: EffectChain, cfg: FitConfig | None = None,
                post=None) -> tuple[EffectChain, float, float]:
    """Jointly refit the free parameters of every force/measurement-stage effect of `chain` on the
    whole table (bounded least squares from the current values): effects found one after the
    other were each fitted while the others were still missing. Returns (chain, rms before, after)."""
    from ...runtime.stages.effects import EnabledEffect

    cfg = cfg or FitConfig()
    items = [it for it in chain.items if it.effect.stage in ("force", "measurement")]
    slots = [(i, q) for i, it in enumerate(chain.items) if it in items for q in it.effect.free_params]
    if not slots:
        return chain, float("nan"), float("nan")
    cov = table.cov()
    x0 = np.array([chain.items[i].params[q.name] for i, q in slots])
    lo = np.array([q.lo for _, q in slots])
    hi = np.array([q.hi for _, q in slots])

    def build(theta) -> EffectChain:
        new = [EnabledEffect(it.effect, dict(it.params)) for it in chain.items]
        for (i, q), v in zip(slots, np.clip(theta, lo, hi)):
            new[i].params[q.name] = float(v)
        return EffectChain(new)

    def resid(theta):
        return (table.meas - deployed_prediction(table.model, cov, build(theta), post)).ravel()

    span = np.maximum(hi - lo, 1e-12)
    start = np.clip(x0, lo + 1e-6 * span, hi - 1e-6 * span)
    r0 = resid(x0)
    sol = least_squares(resid, start, bounds=(lo, hi), x_scale=span, diff_step=cfg.diff_step,
                        max_nfev=cfg.max_nfev * 2, method="dogbox")
    before = float(np.sqrt(np.mean(r0 ** 2) * 3))
    after = float(np.sqrt(np.mean(sol.fun ** 2) * 3))
    if after >= before:
        return chain, before, before
    return build(sol.x), before, after
