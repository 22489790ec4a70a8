"""Issue 6's acceptance on the deployed-network path, as a reusable harness (the slow tests in
tests/test_workbench_net_twin.py and the table in docs/history/workbench.md both come from here).

    tensortouch accept workbench --model exported_models/hiera-qup-128 [--nulls 10]

Unit TWIN-WB01 (not a training unit), FE twin sessions with 30 fps frames (tools.workbench.scenarios,
recorded once and cached). The sensor first gets its nominal correction, fitted on a calibration
sessions without hidden physics that together cover the gel (`CALIB_SEEDS`, 16 pokes each). Each case is one session
with one hidden effect: switched on in the twin's truth ("truth") or put into the null session's
measurements by tools/accept/alter.py ("altered": written separately from the twin's effect
code). Diagnosis reads the sample table only (no provenance, truth or effect list).

The model's floor = held-out rms |r| on the null session of the test plan (after the correction);
the effect's size = rms over rows of the change the effect makes to the measured force (the altered
or truth session minus the null session, same plan and frames); their ratio says how fair a case is.
"""
from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...contracts.store import CalibrationStore
from ...runtime.stages.effects import EffectChain, Registry
from ..workbench.compare import run_compare
from ..workbench.diagnose import add_to_chain, diagnose
from ..workbench.fit import refit_chain
from ..workbench.scenarios import NET_TEST_SEED, net_scenario, record, store_root
from .alter import alter_session

log = logging.getLogger(__name__)
SENSOR = "TWIN-WB01"
CALIB_SEEDS = (100, 103)          # calibration sessions (16 pokes each, as long as a test session)
NULL_POKES = 8
PLUGINS = Path(__file__).parent / "workbench_plugins"
GEL_KINDS = ("strain", "rim", "mullins", "friction")   # alterations that need the gel geometry


@dataclass(frozen=True)
class Case:
    effect: str                   # the canonical name diagnosis should find
    source: str                   # "truth" (twin) or "altered" (tools/accept/alter.py)
    params: dict
    kind: str = ""                # alteration kind
    base: str = "test"            # the null session's plan: "test" (the test plan) or "slides"
    tag: str = ""                 # tells cases of one effect and source apart (test ids)


# Magnitudes: physically plausible and clearly above the network's floor (the ratio is in the table;
# a reduction >= 50 % needs an effect of at least ~1.7x the floor: sqrt(floor^2 + size^2) >= 2 floor).
ALTERED = (
    Case("viscoelastic_relaxation", "altered", {"g1": 0.5, "tau": 1.0}, "viscoelastic"),
    Case("temperature_softening", "altered", {"alpha": 0.05, "t_ref": 18.0}, "temperature"),
    Case("mullins_softening", "altered", {"r": 0.6, "m": 0.3}, "mullins"),
    Case("strain_stiffening", "altered", {"k": 15.0}, "strain"),
    Case("friction_mismatch", "altered", {"mu": 0.1}, "friction", base="slides"),   # friction shows in slides
    Case("rim_stiffening", "altered", {"a": 3.0, "w": 5.0}, "rim"),
    Case("ft_bias_drift", "altered", {"bx": 0.0, "by": 0.008, "bz": 0.015}, "ft_bias"),
    Case("led_drift", "altered", {"c": -0.003}, "led"),
)
# the same effects and magnitudes switched on in the twin's truth (the twin's own effect code)
TRUTH = tuple(Case(c.effect, "truth", c.params, base=c.base) for c in ALTERED)
# a weaker relaxation in truth (g1 = 0.3): its size is about the network's floor
WEAK = (Case("viscoelastic_relaxation", "truth", {"g1": 0.3, "tau": 1.0}, tag="weak"),)
CASES = WEAK + ALTERED + TRUTH
TWO = (("viscoelastic_relaxation", {"g1": 0.5, "tau": 1.0}), ("rim_stiffening", {"a": 3.0, "w": 5.0}))
TWO_WEAK = (("viscoelastic_relaxation", {"g1": 0.3, "tau": 1.0}), ("rim_stiffening", {"a": 2.0, "w": 4.0}))
# the same two effects put into the null session one after the other by the alteration script
TWO_ALTERED = (("viscoelastic_relaxation", "viscoelastic", {"g1": 0.5, "tau": 1.0}),
               ("rim_stiffening", "rim", {"a": 3.0, "w": 5.0}))
