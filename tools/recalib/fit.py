"""Zero-constrained random-forest force correction from a handful of pokes (seed §III.I).

Each poke pairs the model's cluster force F_pred (N, vector) with the reference force magnitude F_ref
(N, from a force gauge or typed in) at a 2D contact position (u, v normalized to [0, 1] on the model
grid). The forest learns the *gain* g = |F_ref| / |F_pred| as a function of force magnitude and
position; the runtime applies F' = g · F_pred (runtime/stages/correction.py, output kind "gain"), so a zero
predicted force stays exactly zero whatever the forest says (the zero constraint), and the direction
of the predicted force is kept.

Everything here is a pure function of arrays; `to_onnx` converts with skl2onnx so the runtime needs
onnxruntime only. No pickle: the fitted forest leaves this module as ONNX bytes.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ...contracts.errors import CalibrationError
from ...runtime.stages.correction import FEATURES, feature_matrix

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FitConfig:
    """Forest and acceptance settings. Seed: 5–7 pokes; the gain clip matches the runtime's."""

    # feature columns (runtime FEATURES names): magnitude and position (seed); θ lets a tree split on
    # distance from the dome apex, where stiffness/thickness/centre errors of a dome mostly act.
    # Used as given when `candidates` is empty; else the fit chooses among `candidates` (below).
    inputs: tuple[str, ...] = ("fmag", "theta", "u", "v")
    # position enters only where the pokes support it: candidate input sets, simplest first; a richer set
    # is chosen only if its leave-one-out MAE beats the simpler choice by `select_margin` (relative).
    # The reported held-out error is then a NESTED leave-one-out (selection redone without the held-out poke).
    # () = one gain for the whole gel (a forest that cannot split: every leaf holds all pokes). With a
    # model whose error on a unit is mostly a clean gain (a stiffer or softer gel), 5–7 pokes estimate
    # one number far better than a forest of piecewise gains over |F| (on the stiffer twin units a
    # per-|F| forest stayed 0.07–0.09 N above the best constant gain).
    candidates: tuple[tuple[str, ...], ...] = ((), ("fmag",), ("fmag", "theta"), ("fmag", "theta", "u", "v"))
    select_margin: float = 0.15
    # ... and only if the per-poke gain is consistent: a paired one-sided t statistic of the leave-one-out
    # |errors| (current choice − richer set) of at least `select_t` (1.5 ≈ p 0.09 with 6 dof). With 5–7
    # pokes a 15 % lower mean is often one poke's luck: on the twin bench, sets chosen by the mean alone
    # did worse on the held-out probe than one gain in 8–15 of 21 unit × poke-count cases.
    select_t: float = 1.5
    select_estimators: int = 20                   # trees per forest inside the selection (speed; the stored one has n_estimators)
    n_estimators: int = 50                        # DESIGN §10: 50 trees ≈ 10 µs/sample in onnxruntime
    max_depth: int | None = 3                     # shallow: 5–7 samples cannot support deeper trees
    min_samples_leaf: int = 1
    bootstrap: bool = True
    random_state: int = 0
    max_gain: float = 5.0                         # = runtime ForceCorrection.max_gain
    min_pokes: int = 5                            # seed: as few as 5–7 measurement points
    min_pred_force_n: float = 1e-3                # pokes below this predicted force carry no gain info
    target_opset: int = 17


