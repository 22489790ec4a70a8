"""The workbench on each model path: hidden effects in forms no test uses, on twin units no test or
recipe uses, diagnosed through the shipped network's output, the contact law fitted on several
calibration sessions, and FE solved at each session's measured keypoints (issue 45's acceptance).

    tensortouch accept workbench-paths [--paths contact-law output fe] [--draws 1] [--sizes 1 3]
                                       [--nulls 10] [--forms NAME ...] [--tuning] [--fe-physics fe]
                                       [--world analytic|fe] [--fe-pokes 6]
                                       [--model PACKAGE] [--mde-target X] [--max-sessions 8]
                                       [--work DIR] [--progress FILE]

Units TWIN-K01..K03, frames at 2 fps rendered at the shipped model's 128 px, recorded with the twin's
analytic contact physics or (`--world fe`) with the twin's FE, the physics the shipped network was
trained on and the FE path solves (the FE path's floor is then the label error: keypoints found from
the session's poses and F/T instead of the plan's).
Per unit and path, two calibration sessions without hidden physics: the contact law is fitted on
both together (`ContactLaw.fit_sessions`), and on every path the model's own error (own_error.py) is
fitted on both and every diagnosis runs against it. Paths: "output" = the shipped network's raw
force over the session's frames (no correction: the nominal correction did nothing on these units);
"contact-law"; "fe" = the recipe's stages 1-2 on the session (keypoints from its own poses and F/T,
one scenario per contact period) solved by tools.fe with its shared on-disk cache
(`--fe-physics hertz-fallback`: the recipe's analytic stand-in). FE solves cost ~30 s per contact
period on the shared 2 cores, so the FE path runs on unit TWIN-K01 only, with sessions of
FE_POKES pokes; the others on 30-poke sessions of all three units.

FE at the keypoints of an altered session: stage 1 finds contact periods from |F| thresholds, so a
hidden effect in the F/T stream moves a period's edges by a few samples and every altered copy would
be solved anew. The harness solves each recording once, at the keypoints stage 1 finds on it before
the effect is put in, and compares the altered F/T with that; `compare --paths fe` on a written
altered copy solves its own keypoints.

Hidden forms (tools/accept/alter_forms.py), kept in two sets: the TUNING forms (log_stiffening,
exp_temperature, ft_offset_ramp, sector_stiffening; used while the method was developed,
`--tuning`) and the SCORED forms (cubic_stiffening, logistic_temperature, ft_offset_sqrt,
rim_linear; the default), each with the library family a right verdict names (sector_stiffening:
no verdict and the azimuth φ named, significant). Each is scaled so its own contribution on the
path's rows is `size` × the path's floor (rms |r| of the unaltered session against the model + its
own error). Per row: the verdict, "right", and on a second session of the unit altered the same way,
with the verdict added, the share of the effect's own contribution removed:
(before - after) / (before - unaltered).

Pooled sessions (`--mde-target X`): when a case's or a null's session gives no verdict and an MDE above
X times its floor, as many more sessions of the unit as the MDE asks for (seeds + MORE_SEED·k, the same
effect at the same amplitude; at most `--max-sessions`, at most twice) are diagnosed together with it
(`pool_tables`, as `diagnose SESSION --with ...` does).

Nulls: unaltered sessions the own error was not fitted on: first the cases' test and second sessions
before their effect is put in, then sessions of new plans, `--nulls` in all per path; on the paths of
`--raw-nulls` each is also diagnosed against the model alone. Rows are kept under WORK/rows; a
rerun resumes.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from .alter_forms import MULTIPLICATIVE, gain_of

log = logging.getLogger(__name__)

UNITS = ("TWIN-K01", "TWIN-K02", "TWIN-K03")
FE_UNITS = ("TWIN-K01",)       # FE solves are slow: one unit, shorter sessions
POKES = 30
FE_POKES = 6                   # 6 press blocks: the sign-flip test can still reach p = 1/64
MAX_SESSIONS = 8               # --mde-target: at most this many sessions diagnosed together
MORE_SEED = 1000               # the k-th added session of a seed: seed + MORE_SEED * k
CALIB_SEEDS = (7100, 7150)     # + unit index
TEST_SEED = 7200               # + 10 * form index + draw
SECOND_SEED = 7300
NULL_SEED = 7400
FE_SEED_OFFSET = 1000          # the FE path's sessions: the same seeds + this
TUNING = {"log_stiffening": "strain_stiffening", "exp_temperature": "temperature_softening",
          "ft_offset_ramp": "ft_bias_drift", "sector_stiffening": "phi"}
SCORED = {"cubic_stiffening": "strain_stiffening", "logistic_temperature": "temperature_softening",
          "ft_offset_sqrt": "ft_bias_drift", "rim_linear": "rim_stiffening"}
EXPECTED = {**TUNING, **SCORED}
PATHS = ("contact-law", "output", "fe")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--paths", nargs="+", choices=PATHS, default=list(PATHS), help="model paths to run")
    p.add_argument("--draws", type=int, default=1, help="test sessions per form and size")
    p.add_argument("--sizes", type=float, nargs="+", default=[1.0, 3.0], help="effect sizes (× the path's floor)")
    p.add_argument("--nulls", type=int, default=10, help="sessions without a hidden effect")
    p.add_argument("--forms", nargs="+", choices=sorted(EXPECTED), help="hidden forms (default: the scored set)")
    p.add_argument("--tuning", action="store_true", help="the tuning forms instead of the scored ones")
    p.add_argument("--fe-physics", choices=("fe", "hertz-fallback"), default="fe",
                   help="what solves the FE path: tools.fe (default) or the recipe's analytic stand-in")
    p.add_argument("--world", choices=sorted(WORLDS), default="analytic",
                   help="the twin physics the sessions are recorded with: analytic contact (default) or the twin's FE")
    p.add_argument("--fe-pokes", type=int, default=FE_POKES, help="pokes per session on the FE path")
    p.add_argument("--model", default=None,
                   help="the model package of the output path (default: the runtime's, the newest installed)")
    p.add_argument("--mde-target", type=float, default=None,
                   help="when a test session (case or null) shows nothing significant and its minimum detectable "
                        "effect is above this many times its floor, record more sessions of the unit and diagnose "
                        "them together, as many as the diagnosis asks for (default: off, one session)")
    p.add_argument("--max-sessions", type=int, default=MAX_SESSIONS,
                   help="with --mde-target: at most this many sessions diagnosed together")
    p.add_argument("--no-own-error", action="store_true", help="diagnose against the model alone")
    p.add_argument("--raw-nulls", nargs="*", choices=PATHS, default=["output"],
                   help="on these paths also diagnose each null against the model alone (the own error's effect)")
    p.add_argument("--work", help="work folder (default: cache/workbench/paths)")
    p.add_argument("--progress", help="append one line per finished row here")
    p.add_argument("--out", help="write every row and the summary as JSON here")
    p.add_argument("--summarize", action="store_true", help="only summarize the rows in the work folder")
    p.add_argument("--markdown", action="store_true", help="with --summarize: the docs' table and case list")
    p.add_argument("--reverse", action="store_true", help="take the rows last to first (a second run on the "
                   "same work folder then meets the first one in the middle)")


def _rms(x) -> float:
    x = np.asarray(x)
    return float(np.sqrt(np.mean(np.sum(x ** 2, axis=1)))) if len(x) else float("nan")


def record(sc):
    """The scenario's session (tools.workbench.scenarios.record), under a lock per scenario: runs of
    this harness on different paths share their recordings and may meet on one."""
    import fcntl

    from ..workbench.scenarios import record as _record
    from ..workbench.scenarios import root

    root().mkdir(parents=True, exist_ok=True)
    with open(root() / f".lock-{sc.key()}", "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        return _record(sc)


WORLDS = {"analytic": "hertz-fallback", "fe": "fe"}   # --world: the twin physics the sessions are recorded with


def _scenario(seed: int, unit: str, path: str = "output", world: str = "analytic", fe_pokes: int = FE_POKES):
    """The recording of `seed` on `unit` for `path` (the FE path's are shorter, `fe_pokes` pokes, with
    seeds of their own) in `world` (WORLDS)."""
    from ..workbench.scenarios import Scenario

    if path == "fe":
        return Scenario(seed + FE_SEED_OFFSET, pokes=fe_pokes, unit=unit, model_size=128, physics=WORLDS[world])
    return Scenario(seed, pokes=POKES, unit=unit, model_size=128, physics=WORLDS[world])


def sessions_needed(mde: dict | None, n: int, target: float | None, max_n: int = MAX_SESSIONS) -> int | None:
    """How many sessions like the `n` diagnosed together the diagnosis needs for its minimum
    detectable effect (`mde`: its `tools.workbench.mde` result) to come down to `target` × its floor,
    as its "record N more presses" line computes it: the statistical bar falls as 1/sqrt(presses).
    None when it already does, when the practical bar (which more presses do not lower) is above the
    target, or when no more sessions are allowed."""
    if target is None or not mde or not mde.get("floor"):
        return None
    goal = target * mde["floor"]
    if mde["mde"] <= goal or mde["practical"] > goal:
        return None
    new = min(max_n, int(np.ceil(n * (mde["statistical"] / goal) ** 2)))
    return new if new > n else None


def units_of(path: str) -> tuple:
    return FE_UNITS if path == "fe" else UNITS


def case_unit(path: str, form: str, draw: int) -> str:
    u = units_of(path)
    return u[(list(EXPECTED).index(form) + draw) % len(u)]


class PathLab:
    """One unit on one model path: its store, model, own error; tables of (altered) sessions."""

    def __init__(self, path: str, unit: str, work: Path, model_dir: str, own: bool = True,
                 fe_physics: str = "fe", world: str = "analytic", fe_pokes: int = FE_POKES):
        from ...contracts.store import CalibrationStore
        from ...runtime.stages.effects import Registry
        from ..workbench.scenarios import store_root

        self.path, self.unit, self.work, self.fe_physics, self.world = path, unit, Path(work), fe_physics, world
        self.fe_pokes = fe_pokes
        self.fe: dict = {}
        self.store = CalibrationStore(store_root(unit, 128))
        self.cal = self.store.load(unit)
        self.reg = Registry.default(entry_points=False)
        self.gel = _gel_128(unit)
        self.loaded: dict = {}
        self.calib = [record(self.scenario(s + UNITS.index(unit))) for s in CALIB_SEEDS]
        if path == "contact-law":
            self.law = self._law()
        if path == "output":
            from ...runtime.stages.model import find_package
            from ..workbench.network import NetworkConfig, NetworkModel

            package = find_package(model_dir)
            self.model_name = package.name
            self.net = NetworkModel(package, NetworkConfig())
        self.own = self._own() if own else None

    def _law(self):
        from ..workbench.compare import load_table
        from ..workbench.models import ContactLaw

        f = self.work / f"law-{self.unit}{self.tag()}.json"
        if f.is_file():
            return ContactLaw.load(f)
        law = ContactLaw.fit_sessions([load_table(c, self.cal)[0] for c in self.calib], self.calib)
        law.save(f)
        return law

    def _own(self):
        from ..workbench.diagnose import DiagnoseConfig, blocks_of
        from ..workbench.own_error import OwnError

        f = self.work / f"own-{self.path}-{self.unit}{'-' + self.fe_physics if self.path == 'fe' else ''}{self.tag()}.json"
        if f.is_file():
            return OwnError.from_json(json.loads(f.read_text()))
        parts = []
        for c in self.calib:
            t, _ = self.table(c)
            parts.append((t.cov(), t.model, t.meas, blocks_of(t, DiagnoseConfig())[0]))
        own = OwnError.fit(parts, source="calibration sessions " + ", ".join(Path(c).name for c in self.calib))
        from ...contracts.files import atomic_write_json

        atomic_write_json(f, own.to_json())
        return own

    def scenario(self, seed: int):
        return _scenario(seed, self.unit, self.path, self.world, self.fe_pokes)

    def tag(self) -> str:
        """File-name tag of the world and the FE path's session length (none for the defaults, whose
        files came first)."""
        return variant_tag(self.path, self.world, self.fe_pokes)

    def session(self, base: Path):
        from ...contracts.session import load_session

        if base not in self.loaded:
            self.loaded[base] = load_session(base, check_frames=False)
        return self.loaded[base]

    def table(self, base: Path, form: str | None = None, amp: float = 0.0):
        """(table with the path's raw prediction in `model`, the unaltered session's measured force on
        the same rows); the FE path is solved at the recording's keypoints (module docstring)."""
        from ..workbench.compare import load_table
        from .alter_forms import altered_session

        base = Path(base)
        t0 = load_table(base, self.cal)[0]
        if form:
            ses = altered_session(self.session(base), form, amp, self.gel)
            tb = load_table(base, self.cal, cache=False, session=ses)[0]
        else:
            ses, tb = None, t0
        if self.path == "contact-law":
            return tb.with_model(self.law.predict(tb)), t0.meas
        if self.path == "output":
            from ..workbench.compare import cache_root

            net = cache_root() / "net"
            clean = self.net.build_table(self.session(base), self.cal, t0, None, net)
            t = self.net.build_table(ses, self.cal, tb, None, net) if form else clean
            return t, clean.meas
        from ..workbench.fe_path import FEModel, take_rows

        if base not in self.fe:
            self.fe[base] = FEModel(base, self.cal.meta, self.fe_physics, session=self.session(base))
        pred = self.fe[base].predict(tb)
        keep = np.all(np.isfinite(pred), axis=1)
        return take_rows(tb.with_model(pred), keep), t0.meas[keep]

    def post(self, table, chain=None):
        return self.own.post(table.cov()) if self.own is not None else None

    def base(self, table, chain=None) -> np.ndarray:
        from ...runtime.stages.effects import EffectChain
        from ..workbench.fit import Channels

        return Channels(table, chain or EffectChain(), self.post(table)).base_force

    def diagnose(self, table, own: bool = True):
        from ..workbench.diagnose import diagnose

        return diagnose(table, self.reg, None, post=self.post(table) if own else None)


