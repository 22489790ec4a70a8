"""Diagnosis: which physical effect is missing from the model? (pure core, no files)

1. The session is cut into `n_blocks` contiguous time blocks (samples inside a block are
   correlated; blocks are the unit of resampling).
2. For every candidate effect (library + plugins, minus those already enabled) and every block b:
   fit the effect's free parameters on the other blocks (bounded least squares, fit.py) and
   score on block b. Per block: SSE before (model + enabled effects) and after (+ candidate).
3. Held-out error = RMS of the residual vector over all held-out rows (N for force, relative
   intensity for the brightness channel); reduction = 1 - after / before.
4. Significance: one-sided sign-flip permutation test on the per-block SSE differences
   (exact over all 2^B sign patterns for B <= 16), corrected over the candidates by the
   Westfall-Young step-down minP (`minp_adjusted`): every sign pattern flips the same blocks of
   every candidate, so the correction knows the candidates are scored on the same residuals
   (Holm, until session 6, treated them as unrelated and lost power: effects that act in a few
   blocks were ranked first but not significant). Block edges
   sit at contact-free moments, so one press never straddles two blocks (residuals are strongly
   autocorrelated within a press; blocks are the independent units). With a calibration-session
   baseline r0 for the candidate (the reduction it reaches where no physics is hidden), the null
   hypothesis is "removes no more than r0": the test runs on before_b (1 - r0)^2 - after_b.
   An effect is reported significant when the corrected p <= alpha AND the held-out reduction is
   at least r0 + `min_reduction` AND it removes at least `min_abs` of the channel's rms error
   (one 8-bit grey level for brightness): statistically and practically significant.
5. Ranking: significant effects first, each group by held-out reduction (relative reductions of
   the force and the brightness channel are not comparable, significance is); the verdict is the
   best significant effect; its final parameters are fitted on all blocks.
6. The covariate that best explains the remaining residual (scan.py) is named.
Nothing here reads a session's provenance or ground truth: only the sample table.
"""
from __future__ import annotations