UNKNOWN = {"a": 0.35, "phi0": 0.5}          # azimuth stiffness (not in the library)


def gel_params() -> dict:
    gel = CalibrationStore(store_root(SENSOR, 128)).load(SENSOR).meta["gel"]
    return {"radius": gel["radius_mm"], "center_z": gel["center_z_mm"], "skirt": gel["skirt_mm"]}


class Bench:
    """The network model + a store holding the sensor's nominal correction; `table(session)`."""

    def __init__(self, model_dir: str | Path | None, work: Path, calib_seeds=CALIB_SEEDS,
                 precision: str = "int8"):
        from ...runtime.stages.model import find_package
        from ..workbench.network import NetworkConfig, NetworkModel
        from ..workbench.nominal import fit_and_store_correction

        self.package = find_package(str(model_dir) if model_dir else None)
        self.model = NetworkModel(self.package, NetworkConfig(precision=precision))
        self.reg = Registry.default(entry_points=False)
        self.work = Path(work)
        self.raw_root = self._store("raw")
        self.root = self._store("corrected")
        self.store = CalibrationStore(self.root)
        self.calib = [record(net_scenario(s)) for s in calib_seeds]
        t0 = time.perf_counter()
        _, self.correction_text = fit_and_store_correction(self.calib, SENSOR, self.store, self.model, self.reg)
        log.info("%s (%.0f s)", self.correction_text, time.perf_counter() - t0)

    def _store(self, name: str) -> Path:
        root = self.work / f"store-{name}"
        if root.exists():
            shutil.rmtree(root)
        shutil.copytree(store_root(SENSOR, 128), root)
        return root

    def table(self, session, corrected: bool = True):
        st = self.store if corrected else CalibrationStore(self.raw_root)
        comp = run_compare(session, SENSOR, st, self.model, self.reg)
        base = (comp.summary.get("correction") or {}).get("nominal_reductions")
        return comp.table, comp.post, base

    def diagnose(self, session, chain=None, registry=None, corrected: bool = True):
        t, post, base = self.table(session, corrected)
        return diagnose(t, registry or self.reg, chain, post=post, baseline=base)


SLIDES_SEED = 102                 # a null session of slides and presses (friction acts while sliding)


def plan_session(seed: int = NET_TEST_SEED, effects: tuple = ()) -> Path:
    """The session of a plan (the test plan, the slides plan or a short null plan), with `effects`
    switched on in the twin's truth."""
    if seed == SLIDES_SEED:
        return record(net_scenario(SLIDES_SEED, pokes=16, kinds=("slide", "press"), effects=effects))
    return record(net_scenario(seed, pokes=16 if seed == NET_TEST_SEED else NULL_POKES, effects=effects))


def null_session(seed: int = NET_TEST_SEED) -> Path:
    return plan_session(seed)


def base_of(case: Case) -> Path:
    return null_session(SLIDES_SEED if case.base == "slides" else NET_TEST_SEED)


def case_session(case: Case, work: Path) -> Path:
    if case.source == "truth":
        return plan_session(SLIDES_SEED if case.base == "slides" else NET_TEST_SEED,
                            ((case.effect, dict(case.params)),))
    params = dict(case.params, **gel_params()) if case.kind in GEL_KINDS else dict(case.params)
    return alter_session(base_of(case), Path(work) / f"{case.kind}-{case.effect}", case.kind, params)


def effect_size(bench: Bench, session: Path, null: Path) -> float:
    """rms over rows of |measured force with the effect - without| (N); nan when rows differ."""
    a, _, _ = bench.table(session)
    b, _, _ = bench.table(null)
    if len(a) != len(b) or not np.allclose(a.cols["time"], b.cols["time"]):
        return float("nan")
    return float(np.sqrt(np.mean(np.sum((a.meas - b.meas) ** 2, axis=1))))


