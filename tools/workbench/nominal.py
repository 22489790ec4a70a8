"""The network's nominal error, learned once on a calibration session, as the sensor's correction.

A trained network is not exact (≈ 0.6 N on held-out twin units, mostly a gain error that grows
with depth). Diagnosis would read that systematic error as a physical effect (strain stiffening,
rim stiffening, ...). The deployed pipeline already has the place for it: the zero-constrained
force correction (seed §III.I, runtime/correction.py) that `tensortouch recalibrate` fits from 5–7
pokes. Here the same correction (a random-forest gain on |F|, θ, u, v; tools/recalib/fit.py,
ONNX, stored as a new calibration version) is fitted on every matched contact frame of a
calibration session recorded without hidden physics. From then on `compare`/`diagnose` see the
network *as deployed with its correction*, and only what differs from the calibration session
remains for the effects. Pure core: `correction_pokes`, `blocked_check`; shell: `fit_and_store_correction`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from tools.workbench.table import SampleTable

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NominalConfig:
    min_force_n: float = 0.3          # rows with a smaller measured or predicted |F| carry no gain information
    inputs: tuple = ("fmag", "theta", "u", "v")
    n_estimators: int = 50
    max_depth: int = 6                # thousands of frames support deeper trees than 5–7 pokes
    min_samples_leaf: int = 20
    min_frames: int = 50              # fewer matched contact frames: refuse (not a calibration session)


def correction_pokes(table: SampleTable, pre: np.ndarray, cfg: NominalConfig = NominalConfig()):
    """Matched contact rows as a recalibration PokeSet (predicted force = model + enabled effects)."""
    from tools.recalib.fit import PokeSet

    ref = np.linalg.norm(table.meas, axis=1)
    pm = np.linalg.norm(pre, axis=1)
    depth = table.cols.get("mocap_depth", table.cols["depth"])
    ok = (table.cols.get("matched", np.ones(len(table))) > 0) & (depth > 0) & (ref > cfg.min_force_n) \
        & (pm > cfg.min_force_n)
    idx = np.flatnonzero(ok)
    return PokeSet(-pre[idx], ref[idx], table.vec["corr_uv"][idx], table.vec["corr_theta_phi"][idx]), idx


def _fit_cfg(cfg: NominalConfig):
    from tools.recalib.fit import FitConfig

    return FitConfig(inputs=tuple(cfg.inputs), n_estimators=cfg.n_estimators, max_depth=cfg.max_depth,
                     min_samples_leaf=cfg.min_samples_leaf)


def blocked_check(pokes, times: np.ndarray, cfg: NominalConfig = NominalConfig()) -> dict:
    """Held-out |F| error before/after: fit on one half of the session, test on the other (both ways)."""
    from tools.recalib.fit import corrected_magnitude, error_stats, fit_forest

    fc = _fit_cfg(cfg)
    half = times >= np.median(times)
    est = np.empty(len(pokes))
    for test in (half, ~half):
        rf = fit_forest(pokes.subset(np.flatnonzero(~test)), fc)
        est[test] = corrected_magnitude(pokes.pred_mag[test], rf.predict(pokes.subset(np.flatnonzero(test)).features(fc.inputs)), fc)
    return {"before": error_stats(pokes.pred_mag, pokes.ref_force), "after": error_stats(est, pokes.ref_force)}


def forest_post(table: SampleTable, rf, fc):
    """The fitted forest as the runtime applies it (gain clipped, zero stays zero), on table rows."""
    from runtime.correction import apply_output, feature_matrix

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


def nominal_reductions(comp, chain, pokes, idx, registry, cfg: "NominalConfig" = None) -> dict:
    """Held-out reduction each candidate reaches on the calibration session (no hidden physics):
    the model's own residual structure, which diagnosis must beat to call something physics.

    Cross-fitted, so it measures what a test session sees: the session is cut in two halves in time;
    the correction is fitted on the pokes of one half and the other half is diagnosed with it (its
    contact positions and loads are new to that correction, as a test session's are). The baseline
    is the mean over the two halves (each half's value is kept under `halves`)."""
    from tools.recalib.fit import fit_forest
    from tools.workbench.diagnose import diagnose

    cfg = cfg or NominalConfig()
    fc = _fit_cfg(cfg)
    table = comp.table
    t = table.cols["time"]
    cut = float(np.median(t[idx])) if len(idx) else float(np.median(t))
    halves = []
    for test in (t < cut, t >= cut):
        train = np.flatnonzero(~test[idx])
        if len(train) < cfg.min_frames:
            continue
        rf = fit_forest(pokes.subset(train), fc)
        sub = take_rows(table, np.flatnonzero(test))
        diag = diagnose(sub, registry, chain, post=forest_post(sub, rf, fc))
        halves.append({s.effect.name: float(s.reduction) for s in diag.ranking})
    names = sorted({n for h in halves for n in h})
    out = {n: round(float(np.mean([h[n] for h in halves if n in h])), 4) for n in names}
    out["halves"] = [{n: round(v, 4) for n, v in h.items()} for h in halves]
    return out


def fit_and_store_correction(calib_session, sensor: str, store, model, registry, cache: bool = True,
                             progress=None, cfg: NominalConfig = NominalConfig()) -> tuple[str, str]:
    """Fit the correction on a calibration session and store it (new calibration version)."""
    from runtime.effects import EffectChain
    from tools.recalib.fit import _check_onnx, fit_forest, to_onnx
    from tools.recalib.store_ops import store_recalibration
    from tools.workbench.compare import run_compare

    comp = run_compare(calib_session, sensor, store, model, registry, cache=cache, progress=progress)
    chain = EffectChain.from_calibration(store.load(sensor), registry)
    pre = chain.apply(comp.table.model, comp.table.cov(), stages=("force",))
    pokes, idx = correction_pokes(comp.table, pre, cfg)
    if len(pokes) < cfg.min_frames:
        from runtime.errors import CalibrationError

        raise CalibrationError(f"{calib_session}: only {len(pokes)} matched contact frames; a nominal "
                               "correction needs a calibration session with pokes the network sees")
    check = blocked_check(pokes, comp.table.cols["time"][idx], cfg)
    fc = _fit_cfg(cfg)
    rf = fit_forest(pokes, fc)
    onnx = to_onnx(rf, len(fc.inputs), fc)
    x = pokes.features(fc.inputs)
    _check_onnx(onnx, x, rf.predict(x))
    spec = {"file": "correction.onnx", "inputs": list(fc.inputs), "output": "gain",
            "kind": "random_forest_gain", "n_estimators": fc.n_estimators, "max_depth": fc.max_depth,
            "frames": int(len(pokes)), "source": "workbench nominal correction",
            "nominal_reductions": nominal_reductions(comp, chain, pokes, idx, registry, cfg)}
    cal = store.load(sensor)
    version = store_recalibration(store, cal, {"method": "workbench nominal correction",
                                               "session": str(calib_session), "frames": int(len(pokes)),
                                               "heldout_mae_n": [check["before"]["mae_n"], check["after"]["mae_n"]]},
                                  correction=(spec, onnx))
    text = (f"nominal correction fitted on {calib_session} ({len(pokes)} contact frames): held-out |F| MAE "
            f"{check['before']['mae_n']:.3f} -> {check['after']['mae_n']:.3f} N (half-session split) "
            f"-> calibration {version}")
    return version, text