def variant_tag(path: str, world: str, fe_pokes: int) -> str:
    """File-name tag of a run's world and (FE path) session length; empty for the defaults."""
    return (("" if world == "analytic" else f"-world-{world}")
            + (f"-pokes{fe_pokes}" if path == "fe" and fe_pokes != FE_POKES else ""))


def _gel_128(unit: str) -> dict:
    from ...contracts.store import CalibrationStore
    from ..workbench.scenarios import store_root

    gel = CalibrationStore(store_root(unit, 128)).load(unit).meta["gel"]
    return {"radius": gel["radius_mm"], "center_z": gel["center_z_mm"], "skirt": gel["skirt_mm"]}


def _diag(d) -> dict:
    """The twin-generality harness's row of a diagnosis, with the path's floor beside its MDE."""
    from .twin_generality import _diag_row

    return {**_diag_row(d), "diag_floor": d.mde["floor"] if d.mde else None}


def pooled(diagnosed, target: float | None, max_n: int = MAX_SESSIONS):
    """`diagnosed(n)`: the diagnosis of the first n sessions of a unit pooled (`pool_tables`). Starts
    with one; while it finds nothing significant and asks for more sessions (`sessions_needed`), at
    most twice, diagnoses that many together. Returns (the last diagnosis, its sessions, {"first": the
    first diagnosis} or {} with one session)."""
    n, d, first = 1, diagnosed(1), {}
    for _ in range(2):
        more = sessions_needed(d.mde, n, target, max_n) if d.verdict is None else None
        if more is None:
            break
        if not first:
            f = _diag(d)
            first = {"first": {"sessions": 1, **{k: f[k] for k in ("verdict", "p", "mde", "diag_floor")}}}
        n = more
        d = diagnosed(n)
    return d, n, first


