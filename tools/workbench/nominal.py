"""The network's nominal error, learned once on a calibration session, as the sensor's correction.

A trained network is not exact (≈ 0.6 N on held-out twin units, mostly a gain error that grows
with depth). Diagnosis would read that systematic error as a physical effect (strain stiffening,
rim stiffening, ...). The deployed pipeline already has the place for it: the zero-constrained
force correction (seed §III.I, runtime/stages/correction.py) that `tensortouch recalibrate` fits from 5–7
pokes. Here the same correction (a random-forest gain on |F|, θ, u, v; tools/recalib/fit.py,
ONNX, stored as a new calibration version) is fitted on every matched contact frame of a
calibration session recorded without hidden physics. From then on `compare`/`diagnose` see the
network *as deployed with its correction*, and only what differs from the calibration session
remains for the effects. Pure core: `correction_pokes`, `blocked_check`; shell: `fit_and_store_correction`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .table import SampleTable

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NominalConfig:
    min_force_n: float = 0.3          # rows with a smaller measured or predicted |F| carry no gain information
    inputs: tuple = ("fmag", "theta", "u", "v")
    n_estimators: int = 50
    max_depth: int = 6                # thousands of frames support deeper trees than 5–7 pokes
    min_samples_leaf: int = 20
    min_frames: int = 50              # fewer matched contact frames: refuse (not a calibration session)
    # inputs chosen on the calibration session by the half-session check, simplest first: a richer
    # set must beat the simpler choice's held-out |F| MAE by `select_margin` (relative). Position
    # inputs (u, v) only pay off when the session's pokes cover the gel densely enough.
    input_sets: tuple = (("fmag",), ("fmag", "theta"), ("fmag", "theta", "u", "v"))
    select_margin: float = 0.03


def correction_pokes(table: SampleTable, pre: np.ndarray, cfg: NominalConfig = NominalConfig()):
    """Matched contact rows as a recalibration PokeSet (predicted force = model + enabled effects)."""
    from ..recalib.fit import PokeSet

    ref = np.linalg.norm(table.meas, axis=1)
    pm = np.linalg.norm(pre, axis=1)
    depth = table.cols.get("mocap_depth", table.cols["depth"])
    ok = (table.cols.get("matched", np.ones(len(table))) > 0) & (depth > 0) & (ref > cfg.min_force_n) \
        & (pm > cfg.min_force_n)
    idx = np.flatnonzero(ok)
    return PokeSet(-pre[idx], ref[idx], table.vec["corr_uv"][idx], table.vec["corr_theta_phi"][idx]), idx


def _fit_cfg(cfg: NominalConfig):
    from ..recalib.fit import FitConfig

    return FitConfig(inputs=tuple(cfg.inputs), n_estimators=cfg.n_estimators, max_depth=cfg.max_depth,
                     min_samples_leaf=cfg.min_samples_leaf)


def folds_of(times: np.ndarray, sessions: np.ndarray) -> np.ndarray:
    """Cross-fitting folds: one per calibration session when there are several, else the two
    halves of the one session in time."""
    if len(np.unique(sessions)) > 1:
        return np.asarray(sessions, dtype=int)
    return (np.asarray(times) >= np.median(times)).astype(int)


def blocked_check(pokes, folds: np.ndarray, cfg: NominalConfig = NominalConfig()) -> dict:
    """Held-out |F| error before/after: for each fold, the forest fitted on the other folds."""
    from ..recalib.fit import corrected_magnitude, error_stats, fit_forest

    fc = _fit_cfg(cfg)
    est = np.empty(len(pokes))
    for f in np.unique(folds):
        test = folds == f
        rf = fit_forest(pokes.subset(np.flatnonzero(~test)), fc)
        est[test] = corrected_magnitude(pokes.pred_mag[test], rf.predict(pokes.subset(np.flatnonzero(test)).features(fc.inputs)), fc)
    return {"before": error_stats(pokes.pred_mag, pokes.ref_force), "after": error_stats(est, pokes.ref_force)}


def choose_inputs(pokes, folds: np.ndarray, cfg: NominalConfig = NominalConfig()) -> tuple[NominalConfig, dict]:
    """The correction's inputs: each candidate set's cross-fitted check; the simplest set unless a
    richer one is better by `select_margin`. Returns (config with those inputs, {set: check})."""
    from dataclasses import replace

    from ..recalib.fit import simplest_adequate

    sets = [tuple(x) for x in (cfg.input_sets or (cfg.inputs,))]
    checks = {",".join(x): blocked_check(pokes, folds, replace(cfg, inputs=x)) for x in sets}
    best = simplest_adequate(sets, lambda x: checks[",".join(x)]["after"]["mae_n"], cfg.select_margin)
    raw = checks[",".join(best)]["before"]
    checks["none"] = {"before": raw, "after": raw}
    if checks[",".join(best)]["after"]["mae_n"] >= (1.0 - cfg.select_margin) * raw["mae_n"]:
        return replace(cfg, inputs=()), checks      # no gain forest beats the raw network on held-out data
    return replace(cfg, inputs=best), checks


def forest_post(table: SampleTable, rf, fc):
    """The fitted forest as the runtime applies it (gain clipped, zero stays zero), on table rows."""
    from ...runtime.stages.correction import apply_output, feature_matrix

    uv, tp = table.vec["corr_uv"], table.vec["corr_theta_phi"]

    def post(forces):
        f = np.asarray(forces, dtype=np.float64)
        out = f.copy()
        nz = np.flatnonzero(np.any(f != 0.0, axis=1))
        if len(nz):
            g = rf.predict(feature_matrix(-f[nz], uv[nz], tp[nz], list(fc.inputs)))
            out[nz] = -apply_output(-f[nz], g, "gain", fc.max_gain)
        return out

    return post


def take_rows(table: SampleTable, rows: np.ndarray) -> SampleTable:
    """The table restricted to `rows` (in time order)."""
    return SampleTable({k: v[rows] for k, v in table.cols.items()}, table.meas[rows], table.model[rows],
                       {k: v[rows] for k, v in table.vec.items()}, dict(table.meta))


def nominal_reductions(tables: list, chain, pokes, row_of: list, folds: np.ndarray, registry,
                       cfg: "NominalConfig" = None) -> dict:
    """Held-out reduction each candidate reaches on the calibration sessions (no hidden physics):
    the model's own residual structure, which diagnosis must beat to call something physics.

    Cross-fitted, so it measures what a test session sees: for each fold (a calibration session, or
    a half of the only one) the correction is fitted on the other folds' pokes and the fold's rows
    are diagnosed with it (contact positions and loads new to that correction, as a test session's
    are). The baseline is the mean over the folds (each fold's value is kept under `folds`).
    `row_of[i]`: (table index, row) of poke i; `folds[i]`: its fold."""
    from ..recalib.fit import fit_forest
    from .diagnose import diagnose

    cfg = cfg or NominalConfig()
    fc = _fit_cfg(cfg)
    row_of = np.asarray(row_of)
    per = []
    for f in np.unique(folds):
        train = np.flatnonzero(folds != f)
        if len(train) < cfg.min_frames:
            continue
        rf = fit_forest(pokes.subset(train), fc)
        k = int(row_of[folds == f][0, 0])            # the fold's table
        table = tables[k]
        if len(tables) > 1:
            sub = table
        else:                                        # the halves of folds_of(): split at the median poke time
            t = table.cols["time"]
            cut = float(np.median(t[row_of[:, 1]]))
            sub = take_rows(table, np.flatnonzero((t >= cut) == bool(f)))
        diag = diagnose(sub, registry, chain, post=forest_post(sub, rf, fc))
        per.append({s.effect.name: float(s.reduction) for s in diag.ranking})
    names = sorted({n for h in per for n in h})
    out = {n: round(float(np.mean([h[n] for h in per if n in h])), 4) for n in names}
    out["folds"] = [{n: round(v, 4) for n, v in h.items()} for h in per]
    return out


def fit_and_store_correction(calib_sessions, sensor: str, store, model, registry, cache: bool = True,
                             progress=None, cfg: NominalConfig = NominalConfig()) -> tuple[str, str]:
    """Fit the correction on one or more calibration sessions and store it (new calibration version).
    Several short sessions that together cover the gel are better than one long one: each stays in
    the conditions (duration, temperature range) of the sessions being diagnosed, and each is a
    natural cross-fitting fold."""
    from ...runtime.stages.effects import EffectChain
    from ..recalib.fit import PokeSet, _check_onnx, fit_forest, to_onnx
    from ..recalib.store_ops import store_recalibration
    from .compare import run_compare

    sessions = [calib_sessions] if isinstance(calib_sessions, (str, Path)) else list(calib_sessions)
    chain = EffectChain.from_calibration(store.load(sensor), registry)
    tables, parts, row_of, sess_id, times = [], [], [], [], []
    for k, s in enumerate(sessions):
        comp = run_compare(s, sensor, store, model, registry, cache=cache, progress=progress)
        pre = chain.apply(comp.table.model, comp.table.cov(), stages=("force",))
        pk, idx = correction_pokes(comp.table, pre, cfg)
        tables.append(comp.table)
        parts.append(pk)
        row_of += [(k, int(i)) for i in idx]
        sess_id.append(np.full(len(idx), k))
        times.append(comp.table.cols["time"][idx])
    pokes = PokeSet(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("pred_force", "ref_force", "uv", "theta_phi")))
    names = ", ".join(str(s) for s in sessions)
    if len(pokes) < cfg.min_frames:
        from ...contracts.errors import CalibrationError

        raise CalibrationError(f"{names}: only {len(pokes)} matched contact frames; a nominal "
                               "correction needs calibration sessions with pokes the network sees")
    folds = folds_of(np.concatenate(times), np.concatenate(sess_id))
    cfg, checks = choose_inputs(pokes, folds, cfg)
    identity = not cfg.inputs
    check = checks[",".join(cfg.inputs) or "none"]
    if identity:   # stored as a forest of gain 1 (exactly: |F|/|F|), so the calibration still carries the baseline
        from dataclasses import replace

        cfg = replace(cfg, inputs=("fmag",))
        pokes = PokeSet(pokes.pred_force, pokes.pred_mag, pokes.uv, pokes.theta_phi)
    fc = _fit_cfg(cfg)
    rf = fit_forest(pokes, fc)
    onnx = to_onnx(rf, len(fc.inputs), fc)
    x = pokes.features(fc.inputs)
    _check_onnx(onnx, x, rf.predict(x))
    spec = {"file": "correction.onnx", "inputs": list(fc.inputs), "output": "gain",
            "kind": "random_forest_gain", "n_estimators": fc.n_estimators, "max_depth": fc.max_depth,
            "frames": int(len(pokes)), "source": "workbench nominal correction",
            "sessions": [str(s) for s in sessions], "identity": identity,
            "input_checks": {k: [round(v["before"]["mae_n"], 4), round(v["after"]["mae_n"], 4)] for k, v in checks.items()},
            "nominal_reductions": nominal_reductions(tables, chain, pokes, row_of, folds, registry, cfg)}
    cal = store.load(sensor)
    version = store_recalibration(store, cal, {"method": "workbench nominal correction",
                                               "session": names, "frames": int(len(pokes)),
                                               "heldout_mae_n": [check["before"]["mae_n"], check["after"]["mae_n"]]},
                                  correction=(spec, onnx))
    tried = "; ".join(f"{k}: {v['after']['mae_n']:.3f}" for k, v in checks.items())
    how = "one fold per session" if len(sessions) > 1 else "half-session split"
    text = (f"nominal correction fitted on {names} ({len(pokes)} contact frames), inputs "
            f"{'none (gain 1: no forest beat the raw network)' if identity else ','.join(cfg.inputs)}: held-out |F| MAE {check['before']['mae_n']:.3f} -> {check['after']['mae_n']:.3f} N "
            f"({how}; inputs tried {tried}) -> calibration {version}")
    return version, text