import functools
import itertools
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from ...runtime.stages.effects import Effect, EffectChain, EnabledEffect, Registry
from .fit import Candidate, Channels, FitConfig, channel_of
from .mde import MDEConfig, minimum_detectable_effect
from .mde import words as mde_words
from .pairs import PairConfig, score_pairs
from .scan import ScanConfig, scan
from .table import SCAN_COVARIATES, SCAN_VECTORS, SampleTable

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DiagnoseConfig:
    n_blocks: int = 16
    blocks: str = "press"         # "press": blocks of whole presses (max_press_blocks); "time": n_blocks equal spans
    max_press_blocks: int = 40
    alpha: float = 0.05
    min_reduction: float = 0.05
    min_unexplained: float = 0.02   # partial R² below which "nothing systematic remains"
    max_exact_blocks: int = 16
    n_perm: int = 20000           # Monte-Carlo sign flips when there are more blocks
    quiet_edges: bool = True      # block edges at contact-free moments (time_blocks)
    # smallest held-out rms error an effect must remove, per channel, to count: a brightness drift
    # below one 8-bit grey level (relative intensity 1/255) is not a measurable LED drift
    min_abs: tuple = (("force", 0.0), ("brightness", 1.0 / 255.0))
    seed: int = 0
    pairs: bool = True            # no single effect significant: score pairs of effects (pairs.py)
    pairs_below: float = 0.3      # ... also when the best significant single removes less than this
    pair: PairConfig = field(default_factory=PairConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    scan: ScanConfig = field(default_factory=ScanConfig)
    mde: MDEConfig = field(default_factory=MDEConfig)
    flex_margin: float = 0.02     # a flexible member replaces the named form when its held-out error is this much lower


def time_blocks(time: np.ndarray, n_blocks: int, contact: np.ndarray | None = None) -> np.ndarray:
    """Block id (0..n_blocks-1) per sample: equal-duration contiguous spans of the session. With
    `contact` (per sample: an indenter touches), each inner edge moves to the nearest moment when
    nothing touches (within a quarter block), so a press is not split between a training and a
    test block (its residuals are strongly correlated in time)."""
    t = np.asarray(time, dtype=np.float64)
    edges = np.linspace(t.min(), t.max(), n_blocks + 1)
    if contact is not None and n_blocks > 1:
        ts = np.unique(t)
        busy = np.zeros(len(ts), bool)
        busy[np.searchsorted(ts, t[np.asarray(contact, bool)])] = True
        quiet = ts[~busy]
        width = edges[1] - edges[0]
        for i in range(1, n_blocks):
            if len(quiet):
                q = quiet[np.argmin(np.abs(quiet - edges[i]))]
                if abs(q - edges[i]) <= 0.25 * width:
                    edges[i] = q
    return np.clip(np.searchsorted(edges, t, side="right") - 1, 0, n_blocks - 1)


def press_blocks(time: np.ndarray, contact: np.ndarray, max_blocks: int) -> np.ndarray:
    """Block id per sample, aligned to presses: every press (a run of moments when an indenter
    touches) with the second half of the quiet gap before it and the first half of the one after it
    is one unit; consecutive units are grouped into at most `max_blocks` blocks of nearly equal
    press counts. An effect that lives in a few presses then sits in a few of many blocks, not in
    a few of 16 long ones."""
    t = np.asarray(time, dtype=np.float64)
    ts = np.unique(t)
    busy = np.zeros(len(ts), bool)
    busy[np.searchsorted(ts, t[np.asarray(contact, bool)])] = True
    b = busy.astype(int)
    starts = np.flatnonzero(np.diff(b) == 1) + 1
    ends = np.flatnonzero(np.diff(b) == -1)           # last busy index of a press
    if busy[0]:
        starts = np.r_[0, starts]
    if len(starts) < 2:
        return np.zeros(len(t), dtype=int)
    edges = []
    for s in starts[1:]:
        prev_end = ends[ends < s]
        e = ts[prev_end[-1]] if len(prev_end) else ts[0]
        edges.append(0.5 * (e + ts[s]))
    unit = np.searchsorted(np.asarray(edges), t, side="right")     # 0 .. n_presses-1
    n_units = len(starts)
    k = min(max_blocks, n_units)
    return (unit * k) // n_units


def contact_of(table: SampleTable) -> np.ndarray:
    """Per row: the indenter is in contact (mocap depth > 0) or the model sees a force."""
    depth = table.cols.get("mocap_depth", table.cols["depth"])
    return (depth > 0) | np.any(table.model != 0.0, axis=1)


@functools.lru_cache(maxsize=4)
def _all_signs(B: int) -> np.ndarray:
    return np.array(list(itertools.product((1.0, -1.0), repeat=B)))


def sign_flip_pvalue(d: np.ndarray, cfg: DiagnoseConfig | None = None) -> float:
    """One-sided p-value of sum(d) > 0 under random signs (H0: d symmetric about 0)."""
    cfg = cfg or DiagnoseConfig()
    d = np.asarray(d, dtype=np.float64)
    obs = d.sum()
    stats = _signs(len(d), cfg) @ d
    return float(np.mean(stats >= obs - 1e-12 * max(abs(obs), 1e-300)))


def _signs(B: int, cfg: DiagnoseConfig) -> np.ndarray:
    if B <= cfg.max_exact_blocks:
        return _all_signs(B)
    rng = np.random.default_rng(cfg.seed)
    return np.vstack([np.ones(B), rng.choice((1.0, -1.0), size=(cfg.n_perm, B))])


def minp_adjusted(ds: list, ids: list, n_blocks: int, cfg: DiagnoseConfig | None = None) -> list[float]:
    """Westfall-Young step-down minP p-values (one-sided) for candidates k with per-block statistics
    ds[k] on blocks ids[k] (blocks a candidate has no rows in count 0). Under H0 one sign pattern
    flips the same blocks of every candidate; each candidate's statistic sum(d) is turned into its
    own sign-flip p-value, so candidates whose error reduction sits in a few blocks are not
    penalised. Strong control of the family-wise error; never less powerful than Holm."""
    cfg = cfg or DiagnoseConfig()
    m = len(ds)
    if m == 0:
        return []
    D = np.zeros((n_blocks, m))
    for k, (d, i) in enumerate(zip(ds, ids)):
        D[np.asarray(i, dtype=int), k] = np.asarray(d, dtype=np.float64)
    S = _signs(n_blocks, cfg) @ D                  # row 0: all signs +1 (the observed statistic)
    n = len(S)
    P = np.empty_like(S)
    for k in range(m):                             # each pattern's own p-value, per candidate
        tol = 1e-12 * np.maximum(np.abs(S[:, k]), 1e-300)
        P[:, k] = (n - np.searchsorted(np.sort(S[:, k]), S[:, k] - tol, side="left")) / n
    obs = P[0]
    adj, running = np.ones(m), 0.0
    order = np.argsort(obs, kind="stable")
    for r, k in enumerate(order):
        running = max(running, float(np.mean(P[:, order[r:]].min(axis=1) <= obs[k])))
        adj[k] = running
    return adj.tolist()


def holm(pvalues: list[float]) -> list[float]:
    """Holm-Bonferroni adjusted p-values (same order as given)."""
    m = len(pvalues)
    order = np.argsort(pvalues)
    adj = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * pvalues[i]))
        adj[i] = running
    return adj.tolist()


