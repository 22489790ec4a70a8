"""`tensortouch compare | diagnose | effects` — the physics workbench (thin shell).

    tensortouch compare SESSION --sensor ID --out DIR [--model-from CALIB_SESSION] [--before-after [DIR]]
    tensortouch diagnose SESSION --sensor ID [--json]
    tensortouch effects list [--json]
    tensortouch effects add NAME --sensor ID [--from-diagnosis [FILE]] [--param p=v ...]
    tensortouch effects remove NAME --sensor ID
    tensortouch accept workbench-synthetic-generality [--draws 3] [--sizes 0.3 1 3] [--nulls 10]   (generality.py)

The model side: the deployed network (`--model PATH|NAME`, default: the installed model package when
the sensor's calibration is made for its input size and the session has frames) run over the
session's frames through the runtime's code, with the sensor's enabled effects and correction; or
the nominal contact law (`--model contact-law` / a JSON file; `--model-from CALIB_SESSION` fits it
and makes it the sensor's default). `--correction-from CALIB_SESSION` fits and stores the sensor's
correction for the network on a calibration session. Effect plugins: `--plugins DIR` (repeatable), the
TENSORTOUCH_EFFECTS_PATH folders and the `tensortouch.effects` entry points. The effects commands
live in effects_cli.py, the pieces both share (store, registry, sensor, model) in cli_common.py.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

from ...contracts.files import atomic_write_json
from .cli_common import compare_session, last_diagnosis_path, registry_of, session_args
from .effects_cli import register_effects

log = logging.getLogger(__name__)


def _model_args(p) -> None:
    p.add_argument("--model", metavar="PATH|NAME|contact-law",
                   help="the model: a model package (folder or name under exported_models/; default: the "
                        "installed one when the calibration matches its size and the session has frames), "
                        "'contact-law' (the sensor's stored nominal contact law) or a contact-law JSON file")
    p.add_argument("--precision", choices=("int8", "fp32"), default="int8", help="network precision (default int8)")
    p.add_argument("--model-from", metavar="CALIB_SESSION", nargs="+", action="extend",
                   help="contact law: fit it on these calibration sessions (together they must press with every "
                        "indenter the compared sessions use) and make it the sensor's default")
    p.add_argument("--correction-from", metavar="CALIB_SESSION", nargs="+", action="extend",
                   help="network: fit the sensor's force correction (zero-constrained gain forest, as "
                        "`tensortouch recalibrate` stores) on these calibration sessions (several short "
                        "sessions covering the gel are best), store it as a new calibration version, then compare")
    p.add_argument("--no-cache", action="store_true", help="rebuild the sample table and predictions")
    p.add_argument("--paths", nargs="+", metavar="PATH", choices=("output", "contact-law", "fe"),
                   help="compare/diagnose on each of these model paths and print their floors and minimum "
                        "detectable effects side by side: output (network + effects + correction), contact-law "
                        "(the law fitted with --model-from), fe (FE solved at the session's measured keypoints)")
    p.add_argument("--own-error-from", metavar="CALIB_SESSION", nargs="+", action="extend",
                   help="fit the model's own residual structure on these clean calibration sessions and diagnose "
                        "only what is new against it")
    p.add_argument("--fe-physics", choices=("fe", "hertz-fallback"), default="fe",
                   help="fe path: solve with tools.fe (default) or the analytic stand-in (analytic twin units only)")


def register(sub) -> None:
    c = sub.add_parser("compare", help="compare the model with a session's measurements (residuals, report)")
    session_args(c)
    _model_args(c)
    c.add_argument("--out", required=True, help="folder for residuals.csv, summary.json, report.html, PNGs")
    c.add_argument("--before-after", nargs="?", const="", metavar="DIR",
                   help="show the error change against an earlier comparison (default: the one in --out)")
    c.add_argument("--no-pictures", action="store_true", help="write no PNGs (the table and JSON only)")
    c.set_defaults(func=cmd_compare, extra="train")
    d = sub.add_parser("diagnose", help="which physical effect is missing? (blocked CV, significance test)")
    session_args(d)
    _model_args(d)
    d.add_argument("--with", dest="with_sessions", metavar="SESSION", nargs="+", action="extend",
                   help="more sessions of the same sensor, diagnosed together with SESSION: their presses are "
                        "pooled, so the minimum detectable effect falls as 1/sqrt(presses) (what the diagnosis' "
                        "'record N more presses' asks for)")
    d.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    d.add_argument("--blocks", type=int, help="use this many equal time blocks (default: blocks of whole presses, at most 40)")
    d.add_argument("--alpha", type=float, help="family-wise significance level (default 0.05)")
    d.add_argument("--out", help="also write the diagnosis JSON here")
    d.add_argument("--pictures", metavar="DIR", help="write covariates.png (covariate ranking), residual_top.png "
                   "(residual vs the top covariate) and shape.png (the verdict's fitted shape) here")
    d.set_defaults(func=cmd_diagnose, extra="train")
    register_effects(sub)


# ----- commands --------------------------------------------------------------------------------
def cmd_paths(args, diagnosis: bool) -> int:
    from .model_paths import floors_lines, run_paths

    results = run_paths(args, args.paths, with_diagnosis=True)
    for r in results:
        if diagnosis and r.diagnosis is not None:
            print(f"[{r.path}]")
            for line in r.diagnosis.words():
                print("  " + line)
    for line in floors_lines(results):
        print(line)
    from ...contracts.files import atomic_write_json

    per = {}
    for r in results:     # each path's diagnosis, as `effects add --from-diagnosis --path P` reads it
        d = r.diagnosis.to_json()
        d.update({"session": str(Path(args.session).resolve()), "sensor_id": r.comparison.summary["sensor_id"],
                  "path": r.path, "floor": r.floor(), "mde_n": r.mde(),
                  "model_source": r.comparison.summary["model"].get("source", "")})
        if r.own_error is not None:
            d["own_error"] = r.own_error.to_json()
        per[r.path] = d
    found = [r for r in results if r.diagnosis.verdict is not None]
    lead = min(found, key=lambda r: r.mde()) if found else results[0]
    doc = json.loads(json.dumps(dict(per[lead.path], paths=per), default=float))
    atomic_write_json(last_diagnosis_path(results[0].comparison.summary["sensor_id"]), doc, indent=1)
    out = getattr(args, "out", None)
    if out:
        path = Path(out) / "paths.json" if not diagnosis else Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(path, doc, indent=1)
    return 0


def cmd_compare(args) -> int:
    if args.paths:
        return cmd_paths(args, diagnosis=False)
    from .report import write_report
    from .table import write_residuals_csv

    out = Path(args.out)
    previous = None
    if args.before_after is not None:
        prev_dir = Path(args.before_after) if args.before_after else out
        if (prev_dir / "summary.json").is_file():
            previous = json.loads((prev_dir / "summary.json").read_text())
        else:
            print(f"note: no earlier comparison in {prev_dir} (summary.json); nothing to compare against")
    comp = compare_session(args)
    out.mkdir(parents=True, exist_ok=True)
    write_residuals_csv(out / "residuals.csv", comp.table, comp.pred)
    if args.no_pictures:
        (out / "summary.json").write_text(json.dumps(comp.summary, indent=2, default=float))
    else:
        write_report(comp, out, Path(args.session), previous)
    e = comp.summary["force_error"]
    print(f"{comp.summary['n_samples']} samples, effects: "
          f"{', '.join(x['name'] for x in comp.summary['effects']) or 'none'}")
    print(f"force error (N): rms x/y/z {e['rms_x']:.4f}/{e['rms_y']:.4f}/{e['rms_z']:.4f}, "
          f"rms |r| {e['rms_vector']:.4f}, mean ||F|-|F'|| {e['mae_magnitude']:.4f}")
    pe = comp.summary.get("position_error")
    if pe and pe.get("n"):
        print(f"position error (mm): mean |x|/|y|/|z| {pe['mae_x']:.3f}/{pe['mae_y']:.3f}/{pe['mae_z']:.3f} "
              f"over {pe['n']} matched contact samples (detected {100 * comp.summary.get('detected_fraction', 0):.0f} %)")
    if comp.summary.get("network_pass"):
        npass = comp.summary["network_pass"]
        took = "cached" if npass["cached"] else f"{npass['seconds']:.1f} s"
        corr = comp.summary.get("correction")
        print(f"network pass: {took}; correction: {corr.get('kind', 'on') if corr else 'none'}")
    if previous:
        b = previous["force_error"]["rms_vector"]
        print(f"before -> after: rms |r| {b:.4f} -> {e['rms_vector']:.4f} N ({100 * (e['rms_vector'] / b - 1):+.0f} %)")
    print(f"report: {out / 'report.html'}")
    return 0


def cmd_diagnose(args) -> int:
    from dataclasses import replace

    from .diagnose import DiagnoseConfig, diagnose

    if args.paths:
        if args.with_sessions:
            from ...contracts.errors import TensorTouchError

            raise TensorTouchError("--with pools sessions on one model path; drop --paths (or run one path with "
                                   "--model)")
        return cmd_paths(args, diagnosis=True)
    comp = compare_session(args)
    if args.with_sessions:
        comp = pooled_comparison(args, comp)
    cfg = DiagnoseConfig()
    if args.blocks:
        cfg = replace(cfg, n_blocks=args.blocks, blocks="time")
    if args.alpha:
        cfg = replace(cfg, alpha=args.alpha)
    registry = registry_of(args)
    baseline = (store_cal_correction(comp) or {}).get("nominal_reductions")
    post, own = comp.post, None
    if args.own_error_from:
        own = own_error_of(args, comp)
        post = own.post(comp.table.cov(), comp.post)
        print(f"against the model's own error ({own.describe()}; {own.source})")
    diag = diagnose(comp.table, registry, comp.chain, cfg, post=post, baseline=baseline)
    result = diag.to_json()
    result["path"] = "contact-law" if comp.summary["model"]["name"] == "contact-law" else "output"
    result["model_source"] = comp.summary["model"].get("source", "")
    if own is not None:
        result["own_error"] = own.to_json()
    result.update({"session": str(Path(args.session).resolve()), "sensor_id": comp.summary["sensor_id"],
                   "with": [str(Path(s).resolve()) for s in args.with_sessions or []],
                   "enabled": diag.enabled, "n_samples": diag.n_samples, "n_blocks": diag.n_blocks,
                   "seconds": round(diag.seconds, 2)})
    text = json.dumps(result, default=float)
    for path in filter(None, [last_diagnosis_path(comp.summary["sensor_id"]), args.out and Path(args.out)]):
        atomic_write_json(path, result, indent=2, default=float)
    for line in diag.words():
        print(line)
    if args.pictures:
        from .report import covariate_ranking, effect_shape, residual_vs_covariate

        pic = Path(args.pictures)
        pic.mkdir(parents=True, exist_ok=True)
        made = []
        if diag.scan:
            made += [covariate_ranking(diag, pic / "covariates.png"),
                     residual_vs_covariate(comp.table, diag, pic / "residual_top.png")]
        if diag.verdict is not None and diag.verdict.channel == "force" and diag.verdict.pair is None:
            made.append(effect_shape(diag.verdict, comp.table, pic / "shape.png"))
        print(f"pictures in {pic}: {', '.join(made) or 'none'}")
    for line in ranking_lines(diag):
        print(line)
    if args.json:
        print(text)
    return 0


def pooled_comparison(args, comp):
    """`comp` with the rows of every --with session of the same sensor appended (`pool_tables`; each
    session's correction on its own rows), as one comparison to diagnose."""
    from types import SimpleNamespace

    import numpy as np

    from ...contracts.errors import TensorTouchError
    from .models import pool_posts, pool_tables

    more = []
    for s in args.with_sessions:
        sub = SimpleNamespace(**vars(args))
        sub.session, sub.model_from, sub.correction_from = s, None, None
        c = compare_session(sub)
        if c.summary["sensor_id"] != comp.summary["sensor_id"]:
            raise TensorTouchError(f"{s}: sensor {c.summary['sensor_id']!r}, but {args.session} is of "
                                   f"{comp.summary['sensor_id']!r}; --with pools sessions of one sensor")
        more.append(c)
    comps = [comp] + more
    tables, preds, posts = [c.table for c in comps], [c.pred for c in comps], [c.post for c in comps]
    comp.table, comp.pred = pool_tables(tables), np.concatenate(preds)
    comp.post = pool_posts(posts, [len(t) for t in tables])
    print(f"diagnosing {len(comps)} sessions together ({len(comp.table)} rows)")
    return comp


def own_error_of(args, comp):
    """The model's own error fitted on --own-error-from, compared with the same model as `comp`."""
    from types import SimpleNamespace

    from .model_paths import fit_own_error

    calib = []
    for s in args.own_error_from:
        sub = SimpleNamespace(**vars(args))
        sub.session, sub.model_from, sub.correction_from = s, None, None
        calib.append(compare_session(sub))
    return fit_own_error(calib, args.own_error_from)


def ranking_lines(diag) -> list[str]:
    """The ranking as printed: held-out error change in % (negative = the error falls, as in the
    headline), each row in its channel's unit, parameters fitted at a bound flagged."""
    lines = [f"ranking (held-out error before -> after, change; {diag.n_blocks} {diag.block_kind} blocks):"]
    for s in diag.ranking:
        base = f"  (calibration session: {-100 * s.baseline:+.1f} %)" if s.baseline else ""
        bound = f"  at bound: {', '.join(s.at_bounds())}" if s.at_bounds() else ""
        lines.append(f"  {s.effect.name:24s} {s.before:.4g} -> {s.after:.4g} {s.unit:14s} {-100 * s.reduction:+6.1f} %  "
                     f"p={s.p_adjusted:.3g}{'  *' if s.significant else ''}{base}{bound}")
    return lines


def store_cal_correction(comp) -> dict | None:
    """The sensor's correction entry, when the comparison applied one."""
    return comp.summary.get("correction") if comp.post is not None else None