def _sized(lab: PathLab, base: Path, form: str, size: float):
    """(floor, amplitude, altered table, its clean force, the effect's rms contribution) of `form` put
    into session `base` at `size` × the path's floor there."""
    t0, _ = lab.table(base)
    floor = _rms(t0.meas - lab.base(t0))
    t1, clean = lab.table(base, form, 1.0)
    amp = size * floor / max(_rms(t1.meas - clean), 1e-12)
    t, clean = lab.table(base, form, amp)
    return floor, amp, t, clean, _rms(t.meas - clean)


def run_case(lab: PathLab, form: str, size: float, draw: int, mde_target: float | None = None,
             max_sessions: int = MAX_SESSIONS) -> dict:
    """One hidden form at `size` × the floor of its test session. With `mde_target`, when that
    session's diagnosis finds nothing and could not have seen effects of `mde_target` × its floor,
    more sessions of the unit with the same effect (seeds + MORE_SEED·k) are diagnosed together, as
    many as the diagnosis asks (`pooled`)."""
    from ...runtime.stages.effects import EffectChain, EnabledEffect
    from ..workbench.models import pool_tables

    i = list(EXPECTED).index(form)
    seed = TEST_SEED + 10 * i + draw
    floor, amp, t, clean, size_n = _sized(lab, record(lab.scenario(seed)), form, size)
    tables = [(t, clean)]

    def diagnosed(n: int):
        while len(tables) < n:
            tables.append(lab.table(record(lab.scenario(seed + MORE_SEED * len(tables))), form, amp))
        return lab.diagnose(pool_tables([x for x, _ in tables[:n]]) if n > 1 else t)

    d, n, first = pooled(diagnosed, mde_target, max_sessions)
    row = {"path": lab.path, "form": form, "unit": lab.unit, "draw": draw, "size_floor": size, "floor": floor,
           "size_n": size_n, "amp": amp, "rows": len(t), "sessions": n, **_diag(d), **first}
    if n > 1:
        row["rows_pooled"] = int(sum(len(x) for x, _ in tables[:n]))
        row["size_n_pooled"] = _rms(np.concatenate([x.meas - c for x, c in tables[:n]]))
    if form in MULTIPLICATIVE:
        loaded = np.linalg.norm(clean, axis=1) >= 0.2
        g = gain_of(t.meas, clean)[loaded]
        row["gain_range"] = [float(g.min()), float(g.max())] if len(g) else None
    fam = EXPECTED[form]
    if fam == "phi":
        row["right"] = bool(row["verdict"] is None and row["top_covariate"] == "phi" and (row["covariate_p"] or 1) <= 0.05)
    else:
        row["right"] = bool(row["family"] == fam and not row["pair"])
    v = d.verdict
    if v is not None and v.pair is None and v.channel == "force":
        second = record(lab.scenario(SECOND_SEED + 10 * i + draw))
        a2, clean2 = lab.table(second, form, amp)
        chain = EffectChain([EnabledEffect(v.effect, dict(v.params))])
        base2 = lab.base(a2)
        before, after = _rms(a2.meas - base2), _rms(a2.meas - lab.base(a2, chain))
        unaltered = _rms(clean2 - base2)
        # the hidden form itself put on the model side: what an exact model of the effect leaves
        # (a gain also scales the model's own error, so this is above `unaltered`)
        ideal = _rms(a2.meas - (base2 * gain_of(a2.meas, clean2)[:, None] if form in MULTIPLICATIVE
                                else base2 + (a2.meas - clean2)))
        row.update({"second_before": before, "second_after": after, "second_unaltered": unaltered,
                    "second_ideal": ideal, "removed": (before - after) / max(before - unaltered, 1e-12),
                    "removed_of_removable": (before - after) / max(before - ideal, 1e-12)})
    return row