@dataclass
class PokeSet:
    """Paired measurements: predicted force vectors (N,3) N, reference magnitudes (N,) N,
    positions (N,2) normalized u,v, angles (N,2) θ,φ rad."""

    pred_force: np.ndarray
    ref_force: np.ndarray
    uv: np.ndarray
    theta_phi: np.ndarray

    def __post_init__(self):
        self.pred_force = np.asarray(self.pred_force, dtype=np.float64).reshape(-1, 3)
        n = len(self.pred_force)
        self.ref_force = np.asarray(self.ref_force, dtype=np.float64).reshape(n)
        self.uv = np.asarray(self.uv, dtype=np.float64).reshape(n, 2)
        self.theta_phi = np.asarray(self.theta_phi, dtype=np.float64).reshape(n, 2)

    def __len__(self) -> int:
        return len(self.pred_force)

    def subset(self, idx) -> "PokeSet":
        return PokeSet(self.pred_force[idx], self.ref_force[idx], self.uv[idx], self.theta_phi[idx])

    def features(self, names) -> np.ndarray:
        return feature_matrix(self.pred_force, self.uv, self.theta_phi, list(names))

    @property
    def pred_mag(self) -> np.ndarray:
        return np.linalg.norm(self.pred_force, axis=1)


def gain_targets(pokes: PokeSet, cfg: FitConfig = FitConfig()) -> np.ndarray:
    """g = |F_ref| / |F_pred|, clipped to the runtime's [0, max_gain]."""
    mag = pokes.pred_mag
    if np.any(mag < cfg.min_pred_force_n):
        bad = np.flatnonzero(mag < cfg.min_pred_force_n).tolist()
        raise CalibrationError(f"pokes {bad}: predicted force below {cfg.min_pred_force_n} N; "
                               "a poke the model does not see cannot calibrate its gain")
    return np.clip(pokes.ref_force / mag, 0.0, cfg.max_gain)


def columns(inputs) -> tuple[str, ...]:
    """The runtime feature columns of an input set: () (one constant gain) still feeds |F|, unused."""
    return tuple(inputs) or ("fmag",)


def set_name(inputs) -> str:
    return "+".join(inputs) or "constant"


def chosen_inputs(spec: dict) -> tuple[str, ...]:
    """The input set a stored correction entry was fitted on (() for one constant gain)."""
    return () if spec.get("constant") else tuple(spec["inputs"])


def fit_forest(pokes: PokeSet, cfg: FitConfig = FitConfig()):
    """A scikit-learn RandomForestRegressor of the gain on cfg.inputs; with no inputs, one tree that
    cannot split (min_samples_leaf = all pokes, no bootstrap): the mean gain, everywhere."""
    from sklearn.ensemble import RandomForestRegressor

    bad = [n for n in cfg.inputs if n not in FEATURES]
    if bad:
        raise CalibrationError(f"FitConfig.inputs {bad}: not runtime correction features {FEATURES}")
    if not cfg.inputs:
        rf = RandomForestRegressor(n_estimators=1, max_depth=1, min_samples_leaf=len(pokes), bootstrap=False,
                                   random_state=cfg.random_state, n_jobs=1)
    else:
        rf = RandomForestRegressor(n_estimators=cfg.n_estimators, max_depth=cfg.max_depth,
                                   min_samples_leaf=cfg.min_samples_leaf, bootstrap=cfg.bootstrap,
                                   random_state=cfg.random_state, n_jobs=1)
    rf.fit(pokes.features(columns(cfg.inputs)), gain_targets(pokes, cfg))
    return rf


def corrected_magnitude(pred_mag: np.ndarray, gain: np.ndarray, cfg: FitConfig = FitConfig()) -> np.ndarray:
    """|F'| as the runtime computes it: |F_pred| · clip(g, 0, max_gain); zero stays zero."""
    return np.where(pred_mag == 0.0, 0.0, pred_mag * np.clip(np.ravel(gain), 0.0, cfg.max_gain))


def error_stats(est: np.ndarray, ref: np.ndarray) -> dict:
    """Mean absolute, RMS and mean relative error of force magnitudes (N, N, fraction)."""
    err = np.abs(np.asarray(est, float) - np.asarray(ref, float))
    return {"mae_n": float(err.mean()), "rmse_n": float(np.sqrt((err ** 2).mean())),
            "mre": float((err / np.maximum(np.abs(ref), 1e-9)).mean()), "max_n": float(err.max())}


