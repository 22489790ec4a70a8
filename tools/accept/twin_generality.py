"""Generality of the diagnosis on twin units and plans no test or recipe records, with hidden
effects in forms that are not the library's (tools/accept/alter_forms.py), at sizes around the
model's floor (issue 31's acceptance).

    tensortouch accept workbench-twin-generality [--draws 3] [--sizes 0.15 0.3 0.5 1 3] [--mde-multiples 0.5 2]
                                                 [--nulls 10] [--jobs 1] [--work DIR] [--out FILE]
                                                 [--pictures DIR] [--summarize LOG|DIR]

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
altered the same way, with the verdict added. Nulls: unaltered sessions of new plans. Rows at
`--mde-multiples` scale the form to that multiple of the MDE the unaltered test session's diagnosis
reported for its family (the check of the MDE). Every finished row is a file in WORK/rows; a
rerun with the same WORK diagnoses only what is missing, so a run cut short is resumed by running
it again.
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
    p.add_argument("--sizes", type=float, nargs="*", default=[0.15, 0.3, 0.5, 1.0, 3.0],
                   help="effect sizes (× the floor)")
    p.add_argument("--mde-multiples", type=float, nargs="*", default=[0.5, 2.0],
                   help="also effect sizes at these multiples of the MDE the diagnosis reports for the form's "
                        "family on the unaltered test session (library forms only)")
    p.add_argument("--nulls", type=int, default=10, help="sessions with no hidden effect")
    p.add_argument("--first-null", type=int, default=0, help="index of the first null session (to split a run)")
    p.add_argument("--forms", nargs="+", choices=sorted(EXPECTED), help="hidden forms (default: all)")
    p.add_argument("--jobs", type=int, default=1, help="diagnoses run in parallel")
    p.add_argument("--work", default=None, help="work folder (default: cache/workbench/twin-generality); "
                   "every finished row is kept in its rows/ folder and a rerun resumes from them")
    p.add_argument("--out", help="write every row and the summary as JSON here")
    p.add_argument("--pictures", help="write the detection curve here (folder)")
    p.add_argument("--summarize", metavar="LOG", help="only summarize the rows of an earlier run: its printed "
                   "JSON lines (one per line) or its work folder (a run cut short reports what it finished)")


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(x) ** 2, axis=1))))


def _scenario(seed: int, unit: str):
    from ..workbench.scenarios import Scenario

    return Scenario(seed, pokes=POKES, unit=unit)


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
        self.sessions = {}        # recordings loaded once: every size of a draw alters the same one

    def table(self, session, loaded=None):
        """The sample table of the session folder `session` (cached), or of `loaded`, that session
        changed in memory (not cached)."""
        from ..workbench.compare import run_compare

        return run_compare(session, self.unit, self.store, self.law, self.reg, session=loaded).table

    def altered(self, base: Path, form: str, amp: float):
        """The table of `base` with `form` hidden in its F/T force: the recording is loaded once and
        altered in memory, the same numbers as a copy written by alter_forms.alter and read back."""
        from ...contracts.session import load_session
        from .alter_forms import altered_session

        base = Path(base)
        if base not in self.sessions:
            self.sessions[base] = load_session(base, check_frames=False)
        return self.table(base, altered_session(self.sessions[base], form, amp, self.gel))

    def scaled(self, base: Path, form: str, size: float):
        """(table, amp, measured size N): `form` hidden in `base` at rms size `size` N of its own contribution."""
        t0 = self.table(base)
        amp = 1.0
        for _ in range(4):         # linear in amp except where contact is lost: a few secant steps
            t = self.altered(base, form, amp)
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


def clean_mde(form: str, draw: int, work: str, seed: int) -> dict:
    """The diagnosis of the unaltered test session (kept in work/rows): its verdict and the MDE it
    reports for the form's library family -- what a user is told before the effect is there."""
    path = Path(work) / "rows" / f"clean-{form}-{draw}.json"
    if path.is_file():
        return json.loads(path.read_text())
    from ...contracts.files import atomic_write_json
    from ..workbench.diagnose import diagnose
    from ..workbench.scenarios import record

    unit = UNITS[draw % len(UNITS)]
    lab = Lab(unit, Path(work))
    t0 = lab.table(record(_scenario(seed, unit)))
    row = {"form": form, "draw": draw, "unit": unit, "seed": seed, "floor": _rms(t0.meas - t0.model),
           **_diag_row(diagnose(t0, lab.reg))}
    row["mde_family"] = row["mde_per_effect"].get(EXPECTED[form], row["mde"])
    atomic_write_json(path, json.loads(json.dumps(row, default=float)))
    return row