GAIN_RANGE = (0.5, 4.0)   # a hidden gain outside this on the loaded rows is no gel's correction


def physical(row: dict) -> bool:
    """Whether a case's hidden effect is one a gel could have: a multiplicative form's gain on the rows
    with |F| >= 0.2 N within GAIN_RANGE (the library's stiffening families reach a gain of 4; a sensor
    reading half or a quarter of the force is broken, not uncorrected). Scaling a form to a multiple of
    a high floor can ask for more (a rim 12 times as stiff as the apex)."""
    g = row.get("gain_range")
    return g is None or (GAIN_RANGE[0] <= g[0] and g[1] <= GAIN_RANGE[1])


def null_sessions(path: str, forms: list, draws: int, n: int) -> list[tuple[str, int, str]]:
    """The path's n nulls as (name, seed, unit): the cases' test and second sessions before their
    effect is put in, then sessions of new plans."""
    out = []
    for d in range(draws):
        for f in forms:
            i, u = list(EXPECTED).index(f), case_unit(path, f, d)
            out += [(f"test{TEST_SEED + 10 * i + d}", TEST_SEED + 10 * i + d, u),
                    (f"second{SECOND_SEED + 10 * i + d}", SECOND_SEED + 10 * i + d, u)]
    units = units_of(path)
    k = 0
    while len(out) < n:
        out.append((f"new{NULL_SEED + k}", NULL_SEED + k, units[k % len(units)]))
        k += 1
    return out[:n]