def _loo_held(pokes: PokeSet, cfg: FitConfig, inputs: tuple[str, ...], trees: int | None = None) -> np.ndarray:
    n = len(pokes)
    if n < 3:
        raise CalibrationError(f"leave-one-out needs at least 3 pokes, got {n}")
    c = replace(cfg, inputs=tuple(inputs), candidates=(), n_estimators=trees or cfg.n_estimators)
    held = np.empty(n)
    for i in range(n):
        rest = np.r_[0:i, i + 1:n]
        g = fit_forest(pokes.subset(rest), c).predict(pokes.subset([i]).features(columns(c.inputs)))
        held[i] = corrected_magnitude(pokes.pred_mag[i:i + 1], g, c)[0]
    return held


def select_inputs(pokes: PokeSet, cfg: FitConfig = FitConfig()) -> tuple[tuple[str, ...], dict]:
    """The input set among cfg.candidates (simplest first) with the best leave-one-out MAE; a richer set
    only if it beats the current choice by cfg.select_margin and its per-poke improvement holds up
    (paired t ≥ cfg.select_t over the pokes, each left out in turn). Returns (inputs, {set: LOO MAE})."""
    if not cfg.candidates:
        return tuple(cfg.inputs), {}
    errs = {set_name(c): np.abs(_loo_held(pokes, cfg, c, cfg.select_estimators) - pokes.ref_force)
            for c in cfg.candidates}
    scores = {k: float(np.mean(v)) for k, v in errs.items()}
    best = simplest_adequate([tuple(c) for c in cfg.candidates], lambda c: errs[set_name(c)], cfg.select_margin,
                             cfg.select_t)
    return best, scores


def paired_t(better: np.ndarray, worse: np.ndarray) -> float:
    """One-sample t statistic of the paired differences worse − better (> 0: `better` is lower)."""
    d = np.asarray(worse, float) - np.asarray(better, float)
    if len(d) < 2:
        return 0.0
    sd = d.std(ddof=1)
    return float(np.inf if sd == 0 and d.mean() > 0 else d.mean() / max(sd / np.sqrt(len(d)), 1e-12))


def simplest_adequate(sets: list, error, margin: float, min_t: float | None = None):
    """The first (simplest) of `sets` unless a later, richer one has a mean `error(set)` below
    (1 − margin) × the current choice's: a richer model must earn its extra inputs. With `min_t`,
    `error(set)` gives per-sample errors, and the richer set's improvement must also hold sample by
    sample (paired t ≥ min_t), so one lucky sample does not carry the choice."""
    best = sets[0]
    for x in sets[1:]:
        e, b = np.asarray(error(x), float), np.asarray(error(best), float)
        if e.mean() < (1.0 - margin) * b.mean() and (min_t is None or paired_t(e, b) >= min_t):
            best = x
    return best


def leave_one_out(pokes: PokeSet, cfg: FitConfig = FitConfig()) -> dict:
    """Held-out evaluation: each poke predicted by a forest fitted on the others (with input selection,
    `cfg.candidates`, the selection is redone on the others too: nested, so the estimate stays honest).

    Returns per-poke held-out corrected magnitudes and before/after error statistics; "before" is
    the uncorrected model (use `error_stats` with another baseline to compare with an active correction).
    """
    n = len(pokes)
    if not cfg.candidates:
        held = _loo_held(pokes, cfg, cfg.inputs)
    else:
        if n < 4:
            raise CalibrationError(f"leave-one-out with input selection needs at least 4 pokes, got {n}")
        held = np.empty(n)
        for i in range(n):
            rest = pokes.subset(np.r_[0:i, i + 1:n])
            inputs, _ = select_inputs(rest, cfg)
            c = replace(cfg, inputs=inputs, candidates=())
            g = fit_forest(rest, c).predict(pokes.subset([i]).features(columns(inputs)))
            held[i] = corrected_magnitude(pokes.pred_mag[i:i + 1], g, c)[0]
    return {"held_out_n": held.tolist(), "before": error_stats(pokes.pred_mag, pokes.ref_force),
            "after": error_stats(held, pokes.ref_force)}