@dataclass
class EffectScore:
    effect: Effect
    channel: str
    params: dict
    before: float
    after: float
    p_value: float
    p_adjusted: float = 1.0
    significant: bool = False
    block_gain: list = field(default_factory=list)
    block_before: list = field(default_factory=list)   # per held-out block SSE without / with the effect
    block_after: list = field(default_factory=list)
    baseline: float = 0.0          # held-out reduction of this candidate on the calibration session
    block_ids: list = field(default_factory=list)      # the held-out blocks of block_before/after
    fold_theta: list = field(default_factory=list)     # free parameters fitted without each block
    pair: object = None            # pairs.PairScore when this verdict comes from a pair
    alternatives: list = field(default_factory=list)   # the family's other member(s), scored on the same blocks

    @property
    def reduction(self) -> float:
        return 1.0 - self.after / self.before if self.before > 0 else 0.0

    @property
    def unit(self) -> str:
        return "N" if self.channel == "force" else "rel. intensity"

    def at_bounds(self, tol: float = 1e-3) -> list[str]:
        """Free parameters fitted at (within tol × range of) a bound, as 'name=value (lo|hi)'."""
        out = []
        for q in self.effect.free_params:
            v = self.params.get(q.name)
            if v is None:
                continue
            span = max(q.hi - q.lo, 1e-12)
            off = self.effect.identity_params().get(q.name)
            for side, b in (("lo", q.lo), ("hi", q.hi)):
                if abs(v - b) <= tol * span and not (off is not None and abs(b - off) <= tol * span):
                    out.append(f"{q.name}={v:.3g} ({side})")
        return out

    def to_json(self) -> dict:
        out = {"effect": self.effect.name, "params": {k: float(v) for k, v in self.params.items()},
               "heldout_error_before": float(self.before), "heldout_error_after": float(self.after),
               "reduction": float(self.reduction), "significant": bool(self.significant),
               "p_value": float(self.p_value), "p_adjusted": float(self.p_adjusted)}
        if self.at_bounds():
            out["at_bounds"] = self.at_bounds()
        if self.effect.family:
            out["family"] = self.effect.family
        if self.alternatives:
            out["other_members"] = [{"effect": a.effect.name, "heldout_error_after": float(a.after)}
                                    for a in self.alternatives]
        if self.baseline:
            out["calibration_reduction"] = float(self.baseline)
        if self.channel != "force":
            out["channel"] = self.channel
            out["unit"] = "relative intensity"
        return out