def row_of(diag, case_name: str, truth_params: dict, size: float, floor: float) -> dict:
    v, top = diag.verdict, (diag.ranking[0] if diag.ranking else None)
    return {"hidden": case_name, "truth": truth_params, "rank1": top.effect.name if top else None,
            "before": top.before if top else None, "after": top.after if top else None,
            "reduction": top.reduction if top else None, "p_adjusted": top.p_adjusted if top else None,
            "calibration_reduction": top.baseline if top else None,
            "verdict": v.effect.name if v else None, "fitted": dict(top.params) if top else {},
            "channel": top.channel if top else "force", "effect_size_n": size,
            "top": [[s.effect.name, round(s.reduction, 4), round(s.p_adjusted, 4)] for s in diag.ranking[:4]],
            "ratio": size / floor if floor else None, "unexplained": diag.unexplained}


def run_all(bench: Bench, work: Path, nulls: int = 10, cases=CASES, parts=("two", "unknown")) -> dict:
    out = {"model": str(bench.package.folder), "model_sha256": bench.package.sha256(bench.model.cfg.precision),
           "correction": bench.correction_text, "calibration": [str(c) for c in bench.calib], "cases": [], "nulls": []}
    null = null_session()
    floor_diag = bench.diagnose(null)
    floor = next(s.before for s in floor_diag.ranking if s.channel == "force")
    out["floor_n"] = floor
    raw = bench.diagnose(null, corrected=False)
    out["raw_null"] = row_of(raw, "nothing (raw network, no correction)", {}, 0.0, floor)
    for _i, seed in enumerate([NET_TEST_SEED] + list(range(1, nulls))):
        d = floor_diag if seed == NET_TEST_SEED else bench.diagnose(null_session(seed))
        out["nulls"].append(dict(row_of(d, f"nothing (seed {seed})", {}, 0.0, floor), seed=seed))
        log.info("null seed %d: %s", seed, out["nulls"][-1]["verdict"])
    for case in cases:
        s = case_session(case, work)
        d = bench.diagnose(s)
        size = effect_size(bench, s, base_of(case)) if case.effect != "led_drift" else float("nan")
        out["cases"].append(dict(row_of(d, case.effect, case.params, size, floor), source=case.source))
        log.info("%s (%s): %s", case.effect, case.source, out["cases"][-1]["verdict"])
    out["two"] = two_effects(bench, work) if "two" in parts else None
    out["two_truth"] = two_effects(bench) if "two" in parts else None
    out["two_truth_weak"] = two_effects(bench, truth_effects=TWO_WEAK) if "two" in parts else None
    out["unknown"] = unknown_effect(bench, work) if "unknown" in parts else None
    return out


def two_effects(bench: Bench, work: Path | None = None, truth_effects: tuple = TWO) -> dict:
    """Diagnose, add, diagnose again on a session with two hidden effects: the twin-truth session
    (`truth_effects`: TWO, the altered magnitudes, or TWO_WEAK) or, with `work`, the null session
    altered twice (TWO_ALTERED)."""
    if work is None:
        s, truth = record(net_scenario(NET_TEST_SEED, effects=truth_effects)), [n for n, _ in truth_effects]
    else:
        s, truth = base_of(Case("", "altered", {})), []
        for name, kind, params in TWO_ALTERED:
            params = dict(params, **gel_params()) if kind in GEL_KINDS else dict(params)
            s = alter_session(s, Path(work) / f"two-{kind}", kind, params)
            truth.append(name)
    t, post, base = bench.table(s)
    first = diagnose(t, bench.reg, post=post, baseline=base)
    steps = [first]
    chain = EffectChain()
    while steps[-1].verdict is not None and len(steps) < 4:
        chain = add_to_chain(chain, steps[-1].verdict)
        if len(chain.items) > 1:
            chain, _, _ = refit_chain(t, chain, post=post)
        steps.append(diagnose(t, bench.reg, chain, post=post, baseline=base))
    return {"truth": truth, "found": [d.verdict.effect.name for d in steps if d.verdict],
            "steps": [{"verdict": d.verdict.effect.name if d.verdict else None,
                       "rank1": d.ranking[0].effect.name, "before": d.ranking[0].before,
                       "after": d.ranking[0].after, "reduction": d.ranking[0].reduction,
                       "p_adjusted": d.ranking[0].p_adjusted} for d in steps],
            "chain": {it.effect.name: it.params for it in chain.items}}


