"""The model's own error, modelled: the residual structure a model shows on clean calibration
sessions (no hidden physics), so diagnosis can tell what is NEW on a session from what the model
always gets wrong (pure core, no files).

A trained network is not exact: its error depends on where and how hard the gel is pressed, on the
image's brightness, on the loading rate ... On a clean session that structure is the model's, not
missing physics; a library effect that happens to follow it (an LED drift along brightness, a
temperature softening along a drift the network tracks badly) would otherwise be diagnosed.

Fit (on the residual r = measured - deployed prediction of one or more calibration sessions):

    r ≈ Σ_g X_g(c_g, F) w_g          groups g chosen by forward selection
        additive g:        r_j ≈ s_j(c)        a per-axis offset that depends on covariate c
        multiplicative g:  r ≈ F · s(c)        a gain error that depends on c
        constant:          an offset per axis and a plain gain

s = piecewise-linear (hat basis on the calibration rows' quantiles, light ridge), the same small
models the covariate scan uses (scan.py). Groups enter one at a time while the held-out error on
blocks of whole presses of the calibration sessions (the diagnosis' blocks, per session) falls by
at least `min_gain`; a dependence that does not repeat across presses does not enter. Session time
and the mocap-only covariates (velocity, acceleration) are not used: the model's own error cannot
depend on when a session started or on a stream the sensor does not have.

Use: `OwnError.post(cov, post)` wraps the sensor's correction (or none) so the diagnosis' base
prediction is model -> effects -> correction -> own error, and every candidate effect is scored on
what the model's own error does not already explain (same blocked CV, same test).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from .scan import hat_basis

OWN_COVARIATES = ("depth", "rate", "slip", "temperature", "load_history", "max_depth", "theta", "phi",
                  "rim_distance", "brightness", "force_n", "force_t")


@dataclass(frozen=True)
class OwnErrorConfig:
    covariates: tuple = OWN_COVARIATES
    knots: int = 6
    ridge: float = 1e-3           # relative to the mean diagonal of the normal equations
    min_gain: float = 0.01        # a group enters when the held-out SSE falls by this share
    max_groups: int = 6


@dataclass
class OwnError:
    """Selected groups [(covariate or "constant", form, knots)] and their stacked weights."""

    groups: list = field(default_factory=list)
    weights: list = field(default_factory=list)
    heldout: dict = field(default_factory=dict)    # calibration held-out rms before/after, sessions
    source: str = ""

    # ----- design --------------------------------------------------------------------------
    @staticmethod
    def _column(cov: dict, name: str, n: int) -> tuple[np.ndarray, np.ndarray]:
        c = np.asarray(cov.get(name, np.full(n, np.nan)), dtype=np.float64)
        ok = np.isfinite(c)
        return np.where(ok, c, 0.0), ok

    @classmethod
    def design(cls, group: tuple, cov: dict, pred: np.ndarray) -> np.ndarray:
        """(3N, k) design of one group on rows with prediction `pred` (N, 3)."""
        name, form, knots = group
        n = len(pred)
        if name == "constant":
            B, ok = np.ones((n, 1)), np.ones(n, bool)
        else:
            c, ok = cls._column(cov, name, n)
            B = hat_basis(c, np.asarray(knots, dtype=np.float64)) * ok[:, None]
        k = B.shape[1]
        if form == "additive":
            X = np.zeros((3 * n, 3 * k))
            for j in range(3):
                X[j::3, j * k:(j + 1) * k] = B
            return X
        return (pred[:, :, None] * B[:, None, :]).reshape(3 * n, k)

    def correction(self, cov: dict, pred: np.ndarray) -> np.ndarray:
        """(N, 3) the model's own error predicted on rows with prediction `pred`."""
        pred = np.asarray(pred, dtype=np.float64)
        out = np.zeros(pred.size)
        for g, w in zip(self.groups, self.weights):
            out += self.design(tuple(g), cov, pred) @ np.asarray(w)
        return out.reshape(pred.shape)

    def apply(self, pred: np.ndarray, cov: dict) -> np.ndarray:
        return np.asarray(pred, dtype=np.float64) + self.correction(cov, pred)

    def post(self, cov: dict, post=None):
        """The sensor's correction `post` (None = none) followed by this model, on one table's rows."""
        def finish(x):
            x = post(x) if post is not None else x
            return self.apply(x, cov)
        return finish

    def describe(self) -> str:
        if not self.groups:
            return "no structure that repeats across presses"
        return ", ".join(f"{'offset' if f == 'additive' else 'gain'}" + ("" if n == "constant" else f" along {n}")
                         for n, f, _ in self.groups)

    # ----- fit -----------------------------------------------------------------------------
    @classmethod
    def fit(cls, parts: list, cfg: OwnErrorConfig | None = None, source: str = "") -> "OwnError":
        """`parts`: [(cov, pred (N,3), meas (N,3), blocks (N,))] of clean calibration sessions (blocks
        of whole presses per session)."""
        cfg = cfg or OwnErrorConfig()
        cov = {k: np.concatenate([np.asarray(p[0].get(k, np.full(len(p[1]), np.nan)), dtype=np.float64)
                                  for p in parts]) for k in cfg.covariates}
        pred = np.concatenate([np.asarray(p[1], dtype=np.float64) for p in parts])
        resid = np.concatenate([np.asarray(p[2], dtype=np.float64) for p in parts]) - pred
        blocks, off = [], 0
        for p in parts:
            b = np.asarray(p[3], dtype=int)
            blocks.append(b + off)
            off += int(b.max()) + 1 if len(b) else 0
        blocks = np.concatenate(blocks)
        cands = [("constant", "additive", []), ("constant", "multiplicative", [])]
        for name in cfg.covariates:
            c = cov[name]
            ok = np.isfinite(c)
            if ok.sum() < 10 or len(np.unique(c[ok])) < 4:
                continue
            knots = np.unique(np.quantile(c[ok], np.linspace(0, 1, cfg.knots))).tolist()
            if len(knots) >= 2:
                cands += [(name, "additive", knots), (name, "multiplicative", knots)]
        X = [cls.design(g, cov, pred) for g in cands]
        y = resid.reshape(-1)
        rb = np.repeat(blocks, 3)
        ids = np.unique(blocks)
        full = np.hstack(X)
        spans = np.cumsum([0] + [x.shape[1] for x in X])
        stats = []
        for b in ids:
            m = rb == b
            Xb, yb = full[m], y[m]
            stats.append((Xb.T @ Xb, Xb.T @ yb, float(yb @ yb)))
        XtX = sum(s[0] for s in stats)
        Xty = sum(s[1] for s in stats)
        yy = sum(s[2] for s in stats)

        def cv(cols: np.ndarray) -> float:
            if len(cols) == 0:
                return yy
            sse = 0.0
            for A_b, c_b, yy_b in stats:
                A = XtX[np.ix_(cols, cols)] - A_b[np.ix_(cols, cols)]
                A[np.diag_indices_from(A)] += cfg.ridge * max(float(np.mean(np.diag(A))), 1e-12)
                w = np.linalg.solve(A, Xty[cols] - c_b[cols])
                Ab = A_b[np.ix_(cols, cols)]
                sse += max(yy_b - 2.0 * float(w @ c_b[cols]) + float(w @ Ab @ w), 0.0)
            return sse

        chosen: list[int] = []
        cur = yy
        while len(chosen) < cfg.max_groups:
            best, best_sse = None, cur
            for i in range(len(cands)):
                if i in chosen:
                    continue
                cols = np.concatenate([np.arange(spans[j], spans[j + 1]) for j in chosen + [i]])
                s = cv(cols)
                if s < best_sse:
                    best, best_sse = i, s
            if best is None or best_sse > (1.0 - cfg.min_gain) * cur:
                break
            chosen.append(best)
            cur = best_sse
        out = cls(source=source)
        if chosen:
            cols = np.concatenate([np.arange(spans[j], spans[j + 1]) for j in chosen])
            A = XtX[np.ix_(cols, cols)].copy()
            A[np.diag_indices_from(A)] += cfg.ridge * max(float(np.mean(np.diag(A))), 1e-12)
            w = np.linalg.solve(A, Xty[cols])
            for j in chosen:
                k = spans[j + 1] - spans[j]
                out.groups.append(list(cands[j]))
                out.weights.append(w[:k].tolist())
                w = w[k:]
        n = max(len(y) // 3, 1)
        out.heldout = {"rms_before": float(np.sqrt(yy / n)), "rms_after": float(np.sqrt(cur / n)),
                       "sessions": len(parts), "blocks": int(len(ids))}
        return out

    def to_json(self) -> dict:
        return {"schema": "tensortouch.own_error", "groups": self.groups, "weights": self.weights,
                "heldout": self.heldout, "source": self.source, "describe": self.describe()}

    @classmethod
    def from_json(cls, d: dict) -> "OwnError":
        return cls([list(g) for g in d["groups"]], d["weights"], d.get("heldout", {}), d.get("source", ""))

    def fingerprint(self) -> str:
        import hashlib

        return hashlib.sha256(json.dumps([self.groups, self.weights]).encode()).hexdigest()[:12]
