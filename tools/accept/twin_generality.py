"""Generality of the diagnosis on twin units and plans no test or recipe records, with hidden
effects in forms that are not the library's (tools/accept/alter_forms.py), at sizes around the
model's floor (issue 31's acceptance).

    tensortouch accept workbench-twin-generality [--draws 3] [--sizes 0.3 1 3] [--nulls 10] [--jobs 2]
                                                 [--out FILE] [--pictures DIR]

Units TWIN-G01..G03 (draw k uses unit k mod 3), analytic twin physics (hertz-fallback: the FE
backend is the same pipeline, ~100× slower to record), sessions of 30 pokes (poke / press / slide /
twist, two indenters, ~100 s, temperature drifting 5 °C). The model is the nominal contact law
fitted on a calibration session of the same unit (`compare --model contact-law --model-from`).
Per effect and draw, one test session (a new plan) carries the hidden form, scaled so its own
contribution (rms over the sample table's rows of the altered minus the unaltered measured force)
is `size` × the floor (the model's rms error on the unaltered session). Diagnosis sees the
altered session's sample table only (the same `diagnose` the CLI runs, default settings).

Reported per row: the verdict and its corrected p; "right" (the verdict's family is the form's
physics; for the drag: the top covariate of what remains is the indenter's velocity and
significant); the MDE the diagnosis reported for the form's library family and size / MDE;
"removed" = (before - after) / (before - unaltered) on a second session of the unit (another plan)
altered the same way, with the verdict added. Nulls: unaltered sessions of new plans.
"""
from __future__ import annotations

import argparse
import json
import logging
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

UNITS = ("TWIN-G01", "TWIN-G02", "TWIN-G03")
POKES = 30
CALIB_SEED = 5100             # + unit index
TEST_SEED = 5200              # + 10 * form index + draw
SECOND_SEED = 5300            # + 10 * form index + draw
NULL_SEED = 5400              # + null index
EXPECTED = {"saturating_stiffening": "strain_stiffening", "two_term_relaxation": "viscoelastic_relaxation",
            "rim_profile": "rim_stiffening", "temperature_onset": "temperature_softening",
            "velocity_drag": "velocity"}
VELOCITY = ("velocity", "vel_x", "vel_y", "vel_z")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--draws", type=int, default=3, help="draws (test sessions) per form and size")
    p.add_argument("--sizes", type=float, nargs="+", default=[0.3, 1.0, 3.0], help="effect sizes (× the floor)")
    p.add_argument("--nulls", type=int, default=10, help="sessions with no hidden effect")
    p.add_argument("--first-null", type=int, default=0, help="index of the first null session (to split a run)")
    p.add_argument("--forms", nargs="+", choices=sorted(EXPECTED), help="hidden forms (default: all)")
    p.add_argument("--jobs", type=int, default=1, help="diagnoses run in parallel")
    p.add_argument("--work", default=None, help="work folder (default: cache/workbench/twin-generality)")
    p.add_argument("--out", help="write every row and the summary as JSON here")
    p.add_argument("--pictures", help="write the detection curve here (folder)")
    p.add_argument("--summarize", metavar="LOG", help="only summarize the JSON rows printed by an earlier run "
                   "(one per line; a run cut short reports what it finished)")


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(x) ** 2, axis=1))))


def _scenario(seed: int, unit: str):
    from ..workbench.scenarios import Scenario

    return Scenario(seed, pokes=POKES, unit=unit)


def plannable_seed(seed: int, unit: str, limit_s: float = 10.0) -> int:
    """`seed`, or the first of seed + 100000 k whose plan the twin's planner finishes within `limit_s`
    (some seeds never finish: the placement of two indenters retries forever). Main thread only."""
    import signal

    from ..twin.trajectory import plan_session, with_ranges
    from ..twin.unit import TwinUnit
    from dataclasses import replace
    from ..twin.record import RecordConfig

    sc = _scenario(seed, unit)
    cfg = RecordConfig().trajectory
    cfg = with_ranges(replace(cfg, indenters=tuple(sc.indenters), kinds=tuple(sc.kinds)), None, "")
    gel = TwinUnit(unit).gel

    def _stop(*_):
        raise TimeoutError

    old = signal.signal(signal.SIGALRM, _stop)
    try:
        for k in range(5):
            signal.setitimer(signal.ITIMER_REAL, limit_s)
            try:
                plan_session(POKES, seed + 100000 * k, gel, cfg)
                return seed + 100000 * k
            except TimeoutError:
                log.warning("twin plan of seed %d (unit %s) does not finish; using the next seed", seed + 100000 * k, unit)
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
    finally:
        signal.signal(signal.SIGALRM, old)
    raise RuntimeError(f"no plannable seed near {seed}")


