"""Model paths: what "the model" is in a comparison, and what each can see.

    output       the sensor's output: the deployed network -> enabled effects -> correction (the
                 runtime's own code over the session's frames)
    contact-law  the physics at the measured keypoints: the nominal contact law of each indenter,
                 fitted on several calibration sessions that together cover the indenters
    fe           the physics at the measured keypoints: FE solved at the session's own keypoints by
                 the training recipe's resolve stage (fe_path.py); its floor is the label error

Each path is compared and diagnosed the same way (compare.py, diagnose.py); its **floor** (the
held-out error left with the best candidate in) and its **minimum detectable effect** (mde.py)
say which effects it can see. With `own_error` (own_error.py, fitted on clean calibration sessions
of the same path) a path is diagnosed against the model's own residual structure: only what is new
is reported. `floors_lines` prints the paths side by side.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from ...contracts.errors import TensorTouchError

log = logging.getLogger(__name__)

PATHS = ("output", "contact-law", "fe")


@dataclass
class PathResult:
    path: str
    comparison: object
    diagnosis: object = None
    own_error: object = None
    notes: list = field(default_factory=list)

    @property
    def rms(self) -> float:
        return float(self.comparison.summary["force_error"]["rms_vector"])

    def floor(self) -> float | None:
        m = self.diagnosis.mde if self.diagnosis is not None else None
        return float(m["floor"]) if m else None

    def mde(self) -> float | None:
        m = self.diagnosis.mde if self.diagnosis is not None else None
        return float(m["mde"]) if m else None

    def to_json(self) -> dict:
        d = self.diagnosis
        out = {"path": self.path, "model": self.comparison.summary.get("model", {}).get("name"),
               "rms_vector": self.rms, "n_samples": int(len(self.comparison.table)),
               "floor": self.floor(), "mde": self.mde(), "notes": self.notes}
        if d is not None:
            v = d.verdict
            out.update({"verdict": v.effect.name if v else None, "p": float(v.p_adjusted) if v else None,
                        "best": d.ranking[0].effect.name if d.ranking else None,
                        "best_p": float(d.ranking[0].p_adjusted) if d.ranking else None})
        if self.own_error is not None:
            out["own_error"] = {"describe": self.own_error.describe(), **self.own_error.heldout}
        return out


def fe_comparison(session, sensor, store, registry, physics: str, cache: bool = True):
    """compare on the FE path: the rows the recipe's solved periods cover."""
    from .compare import compare_table, run_compare
    from .fe_path import FEModel, covered_rows, take_rows

    cal = store.load(sensor)
    model = FEModel(session, cal.meta, physics)
    comp = run_compare(session, sensor, store, model, registry, cache=cache)
    keep = covered_rows(comp.table, comp.table.model)
    sub = compare_table(take_rows(comp.table, keep), comp.chain)
    sub.folder = comp.folder
    sub.summary.update({k: v for k, v in comp.summary.items() if k not in sub.summary})
    sub.summary["fe_rows"] = {"covered": int(keep.sum()), "of": int(len(keep)), "periods": len(model.periods)}
    return sub


def own_error_parts(comparisons: list) -> list:
    """[(cov, deployed prediction, measured, blocks)] of clean calibration comparisons (own_error.fit)."""
    from .diagnose import DiagnoseConfig, blocks_of
    from .fit import Channels

    parts = []
    for c in comparisons:
        ch = Channels(c.table, c.chain, c.post)
        parts.append((ch.cov, ch.base_force, c.table.meas, blocks_of(c.table, DiagnoseConfig())[0]))
    return parts


def fit_own_error(comparisons: list, sources: list):
    from .own_error import OwnError

    return OwnError.fit(own_error_parts(comparisons), source="fitted on " + ", ".join(str(s) for s in sources))


def diagnose_path(comp, registry, own_error=None, cfg=None, baseline=None):
    """The diagnosis of one comparison, against the model's own error when `own_error` is given."""
    from .diagnose import diagnose

    post = comp.post
    if own_error is not None:
        post = own_error.post(comp.table.cov(), comp.post)
    return diagnose(comp.table, registry, comp.chain, cfg, post=post, baseline=baseline)