def unknown_effect(bench: Bench, work: Path) -> dict:
    s = alter_session(null_session(), Path(work) / "azimuth", "azimuth", dict(UNKNOWN))
    plain = bench.diagnose(s)
    with_plugin = bench.diagnose(s, registry=Registry.default(plugin_dirs=[PLUGINS], entry_points=False))
    v = with_plugin.verdict
    row = next((s for s in with_plugin.ranking if s.effect.name == "azimuth_stiffness"), None)
    return {"truth": UNKNOWN, "covariate": plain.unexplained.get("covariate"),
            "score": plain.unexplained.get("score"), "verdict_without_plugin": plain.verdict.effect.name
            if plain.verdict else None, "plugin_verdict": v.effect.name if v else None,
            # the plugin's own ranking row (what `effects add azimuth_stiffness --from-diagnosis` takes),
            # whether or not it reached significance
            "plugin_reduction": row.reduction if row else None, "plugin_params": dict(row.params) if row else {},
            "plugin_before": row.before if row else None, "plugin_after": row.after if row else None,
            "plugin_p_adjusted": row.p_adjusted if row else None}


def _fmt(x, f="{:.3f}"):
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f.format(x)


def markdown(res: dict) -> str:
    lines = [("| hidden | source | effect size / floor | rank-1 | held-out before → after | reduction | "
             "p (corr.) | calib. session | verdict | fitted |"), "|---|---|---|---|---|---|---|---|---|---|"]
    for r in [res["raw_null"]] + res["nulls"] + res["cases"]:
        fitted = ", ".join(f"{k} = {v:.3g}" for k, v in r["fitted"].items()) if r["verdict"] else ""
        unit = "" if r["channel"] == "force" else " (rel.)"
        lines.append(f"| {r['hidden']} {json.dumps(r['truth']) if r['truth'] else ''} | {r.get('source', '')} | "
                     f"{_fmt(r['effect_size_n'])} N / {_fmt(res['floor_n'])} N = {_fmt(r['ratio'], '{:.1f}')} | "
                     f"{r['rank1']} | {_fmt(r['before'], '{:.4f}')} → {_fmt(r['after'], '{:.4f}')}{unit} | "
                     f"{_fmt(100 * r['reduction'] if r['reduction'] is not None else None, '{:.0f} %')} | "
                     f"{_fmt(r['p_adjusted'], '{:.2g}')} | "
                     f"{_fmt(100 * r['calibration_reduction'] if r['calibration_reduction'] is not None else None, '{:+.0f} %')} | "
                     f"{r['verdict'] or 'none'} | {fitted} |")
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True, help="model package folder (explicit: the numbers name it)")
    p.add_argument("--precision", default="int8", choices=("int8", "fp32"), help="network graph to run")
    p.add_argument("--calib-seeds", type=int, nargs="+", default=list(CALIB_SEEDS),
                   help="calibration sessions (16 pokes each) for the nominal correction")
    p.add_argument("--nulls", type=int, default=10, help="null sessions: the test plan + seeds 1..N-1")
    p.add_argument("--work", default="cache/workbench/acceptance", help="folder for the recorded sessions and caches")
    p.add_argument("--out", help="write the results as JSON here")
    p.add_argument("--only", nargs="*", help="effects to run (default all)")
    p.add_argument("--skip", nargs="*", default=[], choices=("two", "unknown"), help="parts to leave out")


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    bench = Bench(args.model, work, tuple(args.calib_seeds), args.precision)
    cases = [c for c in CASES if not args.only or c.effect in args.only]
    res = run_all(bench, work, args.nulls, cases, [x for x in ("two", "unknown") if x not in args.skip])
    res["seconds"] = time.perf_counter() - t0
    print(markdown(res))
    print(json.dumps({k: res[k] for k in ("two", "two_truth", "two_truth_weak", "unknown", "floor_n", "correction",
                                          "model_sha256")}, default=str))
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=1, default=str))
    return 0

