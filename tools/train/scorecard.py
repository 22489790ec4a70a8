"""The protocol's scorecard: one package on a set of units, with 95 % confidence intervals.

Input is a table of contact rows and rest frames (what `tools.train.evaluate.evaluate_session` returns,
turned into rows by `session_table`), each row tagged with its unit and poke. The numbers:

- detection: miss rate of contacts with measured |F| ≥ `contact_n` (0.2 N); phantoms: % of rest frames
  (every indenter below `free_n`, 0.05 N) where a cluster holds more than `phantom_n` (0.05 N);
- regression, on detected contacts only: |F| MAE (| |F_pred| − |F_meas| |), and the direction error
  (degrees between the predicted and the measured force vector) beside it;
- the seed's number too: |F| MAE with misses counted as 0 N (comparable with BENCHMARKS and s16).
- the field split at the measured tips (tools.scoring.split_at_tips) scored like the clusters: the network's
  field with the contact stage's clustering left out (where it is close to the clusters' MAE, the field holds it back);
- the signed |F| error (bias) beside the MAE, and a breakdown by indenter × single/two contacts;
- scale ceilings (`scale_ceilings`): the |F| MAE left if every unit, every poke, or every indenter × contact
  count had its own best force gain. What a per-unit calibration could remove against what varies poke to poke.

Confidence intervals: hierarchical bootstrap, units drawn with replacement, then within each drawn unit
its pokes with replacement (a poke = one contact period, its rest frames before it included); the 2.5 and
97.5 percentiles of the replicates' pooled means. Every breakdown (indenter, single/multi contact,
force bin) uses the same replicates. Several packages of one recipe differing in fit seed: mean ± spread.

Pure core: `direction_error_deg`, `poke_segments`, `resample_counts`, `ratio_stats`, `scorecard`,
`best_gain`, `scale_ceilings`, `fit_seed_spread`; `session_table` is the thin adapter from an evaluation's rows.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FORCE_BINS = (0.2, 0.5, 1.5, 3.0, 5.0, np.inf)    # N, measured |F| of the contact
# The scoring's version, kept in each sealed score (tools.train.protocol): raised whenever a fix changes
# what the same frames score. 2: an indenter never takes a cluster another indenter already matched.
SCORER_VERSION = 2


@dataclass(frozen=True)
class ScoreConfig:
    contact_n: float = 0.2        # a contact is scored when its measured |F| is at least this
    free_n: float = 0.05          # a rest frame for phantoms: every indenter's measured |F| below this
    phantom_n: float = 0.05       # a cluster above this on a rest frame is a phantom
    merge_s: float = 0.3          # contact periods closer than this are one poke
    n_boot: int = 2000
    seed: int = 0
    level: float = 0.95


def direction_error_deg(pred: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """Angle (degrees, 0–180) between predicted and measured force vectors (N, 3); NaN where either is 0."""
    p, m = np.asarray(pred, float).reshape(-1, 3), np.asarray(meas, float).reshape(-1, 3)
    npn, nm = np.linalg.norm(p, axis=1), np.linalg.norm(m, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.einsum("ij,ij->i", p, m) / (npn * nm)
    out = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    out[(npn == 0) | (nm == 0)] = np.nan
    return out


def poke_segments(t: np.ndarray, in_contact: np.ndarray, merge_s: float = 0.3) -> np.ndarray:
    """Poke index per frame: contact periods (runs of `in_contact`) closer than `merge_s` are one poke;
    a frame belongs to the poke that starts next (rest frames before the first poke → 0, after the
    last → the last poke)."""
    t, c = np.asarray(t, float), np.asarray(in_contact, bool)
    ends: list[float] = []
    prev = None
    for i in np.flatnonzero(c):
        if prev is not None and t[i] - t[prev] <= merge_s:
            ends[-1] = float(t[i])
        else:
            ends.append(float(t[i]))
        prev = i
    if not ends:
        return np.zeros(len(t), int)
    idx = np.searchsorted(np.asarray(ends), t, side="left")        # contact periods ended before t
    return np.minimum(idx, len(ends) - 1).astype(int)


def resample_counts(clusters_per_unit: list[int], n_boot: int, rng: np.random.Generator) -> np.ndarray:
    """Hierarchical bootstrap weights: (n_boot, total clusters) draw counts. Clusters (pokes) are numbered
    unit by unit; each replicate draws len(units) units with replacement and, for each drawn unit, as many
    of its pokes with replacement as it has."""
    sizes = np.asarray(clusters_per_unit, int)
    offs = np.concatenate([[0], np.cumsum(sizes)])
    W = np.zeros((n_boot, int(offs[-1])))
    for b in range(n_boot):
        for u in rng.integers(len(sizes), size=len(sizes)):
            if sizes[u]:
                np.add.at(W[b], offs[u] + rng.integers(sizes[u], size=sizes[u]), 1.0)
    return W


def ratio_stats(W: np.ndarray, sums: np.ndarray, counts: np.ndarray, level: float = 0.95) -> dict:
    """Pooled mean sum(sums)/sum(counts) and its bootstrap interval: per replicate (W @ sums)/(W @ counts),
    replicates without any row left out; percentiles at (1 ± level)/2."""
    n = float(counts.sum())
    if n == 0:
        return {"n": 0}
    with np.errstate(invalid="ignore", divide="ignore"):
        reps = (W @ sums) / (W @ counts)
    reps = reps[np.isfinite(reps)]
    lo, hi = (np.percentile(reps, [50 * (1 - level), 50 * (1 + level)]) if len(reps) else (np.nan, np.nan))
    return {"n": int(n), "mean": float(sums.sum() / n), "ci": [float(lo), float(hi)]}


def _cluster_ids(units: np.ndarray, pokes: np.ndarray, order: list) -> tuple[np.ndarray, list[int]]:
    """Map each row's (unit, poke) to a cluster number, units in `order`, pokes sorted within a unit."""
    keys = {}
    sizes = []
    for u in order:
        ps = sorted(set(pokes[units == u].tolist()))
        sizes.append(len(ps))
        for p in ps:
            keys[(u, p)] = len(keys)
    return np.array([keys[(u, p)] for u, p in zip(units.tolist(), pokes.tolist())], int), sizes


