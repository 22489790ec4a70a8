"""Material fitting (seed Appendix): Yeoh vs neo-Hookean / Mooney-Rivlin / Ogden on uniaxial +
equibiaxial engineering stress-stretch data with load/unload cycles; fit quality per model.

Incompressible closed forms (nominal stress P, stretch l):
  invariant models  uniaxial  P = 2 (l - l^-2) (W1 + W2 / l)
                    biaxial   P = 2 (l - l^-5) (W1 + l^2 W2)
  Ogden             uniaxial  P = sum mu_p (l^(a_p-1) - l^(-a_p/2-1))
                    biaxial   P = sum mu_p (l^(a_p-1) - l^(-2 a_p-1))
Load and unload branches are fitted together (the elastic fit passes through the hysteresis loop);
the report gives R^2, RMSE (MPa), the loop width the model cannot represent, and a stability check
(positive tangent of both curves for stretches 0.5..3). Data CSV columns: mode (uniaxial|biaxial),
stretch, stress_MPa [, cycle, branch]; every value finite and in DATA_RANGES (stretch 0.1..10, |stress|
<= 1000 MPa, branch +1/-1), else one FEError line naming the row.
"""
from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from .errors import FEError

log = logging.getLogger(__name__)

MODELS = {  # name -> (parameter names, initial guess, lower bounds)
    "yeoh": (("C10", "C20", "C30"), (0.03, 0.0, 0.0), (1e-6, -1.0, 0.0)),
    "neo_hookean": (("C10",), (0.03,), (1e-6,)),
    "mooney_rivlin": (("C10", "C01"), (0.02, 0.01), (-1.0, -1.0)),
    "ogden": (("mu1", "alpha1", "mu2", "alpha2"), (0.05, 2.0, -0.01, -2.0), (-5, -20, -5, -20)),
}

# plausible test data: a stretch of a rubber test (1 = unstretched; compression or tension up to 10x) and a
# nominal stress in MPa (a silicone gel is far below 1000 MPa); outside these no model is fitted
DATA_RANGES = {"stretch": (0.1, 10.0), "stress_MPa": (-1000.0, 1000.0), "branch": (-1.0, 1.0)}

# spellings people write for each model and test mode (compared case-insensitively, '-'/' ' read as '_')
MODEL_ALIASES = {"yeoh": "yeoh", "neo_hookean": "neo_hookean", "neohookean": "neo_hookean", "nh": "neo_hookean",
                 "neo_hooke": "neo_hookean", "mooney_rivlin": "mooney_rivlin", "mooneyrivlin": "mooney_rivlin",
                 "mr": "mooney_rivlin", "ogden": "ogden", "ogden2": "ogden", "ogden_2": "ogden"}
MODE_ALIASES = {"uniaxial": "uniaxial", "uni": "uniaxial", "uniaxial_tension": "uniaxial",
                "biaxial": "biaxial", "equibiaxial": "biaxial", "equi_biaxial": "biaxial", "bi": "biaxial",
                "equibiaxial_tension": "biaxial", "biaxial_tension": "biaxial"}


def _key(text: str) -> str:
    return "_".join(str(text).strip().lower().replace("-", " ").split())


def model_name(text: str) -> str:
    """The MODELS name for a spelling such as 'Yeoh', 'neo-Hookean', 'MR' or 'Ogden'; FEError otherwise."""
    name = MODEL_ALIASES.get(_key(text))
    if name is None:
        raise FEError(f"--models: unknown material model {text!r}; expected one of yeoh, neo_hookean (nh), "
                      f"mooney_rivlin (mr), ogden (2-term)")
    return name


def mode_name(text: str) -> str | None:
    """'uniaxial' or 'biaxial' for a test-mode spelling (equibiaxial, equi-biaxial, ...); None if unknown."""
    return MODE_ALIASES.get(_key(text))


@dataclass
class TestData:
    mode: np.ndarray     # (n,) "uniaxial" | "biaxial"
    stretch: np.ndarray  # (n,)
    stress: np.ndarray   # (n,) nominal (engineering) stress, MPa
    branch: np.ndarray   # (n,) +1 loading, -1 unloading


def nominal_stress(model: str, params, mode, stretch) -> np.ndarray:
    """Incompressible nominal stress (MPa) of `model` for uniaxial/biaxial stretches."""
    lam = np.asarray(stretch, float)
    uni = np.asarray(mode) == "uniaxial"
    if model == "ogden":
        mu1, a1, mu2, a2 = params
        out = np.zeros_like(lam)
        for mu, a in ((mu1, a1), (mu2, a2)):
            out += mu * (lam ** (a - 1) - np.where(uni, lam ** (-a / 2 - 1), lam ** (-2 * a - 1)))
        return out
    I1 = np.where(uni, lam ** 2 + 2 / lam, 2 * lam ** 2 + lam ** -4)
    W2 = 0.0
    if model == "yeoh":
        C10, C20, C30 = params
        W1 = C10 + 2 * C20 * (I1 - 3) + 3 * C30 * (I1 - 3) ** 2
    elif model == "neo_hookean":
        W1 = params[0] + 0 * I1
    elif model == "mooney_rivlin":
        W1, W2 = params[0] + 0 * I1, params[1]
    else:
        raise FEError(f"material fit: unknown model {model!r}; expected one of {list(MODELS)}")
    return np.where(uni, 2 * (lam - lam ** -2) * (W1 + W2 / lam), 2 * (lam - lam ** -5) * (W1 + lam ** 2 * W2))