@dataclass
class Diagnosis:
    ranking: list[EffectScore]
    unexplained: dict
    scan: list[dict]
    enabled: list[str]
    n_samples: int
    n_blocks: int
    seconds: float
    min_unexplained: float = 0.02
    pairs: list = field(default_factory=list)      # pairs.PairScore (scored when no single effect was)
    runner_up: dict | None = None  # the next significant effect when the blocks cannot tell it from the verdict
    mde: dict | None = None        # minimum detectable effect (mde.py)
    block_kind: str = "press"      # how the held-out blocks were cut ("press" or "time")
    residual: object = None        # (N, 3) what remains once the verdict is in (for pictures; not in JSON)

    @property
    def verdict(self) -> EffectScore | None:
        sig = [s for s in self.ranking if s.significant]
        return sig[0] if sig else None

    def to_json(self) -> dict:
        v = self.verdict
        out = {"verdict": v.effect.name if v else None,
               "ranking": [s.to_json() for s in self.ranking],
               "unexplained": self.unexplained}
        if self.pairs:
            out["pairs"] = [p.to_json() for p in self.pairs]
        if self.runner_up:
            out["runner_up"] = self.runner_up
        if self.mde:
            out["mde"] = self.mde
        return out

    def words(self) -> list[str]:
        lines = []
        v = self.verdict
        if v is not None and v.pair is not None:
            pr = v.pair
            other = pr.names[1 - pr.lead]
            lines.append(f"Two effects are missing together: {pr.names[0]} and {pr.names[1]} "
                         f"(neither alone is significant)")
            lines.append(f"  together: held-out error {pr.before:.4g} -> {pr.after:.4g} N "
                         f"({-100 * pr.reduction:+.0f} %), p = {pr.p_adjusted:.3g} (Holm-corrected over pairs)")
            lines.append(f"Add first: {v.effect.describe(v.params)} (alone at the joint fit: "
                         f"{pr.before:.4g} -> {v.after:.4g} N); then diagnose again for {other}")
        elif v is not None:
            unit = "N" if v.channel == "force" else "(relative intensity)"
            lines.append(f"Missing physics: {v.effect.describe(v.params)}")
            lines.append(f"  held-out error {v.before:.4g} -> {v.after:.4g} {unit} "
                         f"({-100 * v.reduction:+.0f} %), p = {v.p_adjusted:.3g} (corrected over the candidates)")
        else:
            best = self.ranking[0] if self.ranking else None
            base = f"; {-100 * best.baseline:+.1f} % on the calibration session" if best and best.baseline else ""
            lines.append("No significant missing effect"
                         + (f" (best candidate {best.effect.name}: held-out error {-100 * best.reduction:+.1f} %, "
                            f"p = {best.p_adjusted:.2g}{base})" if best else ""))
            if self.mde:
                lines.append("  " + mde_words(self.mde))
        if v is not None and self.mde:
            lines.append("  this session: " + mde_words(self.mde))
        if v is not None and v.at_bounds():
            lines.append(f"  fitted at a bound: {', '.join(v.at_bounds())} (the library's form may not reach "
                         "the measured one)")
        if self.runner_up:
            r = self.runner_up
            lines.append(f"  {r['effect']} explains almost as much ({-100 * r['reduction']:+.0f} %): per held-out block "
                         f"the two are not distinguishable on this session (p = {r['p_vs_verdict']:.2g}); a plan "
                         f"that separates their covariates (holds, reloads, temperature range) would tell them apart")
        u = self.unexplained
        if u.get("covariate") and u["score"] >= self.min_unexplained:
            lines.append(f"What remains is best explained by {u['covariate']} "
                         f"(held-out partial R² = {u['score']:.3f}, {u.get('form', '')} error, "
                         f"p = {u.get('p_adjusted', 1.0):.2g} corrected over {u.get('n_covariates', 1)} covariates)")
        elif u.get("covariate"):
            lines.append(f"Nothing systematic remains (best covariate {u['covariate']}: "
                         f"held-out partial R² = {u['score']:.3f})")
        return lines


def _score_candidate(effect: Effect, ch: Channels, blocks: np.ndarray, cfg: DiagnoseConfig) -> EffectScore:
    cand = Candidate(effect, ch, cfg.fit)
    rows = ch.rows(cand.channel)
    blk = blocks[rows]
    base = ch.base_residual(cand.channel)
    ids = np.unique(blk)
    before = np.zeros(len(ids))
    after = np.zeros(len(ids))
    scout = cand.scout(blk)
    thetas = []
    for i, b in enumerate(ids):
        test = blk == b
        train = np.flatnonzero(~test)
        theta, _ = cand.fit(train, scout, ids[ids != b])
        thetas.append(theta)
        r = cand.residual(theta)[test]
        before[i] = float(np.sum(base[test] ** 2))
        after[i] = float(np.sum(r ** 2))
    n = max(len(rows), 1)
    theta_all, _ = cand.fit(np.arange(len(rows)), scout)
    d = before - after
    p = sign_flip_pvalue(d, cfg) if len(ids) > 1 else 1.0
    return EffectScore(effect, cand.channel, cand.params(theta_all), float(np.sqrt(before.sum() / n)),
                       float(np.sqrt(after.sum() / n)), p, block_gain=d.tolist(), block_before=before.tolist(),
                       block_after=after.tolist(), fold_theta=thetas, block_ids=ids.tolist())