def _gel(unit: str) -> dict:
    from ...contracts.store import CalibrationStore
    from ..workbench.scenarios import store_root

    gel = CalibrationStore(store_root(unit)).load(unit).meta["gel"]
    return {"radius": gel["radius_mm"], "center_z": gel["center_z_mm"], "skirt": gel["skirt_mm"]}


class Lab:
    """One unit: its store, the contact law fitted on its calibration session, tables of sessions."""

    def __init__(self, unit: str, work: Path):
        from ...contracts.store import CalibrationStore
        from ...runtime.stages.effects import Registry
        from ..workbench.models import ContactLaw
        from ..workbench.scenarios import store_root

        self.unit, self.work = unit, Path(work)
        self.store = CalibrationStore(store_root(unit))
        self.reg = Registry.default(entry_points=False)
        law_path = self.work / f"law-{unit}.json"
        if law_path.is_file():
            self.law = ContactLaw.load(law_path)
        else:
            from ..workbench.compare import load_table
            from ..workbench.scenarios import record

            calib = record(_scenario(CALIB_SEED + UNITS.index(unit), unit))
            self.law = ContactLaw.fit(load_table(calib, self.store.load(unit))[0], source=str(calib))
            self.law.save(law_path)
        self.gel = _gel(unit)

    def table(self, session, cache: bool = True):
        from ..workbench.compare import run_compare

        return run_compare(session, self.unit, self.store, self.law, self.reg, cache=cache).table

    def altered(self, base: Path, form: str, amp: float, tag: str):
        from .alter_forms import alter

        return self.table(alter(base, self.work / "altered" / tag, form, amp, self.gel), cache=False)

    def scaled(self, base: Path, form: str, size: float, tag: str):
        """(table, amp, measured size N): `form` hidden in `base` at rms size `size` N of its own contribution."""
        t0 = self.table(base)
        amp = 1.0
        for _ in range(4):         # linear in amp except where contact is lost: a few secant steps
            t = self.altered(base, form, amp, tag)
            got = _rms(t.meas - t0.meas)
            if abs(got - size) <= 0.02 * size:
                break
            amp *= size / max(got, 1e-12)
        return t, amp, got


def _diag_row(d) -> dict:
    v, u = d.verdict, d.unexplained
    return {"verdict": v.effect.name if v else None, "family": (v.effect.family or v.effect.name) if v else None,
            "pair": v.pair is not None if v else False, "p": v.p_adjusted if v else None,
            "best": d.ranking[0].effect.name if d.ranking else None,
            "best_p": d.ranking[0].p_adjusted if d.ranking else None,
            "top_covariate": u.get("covariate"), "covariate_p": u.get("p_adjusted"),
            "covariate_score": u.get("score"), "mde": d.mde["mde"] if d.mde else None,
            "mde_per_effect": dict(d.mde.get("per_effect", {})) if d.mde else {}}


def run_case(form: str, size: float, draw: int, work: str, seeds: tuple | None = None) -> dict:
    from ...runtime.stages.effects import EffectChain, EnabledEffect
    from ..workbench.diagnose import diagnose
    from ..workbench.fit import deployed_prediction
    from ..workbench.scenarios import record

    i = list(EXPECTED).index(form)
    unit = UNITS[draw % len(UNITS)]
    lab = Lab(unit, Path(work))
    test_seed, second_seed = seeds or (TEST_SEED + 10 * i + draw, SECOND_SEED + 10 * i + draw)
    base = record(_scenario(test_seed, unit))
    t0 = lab.table(base)
    floor = _rms(t0.meas - t0.model)
    t, amp, got = lab.scaled(base, form, size * floor, f"{form}-{draw}-{size:g}")
    d = diagnose(t, lab.reg)
    row = {"form": form, "unit": unit, "draw": draw, "seed": test_seed, "size_floor": size, "floor": floor, "size_n": got,
           "amp": amp, **_diag_row(d)}
    fam = EXPECTED[form]
    mde = row["mde_per_effect"].get(fam, row["mde"])
    row["mde_effect"] = mde
    row["size_mde"] = got / mde if mde else None
    if form == "velocity_drag":
        row["right"] = bool(row["top_covariate"] in VELOCITY and (row["covariate_p"] or 1.0) <= 0.05)
    else:
        row["right"] = row["family"] == fam and not row["pair"]
    v = d.verdict
    if v is not None and v.pair is None and v.channel == "force":      # removed on a second session of the unit
        second = record(_scenario(second_seed, unit))
        c2 = lab.table(second)
        a2 = lab.altered(second, form, amp, f"{form}-{draw}-{size:g}-second")
        pred = deployed_prediction(a2.model, a2.cov(), EffectChain([EnabledEffect(v.effect, dict(v.params))]))
        before, after, clean = _rms(a2.meas - a2.model), _rms(a2.meas - pred), _rms(c2.meas - c2.model)
        row.update({"second_before": before, "second_after": after, "second_unaltered": clean,
                    "removed": (before - after) / max(before - clean, 1e-12)})
    return row