def floors_lines(results: list[PathResult]) -> list[str]:
    """The paths side by side: rows, rms error, floor, MDE, verdict."""
    lines = [("model paths (floor = held-out error with the best candidate in; MDE = the smallest effect this "
             "session could have shown on that path):"),
             f"  {'path':12s} {'rows':>6s} {'rms |r| N':>10s} {'floor N':>9s} {'MDE N':>9s}  verdict"]
    for r in results:
        f, m = r.floor(), r.mde()
        d = r.diagnosis
        v = d.verdict if d is not None else None
        verdict = (f"{v.effect.name} (p = {v.p_adjusted:.2g})" if v else
                   f"none (best {d.ranking[0].effect.name}, p = {d.ranking[0].p_adjusted:.2g})" if d and d.ranking
                   else "—")
        lines.append(f"  {r.path:12s} {len(r.comparison.table):6d} {r.rms:10.4f} "
                     f"{f if f is not None else float('nan'):9.4f} {m if m is not None else float('nan'):9.4f}  {verdict}")
        for n in r.notes:
            lines.append(f"  {'':12s} {n}")
    ok = [r for r in results if r.mde() is not None]
    if len(ok) > 1:
        best = min(ok, key=lambda r: r.mde())
        lines.append(f"  an effect of size s N is within reach of the paths whose MDE is below s; the {best.path} "
                     f"path sees the smallest ({best.mde():.3g} N)")
    return lines


def run_paths(args, paths: list[str], with_diagnosis: bool = True) -> list[PathResult]:
    """Shell: compare (and diagnose) the session on each path the user asked for."""
    from types import SimpleNamespace

    from .cli_common import compare_session, registry_of, sensor_of, store_of

    sensor = sensor_of(args)
    store = store_of(args)
    registry = registry_of(args)
    out = []
    for path in paths:
        if path not in PATHS:
            raise TensorTouchError(f"--paths: {path!r}, expected one of {', '.join(PATHS)}")
        own_from = getattr(args, "own_error_from", None) or []
        if path == "fe":
            comp = fe_comparison(args.session, sensor, store, registry, getattr(args, "fe_physics", "fe"),
                                 cache=not args.no_cache)
            calib = [fe_comparison(s, sensor, store, registry, getattr(args, "fe_physics", "fe"),
                                   cache=not args.no_cache) for s in own_from]
        else:
            sub = SimpleNamespace(**vars(args))
            sub.model = "contact-law" if path == "contact-law" else (
                None if args.model in (None, "contact-law") or str(args.model).endswith(".json") else args.model)
            if path == "output":
                sub.model_from = None
            comp = compare_session(sub, store, sensor)
            if path == "output" and comp.summary["model"]["name"] == "contact-law":
                raise TensorTouchError(f"{args.session}: the output path needs the network (a model package made "
                                       "for the calibration's size and a session with frames); give --model PATH|NAME")
            sub.model_from, sub.correction_from = None, None   # fitted once, above
            calib = []
            for s in own_from:
                sub.session = s
                calib.append(compare_session(sub, store, sensor))
        res = PathResult(path, comp)
        if own_from:
            res.own_error = fit_own_error(calib, own_from)
            res.notes.append(f"own error ({res.own_error.describe()}) fitted on {len(own_from)} clean session(s): "
                             f"held-out {res.own_error.heldout['rms_before']:.4g} -> "
                             f"{res.own_error.heldout['rms_after']:.4g} N")
        if path == "fe":
            fr = comp.summary["fe_rows"]
            res.notes.append(f"FE at the measured keypoints: {fr['periods']} periods solved, "
                             f"{fr['covered']} of {fr['of']} rows")
        if with_diagnosis:
            res.diagnosis = diagnose_path(comp, registry, res.own_error)
        out.append(res)
    return out


def session_name(p) -> str:
    return Path(p).name