def run_case(form: str, size: float, draw: int, work: str, seeds: tuple | None = None,
             mde_multiple: float | None = None) -> dict:
    """One altered session diagnosed. `size` × the floor, or with `mde_multiple` that multiple of the
    MDE the unaltered session's diagnosis reports for the form's family (then `size` is ignored)."""
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
    extra, clean = {}, None
    if form != "velocity_drag":
        clean = clean_mde(form, draw, work, test_seed)
        extra["mde_clean"] = clean["mde_family"]
    if mde_multiple is not None:
        size = mde_multiple * clean["mde_family"] / floor
        extra["mde_target"] = mde_multiple
    t, amp, got = lab.scaled(base, form, size * floor)
    d = diagnose(t, lab.reg)
    row = {"form": form, "unit": unit, "draw": draw, "seed": test_seed, "size_floor": size, "floor": floor, "size_n": got,
           "amp": amp, **extra, **_diag_row(d)}
    fam = EXPECTED[form]
    mde = row["mde_per_effect"].get(fam, row["mde"])
    row["mde_effect"] = mde
    row["size_mde"] = got / mde if mde else None
    if clean is not None and clean["mde_family"]:
        row["size_clean_mde"] = got / clean["mde_family"]
    if form == "velocity_drag":
        row["right"] = bool(row["top_covariate"] in VELOCITY and (row["covariate_p"] or 1.0) <= 0.05)
    else:
        row["right"] = row["family"] == fam and not row["pair"]
    v = d.verdict
    if v is not None and v.pair is None and v.channel == "force":      # removed on a second session of the unit
        second = record(_scenario(second_seed, unit))
        c2 = lab.table(second)
        a2 = lab.altered(second, form, amp)
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


def mde_multiple(r: dict) -> float | None:
    """A row's size / MDE: the targeted multiple, else the size over the MDE the unaltered session
    reported for the family, else over the one the altered session reported."""
    if r.get("mde_target") is not None:
        return r["mde_target"]
    return r.get("size_clean_mde") or r.get("size_mde")


def summarize(rows: list, nulls: list) -> dict:
    """Counts over the rows: `rows` at sizes × the floor and, marked `mde_target`, at multiples of the
    unaltered session's MDE (those count in the MDE check, not in the size/floor curve)."""
    grid = [r for r in rows if r.get("mde_target") is None]
    by: dict = {}
    for r in grid:
        by.setdefault(r["form"], {}).setdefault(r["size_floor"], []).append(r)
    rate = {f: {f"{s:g}": f"{sum(r['right'] for r in rs)}/{len(rs)}" for s, rs in sorted(d.items())}
            for f, d in by.items()}
    removed = [r["removed"] for r in grid if r["right"] and "removed" in r and r["size_floor"] >= 1.0]
    big = [r for r in grid if r["size_floor"] >= 1.0]
    lib = [r for r in rows if r["form"] != "velocity_drag"]

    multiple = mde_multiple

    two = [r for r in lib if (multiple(r) or 0) >= 2.0]
    half = [r for r in lib if (multiple(r) or 9) <= 0.5]
    targeted = {}
    for r in lib:
        if r.get("mde_target") is not None:
            targeted.setdefault(f"{r['mde_target']:g}", []).append(r)
    drag = [r for r in grid if r["form"] == "velocity_drag" and r["size_floor"] >= 1.0]
    return {"detection": rate,
            "right_at_or_above_floor": f"{sum(r['right'] for r in big)}/{len(big)}",
            "removed_at_or_above_floor": {"n": len(removed), "median": float(np.median(removed)) if removed else None,
                                          "min": float(np.min(removed)) if removed else None,
                                          "at_least_70": f"{sum(x >= 0.7 for x in removed)}/{len(removed)}"},
            "null_false_alarms": f"{sum(n['verdict'] is not None for n in nulls)}/{len(nulls)}",
            "null_covariate_alarms": f"{sum((n['covariate_p'] or 1.0) <= 0.05 for n in nulls)}/{len(nulls)}",
            "drag_velocity_named": f"{sum(r['right'] for r in drag)}/{len(drag)}",
            "mde_2x_found": f"{sum(r['right'] for r in two)}/{len(two)}",
            "mde_half_claimed": f"{sum(r['verdict'] is not None for r in half)}/{len(half)}",
            "mde_targeted": {m: {"right": f"{sum(r['right'] for r in rs)}/{len(rs)}",
                                 "claimed": f"{sum(r['verdict'] is not None for r in rs)}/{len(rs)}"}
                             for m, rs in sorted(targeted.items(), key=lambda kv: float(kv[0]))}}