def run_null(k: int, work: str, seed: int | None = None) -> dict:
    from ..workbench.diagnose import diagnose
    from ..workbench.scenarios import record

    unit = UNITS[k % len(UNITS)]
    lab = Lab(unit, Path(work))
    seed = NULL_SEED + k if seed is None else seed
    t = lab.table(record(_scenario(seed, unit)))
    d = diagnose(t, lab.reg)
    return {"null": k, "unit": unit, "seed": seed, "floor": _rms(t.meas - t.model), **_diag_row(d)}


def summarize(rows: list, nulls: list) -> dict:
    by: dict = {}
    for r in rows:
        by.setdefault(r["form"], {}).setdefault(r["size_floor"], []).append(r)
    rate = {f: {f"{s:g}": f"{sum(r['right'] for r in rs)}/{len(rs)}" for s, rs in sorted(d.items())}
            for f, d in by.items()}
    removed = [r["removed"] for r in rows if r["right"] and "removed" in r and r["size_floor"] >= 1.0]
    big = [r for r in rows if r["size_floor"] >= 1.0]
    two = [r for r in rows if r["form"] != "velocity_drag" and (r["size_mde"] or 0) >= 2.0]
    half = [r for r in rows if r["form"] != "velocity_drag" and (r["size_mde"] or 9) <= 0.5]
    drag = [r for r in rows if r["form"] == "velocity_drag" and r["size_floor"] >= 1.0]
    return {"detection": rate,
            "right_at_or_above_floor": f"{sum(r['right'] for r in big)}/{len(big)}",
            "removed_at_or_above_floor": {"n": len(removed), "median": float(np.median(removed)) if removed else None,
                                          "min": float(np.min(removed)) if removed else None,
                                          "at_least_70": f"{sum(x >= 0.7 for x in removed)}/{len(removed)}"},
            "null_false_alarms": f"{sum(n['verdict'] is not None for n in nulls)}/{len(nulls)}",
            "null_covariate_alarms": f"{sum((n['covariate_p'] or 1.0) <= 0.05 for n in nulls)}/{len(nulls)}",
            "drag_velocity_named": f"{sum(r['right'] for r in drag)}/{len(drag)}",
            "mde_2x_found": f"{sum(r['right'] for r in two)}/{len(two)}",
            "mde_half_claimed": f"{sum(r['verdict'] is not None for r in half)}/{len(half)}"}


