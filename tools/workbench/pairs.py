"""Two effects at once (pure core): when two effects are missing together, each one alone can
explain little: the fit of one bends to absorb the other's residual (a relaxation fitted where the
force is also stiffened near the rim lands on its bounds and removes ~0 %). Diagnosis then scores
*pairs* of force-channel candidates jointly, with the same held-out blocks and the same sign-flip
test as single effects (diagnose.py), and names the member to add first.

Cost control, in this order:
1. screening: every pair is fitted once on all blocks from its members' single fits (the joint
   fit can only improve on them); only the `max_pairs` pairs with the largest in-sample reduction
   beyond their best member are cross-validated;
2. each held-out fold starts from that fold's own single fits (training blocks only: no leak),
   bounded least squares with a small evaluation budget;
3. Holm's correction counts *every* pair screened, not only those cross-validated, so screening
   does not buy significance.
The member added first is the one that keeps more of the pair's held-out reduction on its own at
the pair's parameters; after `effects add`, the next diagnosis finds the other as a single effect.
"""
from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from .fit import Candidate, Channels

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairConfig:
    max_pairs: int = 4            # pairs cross-validated after screening
    max_nfev: int = 12            # joint least-squares evaluations per fit
    min_gain: float = 0.05        # the pair must beat its best member's held-out reduction by this


class PairCandidate:
    """Two force-channel candidates applied together in the deployed order (force-stage effects
    before the correction, measurement-stage effects after it)."""

    def __init__(self, a: Candidate, b: Candidate, cfg: PairConfig):
        self.a, self.b, self.cfg = a, b, cfg
        self.ch: Channels = a.ch
        self.k = len(a.free)
        self.lo = np.concatenate([a.lo, b.lo])
        self.hi = np.concatenate([a.hi, b.hi])

    def split(self, theta):
        return theta[:self.k], theta[self.k:]

    def identity(self) -> np.ndarray:
        ids = []
        for c in (self.a, self.b):
            off = c.effect.identity_params()
            ids.append([off[q.name] for q in c.free])
        return np.concatenate([np.asarray(i, float) for i in ids])

    def residual(self, theta: np.ndarray) -> np.ndarray:
        ta, tb = self.split(np.clip(theta, self.lo, self.hi))
        members = ((self.a, self.a.params(ta)), (self.b, self.b.params(tb)))
        ch = self.ch
        x = ch.pre
        for c, p in members:
            if c.effect.stage == "force":
                x = ch.apply(c.effect, x, p)
        x = ch.finish(x)
        for c, p in members:
            if c.effect.stage != "force":
                x = ch.apply(c.effect, x, p)
        return ch.table.meas - x

    def fit(self, rows: np.ndarray, starts: list[np.ndarray]) -> np.ndarray:
        def cost(th):
            return float(np.sum(self.residual(th)[rows] ** 2))

        costs = [cost(s) for s in starts]
        x0 = np.asarray(starts[int(np.argmin(costs))], float)
        span = np.maximum(self.hi - self.lo, 1e-12)
        x0 = np.clip(x0, self.lo + 1e-6 * span, self.hi - 1e-6 * span)
        try:
            sol = least_squares(lambda th: self.residual(th)[rows].ravel(), x0, bounds=(self.lo, self.hi),
                                x_scale=span, diff_step=self.a.cfg.diff_step, max_nfev=self.cfg.max_nfev,
                                method="dogbox")
            if float(np.sum(sol.fun ** 2)) < min(costs):
                return sol.x
        except (ValueError, FloatingPointError) as exc:
            log.debug("pair fit failed (%s); keeping the best start", exc)
        return np.asarray(starts[int(np.argmin(costs))], float)