def picture(rows: list, nulls: list, path: Path) -> Path:
    """Left: share of draws with the right significant verdict against size / the floor, per form and
    over all forms (rows at fixed sizes). Right: the library forms against size / the MDE the
    unaltered session reported (targeted rows at their multiple; the others at their measured ratio,
    binned), with the share of draws that got any verdict. `nulls`: the sessions without a hidden
    effect (the nulls and the unaltered test sessions), whose share with a verdict is drawn too."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid = [r for r in rows if r.get("mde_target") is None]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(8.4, 3.4), dpi=100, gridspec_kw={"width_ratios": [1.25, 1]})
    sizes = sorted({r["size_floor"] for r in grid})
    for form in EXPECTED:
        rs = [r for r in grid if r["form"] == form]
        if rs:
            xs = [s for s in sizes if any(r["size_floor"] == s for r in rs)]
            y = [np.mean([r["right"] for r in rs if r["size_floor"] == s]) for s in xs]
            ax.plot(xs, y, "o-", ms=3.5, lw=1.0, alpha=0.8, label=form.replace("_", " "))
    if sizes:
        y = [np.mean([r["right"] for r in grid if r["size_floor"] == s]) for s in sizes]
        n = [sum(r["size_floor"] == s for r in grid) for s in sizes]
        ax.plot(sizes, y, "k-", lw=2.5, label="all forms")
        for x, yy, k in zip(sizes, y, n):
            ax.annotate(f"n={k}", (x, yy), textcoords="offset points", xytext=(0, -11), ha="center", fontsize=6)
        ax.set_xscale("log")
        ax.set_xticks(sizes)
        ax.set_xticklabels([f"{s:g}×" for s in sizes])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    if nulls:
        fa = np.mean([n["verdict"] is not None for n in nulls])
        ax.axhline(fa, color="grey", ls=":", lw=1)
        ax.text(sizes[0] if sizes else 1.0, fa + 0.04, f"verdicts on {len(nulls)} sessions without a hidden effect: {100 * fa:.0f} %",
                fontsize=7, color="grey")
    ax.axvline(1.0, color="grey", lw=0.6)
    ax.set_ylim(-0.08, 1.08)
    ax.set_xlabel("hidden effect's own contribution / the model's floor")
    ax.set_ylabel("share of draws: right significant verdict")
    ax.legend(fontsize=6, loc="lower right")
    ax.set_title(f"{len(grid)} altered sessions at fixed sizes", fontsize=9)

    lib = [r for r in rows if r["form"] != "velocity_drag"]

    multiple = mde_multiple

    bins = [(0.0, 0.75, 0.5), (0.75, 1.5, 1.0), (1.5, 3.0, 2.0), (3.0, 6.0, 4.0), (6.0, np.inf, 8.0)]
    xs, right, claimed, ns = [], [], [], []
    for lo, hi, x in bins:
        rs = [r for r in lib if multiple(r) is not None and lo <= multiple(r) < hi]
        if rs:
            xs.append(x)
            right.append(np.mean([r["right"] for r in rs]))
            claimed.append(np.mean([r["verdict"] is not None for r in rs]))
            ns.append(len(rs))
    bx.plot(xs, right, "ko-", lw=2, ms=4, label="right verdict")
    bx.plot(xs, claimed, "s--", color="tab:red", lw=1, ms=3.5, label="any verdict")
    for x, yy, k in zip(xs, right, ns):
        bx.annotate(f"n={k}", (x, yy), textcoords="offset points", xytext=(0, -11), ha="center", fontsize=6)
    bx.axhline(0.9, color="tab:green", ls=":", lw=0.8)
    bx.axhline(0.1, color="tab:red", ls=":", lw=0.8)
    bx.set_xscale("log")
    bx.set_xticks([0.5, 1, 2, 4, 8])
    bx.set_xticklabels(["<0.75", "0.75–1.5", "1.5–3", "3–6", "≥6"], fontsize=7)
    bx.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    bx.set_ylim(-0.08, 1.08)
    bx.set_xlabel("size / the unaltered session's MDE (binned)")
    bx.set_title(f"library forms, {len(lib)} sessions", fontsize=9)
    bx.legend(fontsize=6.5, loc="lower right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def markdown(rows: list) -> str:
    lines = ["| hidden form | size | right | verdicts (p) | size / MDE | own contribution removed (2nd session) |",
             "|---|---|---|---|---|---|"]
    by: dict = {}
    for r in sorted(rows, key=lambda r: (list(EXPECTED).index(r["form"]), r.get("mde_target") is not None,
                                         r.get("mde_target") or r["size_floor"], r.get("draw") or 0)):
        by.setdefault((r["form"], r.get("mde_target"), None if r.get("mde_target") else r["size_floor"]), []).append(r)
    for (form, target, size), rs in by.items():
        verdicts = ", ".join(f"{r['verdict'] or ('cov ' + str(r['top_covariate']) if form == 'velocity_drag' else 'none')}"
                             f" ({(r['p'] if r['verdict'] else r['covariate_p'] if form == 'velocity_drag' else r['best_p']) or 1:.2g})"
                             for r in rs)
        rem = ", ".join(f"{100 * r['removed']:.0f} %" for r in rs if "removed" in r) or "—"
        ratio = ", ".join(f"{mde_multiple(r):.2g}" for r in rs if mde_multiple(r)) or "—"
        label = f"{target:g}× MDE" if target is not None else f"{size:g}× floor"
        lines.append(f"| {form} | {label} | {sum(r['right'] for r in rs)}/{len(rs)} | {verdicts} | {ratio} | {rem} |")
    return "\n".join(lines)


def counts(rows: list) -> str:
    """Markdown: right significant verdicts / draws per form and size (× the floor, then the
    targeted multiples of the MDE)."""
    grid = sorted({r["size_floor"] for r in rows if r.get("mde_target") is None})
    targets = sorted({r["mde_target"] for r in rows if r.get("mde_target") is not None})
    heads = [f"{s:g}× floor" for s in grid] + [f"{m:g}× MDE" for m in targets]
    lines = ["| hidden form | " + " | ".join(heads) + " |", "|---" * (len(heads) + 1) + "|"]
    for form in EXPECTED:
        cells = []
        for s in grid:
            rs = [r for r in rows if r["form"] == form and r.get("mde_target") is None and r["size_floor"] == s]
            cells.append(f"{sum(r['right'] for r in rs)}/{len(rs)}" if rs else "—")
        for m in targets:
            rs = [r for r in rows if r["form"] == form and r.get("mde_target") == m]
            cells.append(f"{sum(r['right'] for r in rs)}/{len(rs)} ({sum(r['verdict'] is not None for r in rs)} claimed)"
                         if rs else "—")
        if any(c != "—" for c in cells):
            lines.append(f"| {form} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def read_clean(work: Path) -> list:
    """The diagnoses of the unaltered test sessions (work/rows/clean-*.json): more sessions without a
    hidden effect, from other plans than the nulls."""
    return [json.loads(f.read_text()) for f in sorted((Path(work) / "rows").glob("clean-*.json"))]


def report(rows: list, nulls: list, a: argparse.Namespace, clean: list | None = None) -> dict:
    out = {"cases": rows, "nulls": nulls, "summary": summarize(rows, nulls)}
    if clean:
        out["unaltered_test_sessions"] = clean
        out["summary"]["unaltered_test_session_verdicts"] = (f"{sum(c['verdict'] is not None for c in clean)}/"
                                                            f"{len(clean)}")
    print(json.dumps(out["summary"], indent=1))
    print(counts(rows))
    print(markdown(rows))
    if a.pictures:
        print(picture(rows, nulls + list(clean or []), Path(a.pictures) / "generality_detection.png"))
    if a.out:
        from ...contracts.files import atomic_write_json

        atomic_write_json(a.out, json.loads(json.dumps(out, default=float)), indent=1)
    return out


def row_key(r: dict) -> tuple:
    return (r["form"], r.get("mde_target"), None if r.get("mde_target") is not None else r["size_floor"], r.get("draw"))


def read_rows(path: str) -> tuple[list, list]:
    """Rows and null rows from the JSON lines of one or more runs, or from a work folder's rows/
    (a case or null met twice counts once)."""
    p = Path(path)
    if p.is_dir():
        lines = [f.read_text() for f in sorted((p / "rows").glob("*.json")) if not f.name.startswith("clean-")]
        lines = [json.dumps(json.loads(x)) for x in lines]
    else:
        lines = p.read_text().splitlines()
    rows, nulls = {}, {}
    for line in lines:
        if line.startswith("{") and line.endswith("}"):
            r = json.loads(line)
            if "form" in r:
                rows.setdefault(row_key(r), r)
            elif "null" in r:
                nulls.setdefault(r["null"], r)
    return list(rows.values()), list(nulls.values())


def _task_file(work: Path, kind: str, args: tuple, mult) -> Path:
    if kind == "null":
        return work / "rows" / f"null-{args[0]}.json"
    form, size, draw = args[:3]
    return work / "rows" / (f"case-{form}-mde{mult:g}-{draw}.json" if mult is not None
                            else f"case-{form}-{size:g}-{draw}.json")


def _do(kind: str, args: tuple, mult) -> dict:
    return run_null(*args) if kind == "null" else run_case(*args, mde_multiple=mult)


def run(a: argparse.Namespace) -> int:
    from ...contracts import paths
    from ...contracts.files import atomic_write_json
    from ..workbench.scenarios import record

    logging.basicConfig(level=logging.WARNING)
    if a.summarize:
        report(*read_rows(a.summarize), a, read_clean(a.summarize) if Path(a.summarize).is_dir() else None)
        return 0
    work = Path(a.work) if a.work else paths.cache_dir() / "workbench" / "twin-generality"
    (work / "rows").mkdir(parents=True, exist_ok=True)
    forms = a.forms or list(EXPECTED)
    seeds = {(f, k): (TEST_SEED + 10 * i + k, SECOND_SEED + 10 * i + k)
             for i, f in enumerate(EXPECTED) if f in forms for k in range(a.draws)}
    null_seeds = {k: NULL_SEED + k for k in range(a.first_null, a.first_null + a.nulls)}
    order = sorted(a.sizes)
    lib = [f for f in forms if f != "velocity_drag"]
    # the sizes the acceptance is about first, then the nulls, the MDE multiples, the small sizes
    tasks = [("case", (f, s, k, str(work), seeds[f, k]), None) for s in order if s >= 1.0
             for k in range(a.draws) for f in forms]
    tasks += [("null", (k, str(work), null_seeds[k]), None) for k in null_seeds]
    tasks += [("case", (f, 0.0, k, str(work), seeds[f, k]), m) for m in a.mde_multiples or []
              for k in range(a.draws) for f in lib]
    tasks += [("case", (f, s, k, str(work), seeds[f, k]), None) for s in order[::-1] if s < 1.0
              for k in range(a.draws) for f in forms]
    rows, nulls, todo = [], [], []
    for kind, args, mult in tasks:                # finished rows are read back: a rerun resumes
        f = _task_file(work, kind, args, mult)
        if f.is_file():
            r = json.loads(f.read_text())
            (rows if kind == "case" else nulls).append(r)
            print(json.dumps(r), flush=True)
        else:
            todo.append((kind, args, mult))

    def keep(kind, args, mult, r):
        atomic_write_json(_task_file(work, kind, args, mult), json.loads(json.dumps(r, default=float)))
        (rows if kind == "case" else nulls).append(r)
        print(json.dumps(r, default=float), flush=True)

    if a.jobs <= 1:
        for kind, args, mult in todo:
            keep(kind, args, mult, _do(kind, args, mult))
    else:
        for unit in UNITS:                        # fit the laws, then record every session once, before the rows
            Lab(unit, work)
        scenarios = {}
        for kind, args, _ in todo:
            unit = UNITS[(args[2] if kind == "case" else args[0]) % len(UNITS)]
            for s in (args[-1] if kind == "case" else (args[-1],)):
                scenarios.setdefault(_scenario(s, unit).key(), _scenario(s, unit))
        with ProcessPoolExecutor(max_workers=a.jobs) as pool:
            list(pool.map(record, scenarios.values()))               # each session by one worker
            futs = [(t, pool.submit(_do, *t)) for t in todo]
            for t, fut in futs:
                keep(*t, fut.result())
    report(rows, nulls, a, read_clean(work))
    return 0