def blocks_of(table: SampleTable, cfg: DiagnoseConfig) -> tuple[np.ndarray, str]:
    """The held-out blocks of a diagnosis and how they were cut (`cfg.blocks`); time blocks when
    the session has fewer than 8 presses."""
    contact = contact_of(table)
    if cfg.blocks == "press":
        b = press_blocks(table.cols["time"], contact, cfg.max_press_blocks)
        if b.max() + 1 >= 8:
            return b, "press"
    return time_blocks(table.cols["time"], cfg.n_blocks, contact if cfg.quiet_edges else None), "time"


def diagnose(table: SampleTable, registry: Registry, enabled: EffectChain | None = None,
             cfg: DiagnoseConfig | None = None, candidates: list[str] | None = None, post=None,
             baseline: dict | None = None) -> Diagnosis:
    """Rank every candidate effect by held-out error reduction (see module docstring). `post`: the
    sensor's correction on table rows (applied after the force-stage effects, as deployed).
    `baseline`: {effect: held-out reduction} the same candidate reached on the sensor's calibration
    session (no hidden physics: the model's own residual structure); an effect is significant only
    when it beats that by `min_reduction`."""
    t0 = time.perf_counter()
    cfg = cfg or DiagnoseConfig()
    chain = enabled or EffectChain()
    ch = Channels(table, chain, post)
    blocks, kind = blocks_of(table, cfg)
    n_blocks = int(blocks.max()) + 1
    enabled = {family_of(it.effect) for it in chain.items}   # a family already enabled is not a candidate again
    names = candidates if candidates is not None else [n for n in registry.names()
                                                       if family_of(registry.get(n)) not in enabled]
    scores = []
    for name in names:
        eff = registry.get(name)
        if channel_of(eff) == "brightness" and len(ch.bright_rows) < 2 * n_blocks:
            log.info("%s skipped: the table has no brightness measurements", name)
            continue
        missing = [c for c in eff.covariates if c not in ch.cov]
        if missing:
            log.info("%s skipped: covariates %s not in the table", name, missing)
            continue
        scores.append(_score_candidate(eff, ch, blocks, cfg))
        log.debug("%s: %.4g -> %.4g (p=%.3g)", name, scores[-1].before, scores[-1].after, scores[-1].p_value)
    tested = []
    for s in scores:   # H0: the candidate removes no more than it does on the calibration session
        s.baseline = float((baseline or {}).get(s.effect.name, 0.0))
        kept = (1.0 - s.baseline) ** 2 if s.baseline > 0 else 1.0   # SSE fraction a baseline-sized reduction leaves
        tested.append(np.asarray(s.block_before) * kept - np.asarray(s.block_after))
        if s.baseline > 0 and len(s.block_before) > 1:
            s.p_value = sign_flip_pvalue(tested[-1], cfg)
    padjs = minp_adjusted(tested, [s.block_ids for s in scores], n_blocks, cfg)
    for s, padj in zip(scores, padjs):
        padj = padj if len(s.block_before) > 1 else 1.0
        s.p_adjusted = padj
        s.significant = (padj <= cfg.alpha and s.reduction >= cfg.min_reduction + max(s.baseline, 0.0)
                         and s.before - s.after >= dict(cfg.min_abs).get(s.channel, 0.0))
    scores = pick_members(scores, cfg)
    scores.sort(key=lambda s: (not s.significant, -s.reduction))   # the evidence first, then the size
    scores = _inside_bounds_first(scores, cfg)
    pairs = []
    best = max([s.reduction for s in scores if s.significant and s.channel == "force"] + [0.0])
    if cfg.pairs and (not any(s.significant for s in scores) or 0.0 < best < cfg.pairs_below):
        scores, pairs = _pair_stage(scores, ch, blocks, cfg, baseline or {})
    resid, pred = table.meas - ch.base_force, ch.base_force
    sig = [s for s in scores if s.significant]
    if sig and sig[0].channel == "force":  # what remains once the verdict is in
        resid = Candidate(sig[0].effect, ch, cfg.fit).residual(
            np.array([sig[0].params[q.name] for q in sig[0].effect.free_params]))
        pred = table.meas - resid
    scanned = scan(ch.cov, SCAN_COVARIATES, resid, pred, blocks, cfg.scan, SCAN_VECTORS)
    if scanned:   # the top covariate's significance, corrected over every covariate scanned
        padj = minp_adjusted([d["block_gain"] for d in scanned], [d["block_ids"] for d in scanned], n_blocks, cfg)
        for d, p in zip(scanned, padj):
            d["p_adjusted"] = float(p)
    unexplained = ({"covariate": scanned[0]["covariate"], "score": float(scanned[0]["score"]),
                    "form": scanned[0]["form"], "unit": scanned[0]["unit"],
                    "p_adjusted": scanned[0]["p_adjusted"], "n_covariates": len(scanned)}
                   if scanned else {"covariate": None, "score": 0.0})
    force = [s for s in scores if s.channel == "force"]
    floor = min([s.after for s in force] + [s.before for s in force[:1]]) if force else float("nan")
    mde = (minimum_detectable_effect(table, resid, floor, {s.effect.name: _shape(s.effect, ch, cfg) for s in force},
                                     blocks, cfg.alpha, cfg.min_reduction,
                                     max([s.baseline for s in force] + [0.0]), cfg.mde, n_tests=len(tested))
           if force else None)
    return Diagnosis(scores, unexplained, scanned, chain.names, len(table), n_blocks,
                     time.perf_counter() - t0, cfg.min_unexplained, pairs, _runner_up(scores, cfg), mde,
                     kind, resid)