@dataclass
class PairScore:
    names: tuple[str, str]
    params: tuple[dict, dict]
    before: float
    after: float
    p_value: float
    member_after: tuple[float, float]   # held-out error with only one member, at the pair's fold fits
    p_adjusted: float = 1.0
    significant: bool = False
    baseline: float = 0.0
    block_before: list = field(default_factory=list)
    block_after: list = field(default_factory=list)

    @property
    def reduction(self) -> float:
        return 1.0 - self.after / self.before if self.before > 0 else 0.0

    @property
    def lead(self) -> int:
        """Index of the member to add first: the one that alone keeps the lower held-out error."""
        return int(np.argmin(self.member_after))

    def to_json(self) -> dict:
        return {"effects": list(self.names), "params": [dict(p) for p in self.params],
                "heldout_error_before": self.before, "heldout_error_after": self.after,
                "reduction": self.reduction, "p_value": self.p_value, "p_adjusted": self.p_adjusted,
                "significant": self.significant, "add_first": self.names[self.lead],
                "heldout_error_first_only": self.member_after[self.lead]}


def score_pairs(singles: list, ch: Channels, blocks: np.ndarray, fit_cfg, cfg: PairConfig, pvalue) -> tuple[list, int]:
    """Cross-validated PairScores of the most promising pairs of force-channel `singles`
    (diagnose.EffectScore with per-fold thetas). Returns (scores, number of pairs screened)."""
    force = [s for s in singles if s.channel == "force" and s.effect.free_params]
    if len(force) < 2:
        return [], 0
    cands = {s.effect.name: Candidate(s.effect, ch, fit_cfg) for s in force}
    rows = np.arange(len(ch.table))
    base = ch.base_residual("force")
    sse0 = float(np.sum(base ** 2))
    if sse0 <= 0:
        return [], 0
    screened = []
    for sa, sb in itertools.combinations(force, 2):
        pc = PairCandidate(cands[sa.effect.name], cands[sb.effect.name], cfg)
        ta = np.array([sa.params[q.name] for q in sa.effect.free_params])
        tb = np.array([sb.params[q.name] for q in sb.effect.free_params])
        ia, ib = pc.split(pc.identity())
        starts = [np.concatenate([ta, tb]), np.concatenate([ta, ib]), np.concatenate([ia, tb])]
        th = pc.fit(rows, starts)
        red = [1.0 - np.sqrt(np.sum(pc.residual(x) ** 2) / sse0) for x in (th, starts[1], starts[2])]
        screened.append((red[0] - max(red[1], red[2]), pc, sa, sb, th))   # in-sample, all three alike
    screened.sort(key=lambda z: -z[0])
    out = []
    ids = np.unique(blocks)
    for gain, pc, sa, sb, th_all in screened[:cfg.max_pairs]:
        if gain <= 0:
            continue
        before, after, only_a, only_b = (np.zeros(len(ids)) for _ in range(4))
        ia, ib = pc.split(pc.identity())
        for i, b in enumerate(ids):
            test = blocks == b
            train = np.flatnonzero(~test)
            ta, tb = sa.fold_theta[i], sb.fold_theta[i]
            th = pc.fit(train, [np.concatenate([ta, tb]), np.concatenate([ta, ib]), np.concatenate([ia, tb])])
            fa, fb = pc.split(th)
            before[i] = float(np.sum(base[test] ** 2))
            after[i] = float(np.sum(pc.residual(th)[test] ** 2))
            only_a[i] = float(np.sum(pc.residual(np.concatenate([fa, ib]))[test] ** 2))
            only_b[i] = float(np.sum(pc.residual(np.concatenate([ia, fb]))[test] ** 2))
        n = max(len(rows), 1)
        pa, pb = pc.split(th_all)
        d = before - after
        out.append(PairScore((sa.effect.name, sb.effect.name), (pc.a.params(pa), pc.b.params(pb)),
                             float(np.sqrt(before.sum() / n)), float(np.sqrt(after.sum() / n)),
                             pvalue(d) if len(ids) > 1 else 1.0,
                             (float(np.sqrt(only_a.sum() / n)), float(np.sqrt(only_b.sum() / n))),
                             block_before=before.tolist(), block_after=after.tolist()))
    return out, len(screened)