def picture(rows: list, nulls: list, path: Path) -> Path:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.6, 3.4), dpi=110)
    sizes = sorted({r["size_floor"] for r in rows})
    for form in EXPECTED:
        rs = [r for r in rows if r["form"] == form]
        if rs:
            xs = [s for s in sizes if any(r["size_floor"] == s for r in rs)]
            y = [np.mean([r["right"] for r in rs if r["size_floor"] == s]) for s in xs]
            ax.plot(xs, y, "o-", ms=4, lw=1.2, label=form.replace("_", " "))
    y = [np.mean([r["right"] for r in rows if r["size_floor"] == s]) for s in sizes]
    ax.plot(sizes, y, "k-", lw=2.5, label="all forms")
    if nulls:
        fa = np.mean([n["verdict"] is not None for n in nulls])
        ax.axhline(fa, color="grey", ls=":", lw=1)
        ax.text(sizes[0], fa + 0.04, f"false alarms on {len(nulls)} nulls: {100 * fa:.0f} %", fontsize=7, color="grey")
    ax.axvline(1.0, color="grey", lw=0.6)
    ax.set_xscale("log")
    ax.set_xticks(sizes)
    ax.set_xticklabels([f"{s:g}×" for s in sizes])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_ylim(-0.05, 1.05)
    ax.set_xlabel("hidden effect's own contribution / the model's floor")
    ax.set_ylabel("right significant verdict")
    ax.set_title(f"Detection on twin units ({len(rows)} altered sessions, share of draws per point)", fontsize=9)
    ax.legend(fontsize=6.5, loc="center right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def markdown(rows: list) -> str:
    lines = ["| hidden form | size / floor | right | verdicts (p) | size / MDE | own contribution removed (2nd session) |",
             "|---|---|---|---|---|---|"]
    by: dict = {}
    for r in rows:
        by.setdefault((r["form"], r["size_floor"]), []).append(r)
    for (form, size), rs in by.items():
        verdicts = ", ".join(f"{r['verdict'] or ('cov ' + str(r['top_covariate']) if form == 'velocity_drag' else 'none')}"
                             f" ({(r['p'] if r['verdict'] else r['covariate_p'] if form == 'velocity_drag' else r['best_p']) or 1:.2g})"
                             for r in rs)
        rem = ", ".join(f"{100 * r['removed']:.0f} %" for r in rs if "removed" in r) or "—"
        ratio = ", ".join(f"{r['size_mde']:.1f}" for r in rs if r.get("size_mde"))
        lines.append(f"| {form} | {size:g} | {sum(r['right'] for r in rs)}/{len(rs)} | {verdicts} | {ratio} | {rem} |")
    return "\n".join(lines)


def report(rows: list, nulls: list, a: argparse.Namespace) -> dict:
    out = {"cases": rows, "nulls": nulls, "summary": summarize(rows, nulls)}
    print(json.dumps(out["summary"], indent=1))
    print(markdown(rows))
    if a.pictures:
        print(picture(rows, nulls, Path(a.pictures) / "generality_detection.png"))
    if a.out:
        from ...contracts.files import atomic_write_json

        atomic_write_json(a.out, json.loads(json.dumps(out, default=float)), indent=1)
    return out


def read_rows(path: str) -> tuple[list, list]:
    """Rows and null rows from the JSON lines of one or more runs (a case or null met twice counts once)."""
    rows, nulls = {}, {}
    for line in Path(path).read_text().splitlines():
        if line.startswith("{") and line.endswith("}"):
            r = json.loads(line)
            if "form" in r:
                rows.setdefault((r["form"], r["size_floor"], r.get("draw")), r)
            elif "null" in r:
                nulls.setdefault(r["null"], r)
    return list(rows.values()), list(nulls.values())


def run(a: argparse.Namespace) -> int:
    from ...contracts import paths
    from ..workbench.scenarios import record

    logging.basicConfig(level=logging.WARNING)
    if a.summarize:
        report(*read_rows(a.summarize), a)
        return 0
    work = Path(a.work) if a.work else paths.cache_dir() / "workbench" / "twin-generality"
    work.mkdir(parents=True, exist_ok=True)
    forms = a.forms or list(EXPECTED)
    for unit in UNITS:                 # fit the laws once, before the pool
        Lab(unit, work)
    seeds, null_seeds = {}, {}
    for i, form in enumerate(EXPECTED):       # record every session once, before the pool
        if form in forms:
            for k in range(a.draws):
                unit = UNITS[k % len(UNITS)]
                seeds[form, k] = tuple(plannable_seed(s + 10 * i + k, unit) for s in (TEST_SEED, SECOND_SEED))
                for s in seeds[form, k]:
                    record(_scenario(s, unit))
    for k in range(a.first_null, a.first_null + a.nulls):
        null_seeds[k] = plannable_seed(NULL_SEED + k, UNITS[k % len(UNITS)])
        record(_scenario(null_seeds[k], UNITS[k % len(UNITS)]))
    order = sorted(a.sizes)
    tasks = [("case", (f, s, k, str(work), seeds[f, k])) for s in order if s >= 1.0 for f in forms
             for k in range(a.draws)]                               # the sizes the acceptance is about first
    tasks += [("null", (k, str(work), null_seeds[k])) for k in null_seeds]
    tasks += [("case", (f, s, k, str(work), seeds[f, k])) for s in order[::-1] if s < 1.0 for f in forms
              for k in range(a.draws)]
    rows, nulls = [], []
    with ProcessPoolExecutor(max_workers=max(1, a.jobs)) as pool:
        futs = [(kind, pool.submit(run_case if kind == "case" else run_null, *args)) for kind, args in tasks]
        for kind, fut in futs:
            r = fut.result()
            (rows if kind == "case" else nulls).append(r)
            print(json.dumps(r, default=float), flush=True)
    report(rows, nulls, a)
    return 0