def _inside_bounds_first(scores: list, cfg: DiagnoseConfig) -> list:
    """When the leading significant effect sits at a parameter bound and a later significant effect
    of its channel does not, and the per-block held-out errors cannot say the leader is better
    (sign flip, p > alpha), the one fitted inside its bounds leads: a form pushed to its bound is
    imitating something else (e.g. a temperature law with T_ref far outside the session acting as a
    plain gain)."""
    sig = [s for s in scores if s.significant]
    if len(sig) < 2 or not sig[0].at_bounds():
        return scores
    a = sig[0]
    for b in sig[1:]:
        if b.channel == a.channel and not b.at_bounds():
            p = _p_better(a, b, cfg)
            if p is not None and p > cfg.alpha:
                return [b] + [s for s in scores if s is not b]
            break
    return scores


def family_of(effect: Effect) -> str:
    return effect.family or effect.name


def pick_members(scores: list, cfg: DiagnoseConfig) -> list:
    """One score per effect family: the named library form, unless its flexible member
    (runtime/stages/effects/flexible.py) has a held-out error lower by more than `flex_margin` (relative),
    or the flexible member is significant and the named form is not (parsimony chooses the form
    to report, it does not decide whether the family is missing: near the practical bar a 2 %
    margin is half of the smallest reduction that counts); the other member is kept on the chosen
    score (`alternatives`) for the shape picture."""
    groups: dict[str, list] = {}
    for s in scores:
        groups.setdefault(family_of(s.effect), []).append(s)
    out = []
    for fam, members in groups.items():
        named = next((m for m in members if m.effect.name == fam), None)
        best = min(members, key=lambda m: m.after)
        if (named is not None and named.after <= best.after * (1.0 + cfg.flex_margin)
                and (named.significant or not best.significant)):
            best = named
        best.alternatives = [m for m in members if m is not best]
        out.append(best)
    return out


def _shape(effect: Effect, ch: Channels, cfg: DiagnoseConfig) -> np.ndarray:
    """(N, 3) contribution of a force-channel effect at the library defaults (its shape for the MDE)."""
    cand = Candidate(effect, ch, cfg.fit)
    theta = np.array([cand.defaults[q.name] for q in cand.free])
    return ch.base_residual("force") - cand.residual(theta)