def run_null(lab: PathLab, name: str, seed: int, raw: bool = True, mde_target: float | None = None,
             max_sessions: int = MAX_SESSIONS) -> dict:
    """One session without a hidden effect, with more sessions of its unit pooled as `run_case` pools
    a case's (`pooled`)."""
    from ..workbench.models import pool_tables

    tables = [lab.table(record(lab.scenario(seed)))[0]]
    last: dict = {}

    def diagnosed(n: int):
        while len(tables) < n:
            tables.append(lab.table(record(lab.scenario(seed + MORE_SEED * len(tables))))[0])
        last["t"] = pool_tables(tables[:n]) if n > 1 else tables[0]
        return lab.diagnose(last["t"])

    d, n, first = pooled(diagnosed, mde_target, max_sessions)
    t = last["t"]
    row = {"path": lab.path, "null": name, "seed": seed, "unit": lab.unit, "floor": _rms(t.meas - lab.base(t)),
           "rows": len(t), "sessions": n, **_diag(d), **first}
    if lab.own is not None and raw:
        raw = _diag(lab.diagnose(t, own=False))
        row["without_own_error"] = {k2: raw[k2] for k2 in ("verdict", "p", "best", "best_p", "top_covariate",
                                                           "covariate_p", "diag_floor", "mde")}
    return row