def fit_model(model: str, data: TestData) -> dict:
    names, x0, lo = MODELS[model]
    scale = max(np.abs(data.stress).max(), 1e-9)

    def resid(p):
        return (nominal_stress(model, p, data.mode, data.stretch) - data.stress) / scale

    sol = least_squares(resid, x0, bounds=(lo, [np.inf] * len(x0)), x_scale="jac", max_nfev=5000)
    pred = nominal_stress(model, sol.x, data.mode, data.stretch)
    err = pred - data.stress
    ss_tot = ((data.stress - data.stress.mean()) ** 2).sum()
    per_mode = {}
    for m in ("uniaxial", "biaxial"):
        k = data.mode == m
        if k.any():
            per_mode[m] = float(np.sqrt((err[k] ** 2).mean()))
    lam = np.linspace(0.5, 3.0, 200)
    stable = True
    for m in ("uniaxial", "biaxial"):
        ps = nominal_stress(model, sol.x, np.full(lam.shape, m), lam)
        stable &= bool(np.all(np.diff(ps) > 0))
    params = dict(zip(names, map(float, sol.x)))
    mu0 = (2 * (params.get("C10", 0) + params.get("C01", 0)) if model != "ogden"
           else 0.5 * (params["mu1"] * params["alpha1"] + params["mu2"] * params["alpha2"]))
    return {"model": model, "params": params, "initial_shear_modulus": float(mu0),
            "r2": float(1 - (err ** 2).sum() / ss_tot), "rmse": float(np.sqrt((err ** 2).mean())),
            "rmse_by_mode": per_mode, "max_abs_error": float(np.abs(err).max()), "stable": stable,
            "n_params": len(names)}


def hysteresis_width(data: TestData) -> float:
    """Mean |load - unload| stress at equal stretch (MPa): what no elastic model can fit."""
    widths = []
    for m in np.unique(data.mode):
        k = data.mode == m
        up, dn = k & (data.branch > 0), k & (data.branch < 0)
        if up.sum() > 2 and dn.sum() > 2:
            grid = np.linspace(max(data.stretch[up].min(), data.stretch[dn].min()),
                               min(data.stretch[up].max(), data.stretch[dn].max()), 50)
            ou, od = np.argsort(data.stretch[up]), np.argsort(data.stretch[dn])
            su = np.interp(grid, data.stretch[up][ou], data.stress[up][ou])
            sd = np.interp(grid, data.stretch[dn][od], data.stress[dn][od])
            widths.append(np.abs(su - sd).mean())
    return float(np.mean(widths)) if widths else 0.0


def fit_report(data: TestData, models=("yeoh", "neo_hookean", "mooney_rivlin", "ogden"), plot=None) -> dict:
    models = list(dict.fromkeys(model_name(m) for m in models if str(m).strip()))
    if not models:
        raise FEError("--models: no model named; expected e.g. yeoh,neo_hookean,mooney_rivlin,ogden")
    fits = [fit_model(m, data) for m in models]
    loop = hysteresis_width(data)
    lines = [f"{'model':14s} {'R2':>8s} {'RMSE MPa':>10s} {'uni':>9s} {'biax':>9s} {'stable':>6s}  params",
             "-" * 90]
    for f in sorted(fits, key=lambda f: f["rmse"]):
        pm = f["rmse_by_mode"]
        lines.append(f"{f['model']:14s} {f['r2']:8.5f} {f['rmse']:10.3e} {pm.get('uniaxial', np.nan):9.2e} "
                     f"{pm.get('biaxial', np.nan):9.2e} {str(f['stable']):>6s}  "
                     + ", ".join(f"{k}={v:.4g}" for k, v in f["params"].items()))
    lines.append(f"load/unload loop width (not representable by any elastic model): {loop:.3e} MPa")
    if plot:
        _plot(data, fits, plot)
    return {"fits": fits, "hysteresis_width": loop, "table": "\n".join(lines)}