def _runner_up(scores: list, cfg: DiagnoseConfig) -> dict | None:
    """The second significant effect of the verdict's channel when a sign-flip test on the per-block
    held-out errors of the two cannot say the verdict is better (one-sided, p > alpha)."""
    sig = [s for s in scores if s.significant]
    if len(sig) < 2 or sig[0].pair is not None:
        return None
    a = sig[0]
    b = next((s for s in sig[1:] if s.channel == a.channel and len(s.block_after) == len(a.block_after)), None)
    p = _p_better(a, b, cfg) if b is not None else None
    if p is None or p <= cfg.alpha:
        return None
    return {"effect": b.effect.name, "reduction": float(b.reduction), "params": {k: float(v) for k, v in b.params.items()},
            "p_vs_verdict": float(p)}


def _pair_stage(scores: list, ch: Channels, blocks: np.ndarray, cfg: DiagnoseConfig, baseline: dict):
    """Score pairs (pairs.py); a significant pair puts its first member at the top of the ranking."""
    pairs, n_screened = score_pairs(scores, ch, blocks, cfg.fit, cfg.pair, lambda d: sign_flip_pvalue(d, cfg))
    single = {s.effect.name: s for s in scores}
    for pr in pairs:   # H0 as for singles: no more than both members reach on the calibration session
        r0 = [max(0.0, float(baseline.get(n, 0.0))) for n in pr.names]
        pr.baseline = 1.0 - (1.0 - r0[0]) * (1.0 - r0[1])
        if pr.baseline > 0 and len(pr.block_before) > 1:
            kept = (1.0 - pr.baseline) ** 2
            pr.p_value = sign_flip_pvalue(np.asarray(pr.block_before) * kept - np.asarray(pr.block_after), cfg)
    padj = holm([pr.p_value for pr in pairs] + [1.0] * (n_screened - len(pairs)))   # every pair screened counts
    best_single = max([s.reduction for s in scores if s.channel == "force"] + [0.0])
    for pr, p in zip(pairs, padj):
        pr.p_adjusted = p
        pr.significant = (p <= cfg.alpha and pr.reduction >= cfg.min_reduction + pr.baseline
                          and pr.reduction >= best_single + cfg.pair.min_gain)
    pairs.sort(key=lambda pr: (not pr.significant, -pr.reduction))
    if not pairs or not pairs[0].significant:
        return scores, pairs
    pairs = _stronger_pair_first(pairs, cfg)
    pr = pairs[0]
    lead = single[pr.names[pr.lead]]
    first = EffectScore(lead.effect, "force", dict(pr.params[pr.lead]), pr.before, pr.member_after[pr.lead],
                        lead.p_value, pr.p_adjusted, True, baseline=lead.baseline, pair=pr)
    return [first] + [s for s in scores if s is not lead], pairs


def _stronger_pair_first(pairs: list, cfg: DiagnoseConfig) -> list:
    """Pairs sorted by reduction: when the per-block held-out errors cannot say (sign flip, p > alpha)
    the first beats a later significant pair, the lower corrected p goes first (docs/history/workbench.md,
    session 16: temperature + relaxation 52 %, p 0.018, led rim + relaxation 50 %, p 0.0006)."""
    first = pairs[0]
    for other in pairs[1:]:
        if other.significant and other.p_adjusted < first.p_adjusted:
            p = _p_better(first, other, cfg)
            if p is not None and p > cfg.alpha:
                first = other
    return [first] + [pr for pr in pairs if pr is not first]


def _p_better(a, b, cfg: DiagnoseConfig) -> float | None:
    """One-sided sign-flip p that `a`'s per-block held-out errors are below `b`'s (None: the blocks
    differ in number or are fewer than 2)."""
    if len(a.block_after) != len(b.block_after) or len(a.block_after) < 2:
        return None
    return sign_flip_pvalue(np.asarray(b.block_after) - np.asarray(a.block_after), cfg)


def add_to_chain(chain: EffectChain, score: EffectScore) -> EffectChain:
    return EffectChain(chain.items + [EnabledEffect(score.effect, dict(score.params))])