def summarize(rows: list, forms_set: str = "scored") -> dict:
    """Per model path (the FE path per solver): the acceptance counts over the cases of one form set
    ("scored" or "tuning") and every null."""
    out = {}
    def key(r):
        return (r.get("world", "analytic"), r["path"], r.get("fe_physics") or "", r.get("fe_pokes", FE_POKES),
                r.get("mde_target") or 0.0, r.get("model") or "")

    for world, path, fe, fe_pokes, target, model in sorted({key(r) for r in rows}):
        mine = [r for r in rows if key(r) == (world, path, fe, fe_pokes, target, model)]
        cases = [r for r in mine if "form" in r and r.get("set") == forms_set]
        nulls = [r for r in mine if "null" in r]
        if not cases and not nulls:
            continue
        path = ((f"{path} ({fe}{'' if fe_pokes == FE_POKES else f', {fe_pokes}-poke sessions'})" if fe else path)
                + ("" if world == "analytic" else f" [{world} world]")
                + (f" [sessions pooled to an MDE of {target:g}× the floor]" if target else "")
                + (f" [{model}]" if model else ""))
        big = [r for r in cases if r["size_floor"] >= 1.0]
        removed = [r["removed"] for r in big if r["right"] and "removed" in r]
        lib = [r for r in big if EXPECTED[r["form"]] != "phi"]
        floors = [r["floor"] for r in cases + nulls]
        out[path] = {
            "floor_n": [float(np.min(floors)), float(np.max(floors))] if floors else None,
            "mde_n": [float(np.nanmin([r["mde"] or np.nan for r in nulls])),
                      float(np.nanmax([r["mde"] or np.nan for r in nulls]))] if nulls else None,
            "right_at_or_above_floor": f"{sum(r['right'] for r in big)}/{len(big)}",
            "right_library_forms": f"{sum(r['right'] for r in lib)}/{len(lib)}",
            # the cases the session could show at all: the effect at least the MDE the diagnosis reported
            "right_at_or_above_mde": (f"{sum(r['right'] for r in big if r['mde'] and r['size_n'] >= r['mde'])}/"
                                      f"{sum(bool(r['mde']) and r['size_n'] >= r['mde'] for r in big)}"),
            "size_over_mde": {f"{r['form']}-{r['size_floor']:g}": round(r["size_n"] / r["mde"], 2)
                              for r in big if r["mde"]},
            "per_form": {f: f"{sum(r['right'] for r in big if r['form'] == f)}/{sum(r['form'] == f for r in big)}"
                         for f in EXPECTED if any(r["form"] == f for r in big)},
            "removed_at_least_70": f"{sum(x >= 0.7 for x in removed)}/{len(removed)}",
            "removed_of_removable_at_least_70": (
                f"{sum(r['removed_of_removable'] >= 0.7 for r in big if r['right'] and 'removed_of_removable' in r)}/"
                f"{sum(r['right'] and 'removed_of_removable' in r for r in big)}"),
            "physical_cases": f"{sum(physical(r) for r in big)}/{len(big)}",
            "right_physical": f"{sum(r['right'] for r in big if physical(r))}/{sum(physical(r) for r in big)}",
            "removed_at_least_70_physical": (
                f"{sum(r['removed'] >= 0.7 for r in big if physical(r) and r['right'] and 'removed' in r)}/"
                f"{sum(physical(r) and r['right'] and 'removed' in r for r in big)}"),
            "removed_median": float(np.median(removed)) if removed else None,
            "null_false_alarms": f"{sum(n['verdict'] is not None for n in nulls)}/{len(nulls)}",
            "null_false_alarms_without_own_error": (
                f"{sum(n['without_own_error']['verdict'] is not None for n in nulls if 'without_own_error' in n)}/"
                f"{sum('without_own_error' in n for n in nulls)}")}
    return out