def _plot(data: TestData, fits, path) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise FEError("fit-material --plot needs matplotlib (pip install matplotlib)") from exc
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, m in zip(axes, ("uniaxial", "biaxial")):
        k = data.mode == m
        ax.plot(data.stretch[k], data.stress[k], ".", ms=2, color="0.5", label="data")
        lam = np.linspace(1.0, max(data.stretch[k].max(), 1.01), 100) if k.any() else np.linspace(1, 1.5, 10)
        for f in fits:
            ax.plot(lam, nominal_stress(f["model"], list(f["params"].values()), np.full(lam.shape, m), lam),
                    label=f"{f['model']} (RMSE {f['rmse']:.1e})")
        ax.set(title=m, xlabel="stretch", ylabel="nominal stress (MPa)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def load_test_data(path) -> TestData:
    path = Path(path)
    if not path.is_file():
        raise FEError(f"{path}: material test data not found")
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except UnicodeDecodeError as exc:
        raise FEError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); expected CSV columns "
                      f"mode,stretch,stress_MPa") from None
    except csv.Error as exc:
        raise FEError(f"{path}: not readable as CSV ({exc})") from None
    need = {"mode", "stretch", "stress_MPa"}
    if not rows or not need <= set(rows[0]):
        raise FEError(f"{path}: expected CSV columns {sorted(need)} (+ optional branch), got "
                      f"{sorted(k for k in rows[0] if k is not None) if rows else 'no rows'}")
    modes = [mode_name(r["mode"] or "") for r in rows]
    bad = sorted({str(r["mode"]) for r, m in zip(rows, modes) if m is None})
    if bad:
        raise FEError(f"{path}: column mode: expected uniaxial|biaxial (or equibiaxial), got {bad[:5]}")
    values = {}
    for col in ("stretch", "stress_MPa", "branch"):
        try:
            values[col] = np.array([float(r.get(col) or 1) if col == "branch" else float(r[col]) for r in rows])
        except (TypeError, ValueError):
            raise FEError(f"{path}: column {col}: expected numbers") from None
        if not np.isfinite(values[col]).all():
            raise FEError(f"{path}: column {col}: expected finite numbers")
        lo, hi = DATA_RANGES[col]
        bad = (values[col] < lo) | (values[col] > hi)
        if col == "branch":
            bad = (values[col] != 1) & (values[col] != -1)
        if bad.any():
            row = int(np.argmax(bad))
            want = "+1 (loading) or -1 (unloading)" if col == "branch" else f"a value in [{lo:g}, {hi:g}]"
            raise FEError(f"{path}:{row + 2}: column {col} is {values[col][row]:.6g}, expected {want}")
    return TestData(np.array(modes), values["stretch"], values["stress_MPa"], values["branch"])


def synthetic_test_data(C=(0.03, 0.002, 0.0002), cycles=3, max_strain=0.5, loop=0.03,
                        noise=2e-4, seed=0) -> TestData:
    """Uniaxial + equibiaxial load/unload cycles from a Yeoh 'truth' with a small hysteresis loop
    (unloading stress lower by `loop` relative) and noise (MPa): a stand-in for BioTester data."""
    rng = np.random.default_rng(seed)
    modes, lams, stresses, branches = [], [], [], []
    for mode in ("uniaxial", "biaxial"):
        for _ in range(cycles):
            up = np.linspace(1.0, 1.0 + max_strain, 40)
            for lam, br in ((up, 1.0), (up[::-1], -1.0)):
                s = nominal_stress("yeoh", C, np.full(lam.shape, mode), lam)
                if br < 0:
                    s = s * (1 - loop * np.sin(np.pi * (lam - 1) / max_strain))
                modes += [mode] * len(lam)
                lams.append(lam)
                stresses.append(s + noise * rng.normal(size=lam.shape))
                branches.append(np.full(lam.shape, br))
    return TestData(np.array(modes), np.concatenate(lams), np.concatenate(stresses), np.concatenate(branches))


def fit_to_indentation(scenario, measured_rf, names=("C10",), rel_step=0.02, max_nfev=8) -> dict:
    """Fit material constants of `scenario` so the FE reaction forces match `measured_rf` (F,K,3) N.
    Our solver has no material derivatives: least squares with finite differences, one FE solve per
    function evaluation (cost ~ (len(names)+1) solves per iteration)."""
    import copy

    from .solver import build_mesh, solve

    mesh = build_mesh(scenario)
    target = np.asarray(measured_rf, float).ravel()
    x0 = np.array([getattr(scenario.material, n) for n in names], float)

    def resid(x):
        sc = copy.deepcopy(scenario)
        for n, v in zip(names, x):
            setattr(sc.material, n, float(v))
        return (solve(sc, mesh=mesh).RF.ravel() - target) / max(np.abs(target).max(), 1e-9)

    sol = least_squares(resid, x0, diff_step=rel_step, max_nfev=max_nfev, x_scale=np.abs(x0) + 1e-9)
    return {"params": dict(zip(names, map(float, sol.x))), "cost": float(sol.cost), "nfev": int(sol.nfev)}