def _sums(cid: np.ndarray, n: int, value: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.where(mask, value, 0.0)
    return np.bincount(cid, v, n), np.bincount(cid, mask.astype(float), n)


def force_bin(mag: float) -> str:
    for lo, hi in zip(FORCE_BINS[:-1], FORCE_BINS[1:]):
        if lo <= mag < hi:
            return f"{lo:g}-{hi:g} N" if np.isfinite(hi) else f">= {lo:g} N"
    return "below"


def scorecard(contacts: dict, rest: dict, cfg: ScoreConfig = ScoreConfig()) -> dict:
    """contacts: arrays per scored contact — unit, poke, indenter (name), n_contact (indenters ≥ contact_n
    on that frame), meas (N, 3), pred (N, 3), miss (bool), optionally split (N, 3): the field split at the
    measured tips (tools.scoring.split_at_tips); rest: arrays per rest frame — unit, poke, phantom (bool).
    Returns {"overall": block, "by indenter": {...}, "by contacts": {"single", "multi"}, "by force": {...},
    "units", "pokes"} where a block holds miss_rate, phantom_rate (overall only), force_mae_n (detected),
    direction_error_deg (detected), force_mae_with_misses_n, split_force_mae_n (every scored contact with
    a split; n 0 without one), each {"n", "mean", "ci"}."""
    cu, cp = np.asarray(contacts["unit"], object), np.asarray(contacts["poke"], int)
    ru, rp = np.asarray(rest["unit"], object), np.asarray(rest["poke"], int)
    order = sorted(set(cu.tolist()) | set(ru.tolist()))
    ids, sizes = _cluster_ids(np.concatenate([cu, ru]), np.concatenate([cp, rp]), order)
    ccid, rcid, nc = ids[:len(cu)], ids[len(cu):], int(sum(sizes))
    W = resample_counts(sizes, cfg.n_boot, np.random.default_rng(cfg.seed))

    meas, pred = np.asarray(contacts["meas"], float).reshape(-1, 3), np.asarray(contacts["pred"], float).reshape(-1, 3)
    miss = np.asarray(contacts["miss"], bool)
    mm, pm = np.linalg.norm(meas, axis=1), np.linalg.norm(pred, axis=1)
    scored = mm >= cfg.contact_n
    err = np.abs(pm - mm)
    ang = direction_error_deg(pred, meas)
    split = np.asarray(contacts.get("split", np.full((len(cu), 3), np.nan)), float).reshape(-1, 3)
    split_err = np.abs(np.linalg.norm(split, axis=1) - mm)

    def stat(value, mask):
        return ratio_stats(W, *_sums(ccid, nc, value, mask), level=cfg.level)

    def block(sel):
        sel = sel & scored
        det = sel & ~miss
        return {"contacts": int(sel.sum()), "units": len(set(cu[sel].tolist())),
                "pokes": len(set(zip(cu[sel].tolist(), cp[sel].tolist()))),
                "miss_rate": stat(miss.astype(float), sel),
                "force_mae_n": stat(err, det),
                "force_bias_n": stat(pm - mm, det),
                "direction_error_deg": stat(np.nan_to_num(ang), det & np.isfinite(ang)),
                "force_mae_with_misses_n": stat(np.abs(np.where(miss, 0.0, pm) - mm), sel),
                "split_force_mae_n": stat(np.nan_to_num(split_err), sel & np.isfinite(split_err))}

    overall = block(np.ones(len(cu), bool))
    ph = np.asarray(rest["phantom"], float)
    overall["phantom_rate"] = ratio_stats(W, *_sums(rcid, nc, ph, np.ones(len(ru), bool)), level=cfg.level)
    names = np.asarray(contacts["indenter"], object)
    ncon = np.asarray(contacts["n_contact"], int)
    bins = np.array([force_bin(m) for m in mm], object)
    kinds = {"single": ncon <= 1, "multi": ncon >= 2}
    return {"units": len(order), "pokes": nc, "config": {k: (v if np.isfinite(v) else None) if isinstance(v, float)
                                                        else v for k, v in cfg.__dict__.items()},
            "overall": overall,
            "by indenter": {n: block(names == n) for n in sorted(set(names[scored].tolist()))},
            "by contacts": {k: block(sel) for k, sel in kinds.items()},
            "by indenter and contacts": {f"{n}, {k}": block((names == n) & sel)
                                         for n in sorted(set(names[scored].tolist())) for k, sel in kinds.items()
                                         if (scored & (names == n) & sel).any()},
            "scale ceilings": scale_ceilings(contacts, cfg),
            "by force": {b: block(bins == b) for b in [force_bin(lo) for lo in FORCE_BINS[:-1]]
                         if (bins[scored] == b).any()}}


def best_gain(pred_mag: np.ndarray, meas_mag: np.ndarray) -> float:
    """The gain g minimising Σ |g·p − m| over contacts (p > 0): the p-weighted median of m / p (1.0 without
    any contact)."""
    p, m = np.asarray(pred_mag, float), np.asarray(meas_mag, float)
    if p.shape != m.shape or p.ndim != 1:
        raise ValueError(f"best_gain: expected two (N,) arrays, got {p.shape} and {m.shape}")
    ok = p > 0
    if not ok.any():
        return 1.0
    r, w = m[ok] / p[ok], p[ok]
    o = np.argsort(r)
    c = np.cumsum(w[o])
    return float(r[o][np.searchsorted(c, 0.5 * c[-1])])


def scale_ceilings(contacts: dict, cfg: ScoreConfig = ScoreConfig()) -> dict:
    """|F| MAE of the detected contacts as scored, and after the best gain (`best_gain`) per unit, per
    (indenter, single/two contacts) and per poke: {"as scored", "per unit", "per indenter and contacts",
    "per poke"} in N (pooled means, no CI). The gains are fitted on the same contacts: ceilings, not results."""
    meas = np.asarray(contacts["meas"], float).reshape(-1, 3)
    pred = np.asarray(contacts["pred"], float).reshape(-1, 3)
    m, p = np.linalg.norm(meas, axis=1), np.linalg.norm(pred, axis=1)
    det = (m >= cfg.contact_n) & ~np.asarray(contacts["miss"], bool)
    if not det.any():
        return {}
    unit = np.asarray(contacts["unit"], object)
    poke = np.asarray(contacts["poke"], int)
    group = {"per unit": [str(u) for u in unit],
             "per indenter and contacts": [f"{n}|{'single' if int(k) <= 1 else 'multi'}"
                                           for n, k in zip(contacts["indenter"], contacts["n_contact"])],
             "per poke": [f"{u}|{k}" for u, k in zip(unit, poke)]}
    out = {"as scored": float(np.abs(p - m)[det].mean())}
    for name, g in group.items():
        g = np.asarray(g, object)
        q = p.copy()
        for key in set(g[det].tolist()):
            sel = det & (g == key)
            q[sel] = p[sel] * best_gain(p[sel], m[sel])
        out[name] = float(np.abs(q - m)[det].mean())
    return out


def session_table(unit: str, result: dict, names: dict[int, str], cfg: ScoreConfig = ScoreConfig()) -> tuple[dict, dict]:
    """One evaluated session (evaluate_session's "rows", "frames") → (contacts, rest) arrays of
    `scorecard` for `unit`; `names`: indenter id → indenter name (the session's poses stream)."""
    fr = result["frames"]
    t = np.array([f["t"] for f in fr], float)
    mags = np.array([f["meas_mags"] for f in fr], float).reshape(len(fr), -1)
    poke = poke_segments(t, (mags >= cfg.contact_n).any(1), cfg.merge_s)
    frame_poke = {f["frame"]: int(p) for f, p in zip(fr, poke)}
    at = {f["frame"]: i for i, f in enumerate(fr)}
    rows = [r for r in result["rows"] if np.linalg.norm(r["meas_force"]) >= cfg.contact_n]
    contacts = {"unit": [unit] * len(rows), "poke": [frame_poke[r["frame"]] for r in rows],
                "indenter": [names.get(r["indenter"], str(r["indenter"])) for r in rows],
                "n_contact": [int((mags[at[r["frame"]]] >= cfg.contact_n).sum()) for r in rows],
                "meas": [r["meas_force"] for r in rows], "pred": [r["pred_force"] for r in rows],
                "miss": [r["miss"] for r in rows], "split": [r.get("split_force", [np.nan] * 3) for r in rows]}
    free = [(f, p) for f, p in zip(fr, poke) if f["fields"] and max(f["meas_mags"], default=0.0) < cfg.free_n]
    rest = {"unit": [unit] * len(free), "poke": [int(p) for _, p in free],
            "phantom": [max(f["cluster_forces"], default=0.0) > cfg.phantom_n for f, _ in free]}
    return contacts, rest


def concat_tables(tables: list[tuple[dict, dict]]) -> tuple[dict, dict]:
    c = {k: [v for t in tables for v in t[0].get(k, [[np.nan] * 3] * len(t[0]["unit"]))]
         for k in ("unit", "poke", "indenter", "n_contact", "meas", "pred", "miss", "split")}
    r = {k: [v for t in tables for v in t[1][k]] for k in ("unit", "poke", "phantom")}
    return c, r


HEADLINE = ("miss_rate", "phantom_rate", "force_mae_n", "direction_error_deg", "force_mae_with_misses_n")


def headline(card: dict) -> dict:
    """The overall means of a scorecard (what the sealed log and the fit-seed spread keep)."""
    return {k: card["overall"][k].get("mean") for k in HEADLINE}


def fit_seed_spread(headlines: list[dict]) -> dict:
    """Headline numbers of several fits of one recipe (one per fit seed) → per number: n, mean, sd
    (ddof 1), min, max."""
    out = {}
    for k in HEADLINE:
        v = np.array([h[k] for h in headlines if h.get(k) is not None], float)
        if len(v):
            out[k] = {"n": int(len(v)), "mean": float(v.mean()), "sd": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
                      "min": float(v.min()), "max": float(v.max())}
    return out