def _variant(r: dict) -> tuple[str, str]:
    """(world, path label) of a row, the FE path with its solver and session length."""
    path = r["path"]
    if path == "fe":
        path = f"fe ({r.get('fe_physics')}, {r.get('fe_pokes', FE_POKES)}-poke)"
    if r.get("model"):
        path += f" ({r['model']})"
    if r.get("mde_target"):
        path += f", sessions pooled to MDE ≤ {r['mde_target']:g}× floor"
    return r.get("world", "analytic"), path


def _frac(items: list, ok) -> str:
    return f"{sum(bool(ok(r)) for r in items)} / {len(items)}"


def _span(x: list) -> str:
    return f"{min(x):.3f}–{max(x):.3f}" if x else "—"


def markdown(rows: list, forms_set: str = "scored") -> str:
    """The docs' table (one line per world and path: floors, MDE on nulls, right verdicts at 1x / 3x
    the floor and at >= the MDE, >= 70 % removed and, in brackets, >= 70 % of the exact form's own
    removal, false alarms with and without the own error), then one line per case."""
    groups: dict = {}
    for r in rows:
        groups.setdefault(_variant(r), []).append(r)
    table, lines = [], []
    for (world, path), mine in sorted(groups.items()):
        cases = [r for r in mine if "form" in r and r.get("set") == forms_set]
        nulls = [r for r in mine if "null" in r]
        rem = [r for r in cases if r["right"] and "removed" in r]
        raw = [n for n in nulls if "without_own_error" in n]
        table.append("| " + " | ".join([
            world, path, _span([r["floor"] for r in cases + nulls]), _span([r["mde"] for r in nulls if r.get("mde")]),
            _frac([r for r in cases if r["size_floor"] == 1], lambda r: r["right"]),
            _frac([r for r in cases if r["size_floor"] == 3], lambda r: r["right"]),
            _frac([r for r in cases if r.get("mde") and r["size_n"] >= r["mde"]], lambda r: r["right"]),
            f"{_frac(rem, lambda r: r['removed'] >= 0.7)} ({_frac(rem, lambda r: r['removed_of_removable'] >= 0.7)})",
            _frac(nulls, lambda n: n["verdict"] is not None),
            _frac(raw, lambda n: n["without_own_error"]["verdict"] is not None) if raw else "—"]) + " |")
        for r in sorted(cases, key=lambda r: (r["form"], r["size_floor"], r.get("draw", 0))):
            g = r.get("gain_range")
            verdict = ((r["verdict"] + (" with a second effect (a pair)" if r.get("pair") else "")
                        + f" p = {r['p']:.2g}") if r["verdict"]
                       else f"none (best {r.get('best')}, p = {r.get('best_p') or 0:.2g})")
            removed = (f", removed {100 * r['removed']:.0f} % ({100 * r['removed_of_removable']:.0f} % of the exact "
                       "form's)" if "removed" in r else "")
            lines.append(f"- {world}, {path}, {r['form']} {r['size_floor']:g}× ({r['size_n']:.3f} N, MDE "
                         f"{r['mde'] or 0:.3f} N, {r['unit']}{f', gain {g[0]:.2f}–{g[1]:.2f}' if g else ''}): "
                         f"{verdict}{removed}{'' if r['right'] else ' — wrong/missed'}"
                         + (f"; {r['sessions']} sessions together (one alone: MDE {r['first']['mde'] or 0:.3f} N, "
                            f"{r['first']['verdict'] or 'no verdict'})" if r.get("first") else ""))
    return "\n".join(table + [""] + lines) + "\n"