def to_onnx(rf, n_inputs: int, cfg: FitConfig = FitConfig()) -> bytes:
    """skl2onnx conversion with the output width declared (DESIGN §10: avoids a shape warning)."""
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    model = convert_sklearn(rf, initial_types=[("features", FloatTensorType([None, n_inputs]))],
                            final_types=[("gain", FloatTensorType([None, 1]))],
                            target_opset=cfg.target_opset)
    model.doc_string = "TensorTouch zero-constrained force gain (tools.recalib.fit)"
    return model.SerializeToString()


@dataclass
class CorrectionFit:
    """A fitted correction ready for the calibration store."""

    onnx_bytes: bytes
    spec: dict                    # calibration.json "correction" entry (runtime contract)
    loo: dict                     # leave-one-out before/after
    train_gain: list[float]       # in-sample gains (diagnostics)
    config: dict = field(default_factory=dict)


def fit_correction(pokes: PokeSet, cfg: FitConfig = FitConfig()) -> CorrectionFit:
    """Fit on all pokes, evaluate by leave-one-out, convert to ONNX and check ONNX == sklearn."""
    if len(pokes) < cfg.min_pokes:
        raise CalibrationError(f"{len(pokes)} accepted pokes, need at least {cfg.min_pokes} (seed: 5–7)")
    loo = leave_one_out(pokes, cfg)
    inputs, scores = select_inputs(pokes, cfg)
    loo["selection"] = scores
    cfg = replace(cfg, inputs=inputs, candidates=())
    rf = fit_forest(pokes, cfg)
    x = pokes.features(columns(cfg.inputs))
    onnx_bytes = to_onnx(rf, x.shape[1], cfg)
    _check_onnx(onnx_bytes, x, rf.predict(x))
    spec = {"file": "correction.onnx", "inputs": list(columns(cfg.inputs)), "output": "gain",
            "kind": "random_forest_gain", "n_estimators": len(rf.estimators_), "max_depth": rf.max_depth,
            "pokes": len(pokes), **({"selection_loo_mae_n": scores} if scores else {})}
    if not cfg.inputs:
        spec["constant"] = True            # one leaf: the same gain for every contact
    return CorrectionFit(onnx_bytes, spec, loo, rf.predict(x).tolist(), asdict(cfg))


def _check_onnx(onnx_bytes: bytes, x: np.ndarray, expect: np.ndarray) -> None:
    import onnxruntime as ort

    sess = ort.InferenceSession(onnx_bytes, providers=["CPUExecutionProvider"])
    got = sess.run(None, {sess.get_inputs()[0].name: x.astype(np.float32)})[0].ravel()
    if not np.allclose(got, expect, rtol=1e-4, atol=1e-5):
        raise CalibrationError(f"ONNX conversion of the correction disagrees with scikit-learn "
                               f"(max diff {np.abs(got - expect).max():.3g})")


@dataclass(frozen=True)
class Decision:
    store: bool
    reason: str
    before_mae_n: float
    after_mae_n: float


def decide(held_out_after: dict, active_before: dict, force: bool = False) -> Decision:
    """Store the new correction only if its held-out error beats the active calibration's error on
    the same pokes (or `force`). Both dicts come from `error_stats`."""
    before, after = active_before["mae_n"], held_out_after["mae_n"]
    if after < before:
        return Decision(True, f"held-out error {after:.3f} N < {before:.3f} N with the active calibration",
                        before, after)
    if force:
        return Decision(True, f"held-out error {after:.3f} N is not better than {before:.3f} N; "
                              "stored anyway (--force)", before, after)
    return Decision(False, f"held-out error {after:.3f} N would not improve on {before:.3f} N with the "
                           "active calibration; not stored (use --force to store anyway)", before, after)