def run(a: argparse.Namespace) -> int:
    from ...contracts import paths
    from ...contracts.files import atomic_write_json

    logging.basicConfig(level=logging.WARNING)
    work = Path(a.work) if a.work else paths.cache_dir() / "workbench" / "paths"
    (work / "rows").mkdir(parents=True, exist_ok=True)
    forms = a.forms or list(TUNING if a.tuning else SCORED)
    prog = Path(a.progress) if a.progress else None

    def note(text: str) -> None:
        if prog is not None:
            with open(prog, "a") as fh:
                fh.write(f"{time.strftime('%H:%M:%S')} {text}\n")

    rows = []
    if not a.summarize:
        labs: dict = {}
        per = [(s, d, f) for s in sorted(a.sizes) for d in range(a.draws) for f in forms]
        tasks = []                 # cases and nulls interleaved, the paths taking turns
        nulls = {p: null_sessions(p, forms, a.draws, a.nulls) for p in a.paths}
        for k in range(max(a.nulls, len(per))):
            for path in a.paths:
                if k < len(per):
                    tasks.append((path, "case", per[k]))
                if k < len(nulls[path]):
                    tasks.append((path, "null", nulls[path][k]))
        for path, kind, arg in (tasks[::-1] if a.reverse else tasks):
            tag = ((f"-{a.fe_physics}" if path == "fe" else "") + variant_tag(path, a.world, a.fe_pokes)
                   + (f"-mde{a.mde_target:g}" if a.mde_target is not None else ""))
            name = (f"{path}{tag}-null-{arg[0]}" if kind == "null" else f"{path}{tag}-case-{arg[2]}-{arg[0]:g}-{arg[1]}")
            f = work / "rows" / f"{name}.json"
            if f.is_file():
                continue
            unit = arg[2] if kind == "null" else case_unit(path, arg[2], arg[1])
            t0 = time.perf_counter()
            try:
                if (path, unit) not in labs:
                    labs[path, unit] = PathLab(path, unit, work, a.model, own=not a.no_own_error,
                                               fe_physics=a.fe_physics, world=a.world, fe_pokes=a.fe_pokes)
                lab = labs[path, unit]
                row = (run_null(lab, arg[0], arg[1], path in (a.raw_nulls or []), a.mde_target, a.max_sessions)
                       if kind == "null" else run_case(lab, arg[2], arg[0], arg[1], a.mde_target, a.max_sessions))
                row["set"] = "null" if kind == "null" else ("tuning" if arg[2] in TUNING else "scored")
                if path == "fe":
                    row["fe_physics"], row["fe_pokes"] = a.fe_physics, a.fe_pokes
                row["world"] = a.world
                if a.mde_target is not None:
                    row["mde_target"] = a.mde_target
                if path == "output":
                    row["model"] = lab.model_name
            except Exception as exc:    # a row that fails is reported, the run goes on
                log.exception("%s failed", name)
                note(f"{name}: FAILED {type(exc).__name__}: {exc}")
                continue
            row["seconds"] = time.perf_counter() - t0
            atomic_write_json(f, json.loads(json.dumps(row, default=float)))
            note(f"{name}: verdict {row['verdict']} right {row.get('right', '-')} floor {row['floor']:.4g} "
                 f"removed {row.get('removed', '-')} ({row['seconds']:.0f} s)")
            print(json.dumps(row, default=float), flush=True)
    rows = [json.loads(f.read_text()) for f in sorted((work / "rows").glob("*.json"))]
    if a.markdown:
        print(markdown(rows, "tuning" if a.tuning else "scored"), end="")
        return 0
    summary = summarize(rows, "tuning" if a.tuning else "scored")
    print(json.dumps(summary, indent=1))
    note("summary " + json.dumps(summary))
    if a.out:
        atomic_write_json(a.out, json.loads(json.dumps({"rows": rows, "summary": summary}, default=float)), indent=1)
    return 0
