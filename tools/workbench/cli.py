"""`tensortouch compare | diagnose | effects` — the physics workbench (thin shell).

    tensortouch compare SESSION --sensor ID --out DIR [--model-from CALIB_SESSION] [--before-after [DIR]]
    tensortouch diagnose SESSION --sensor ID [--json]
    tensortouch effects list [--json]
    tensortouch effects add NAME --sensor ID [--from-diagnosis [FILE]] [--param p=v ...]
    tensortouch effects remove NAME --sensor ID

The model side: the deployed network (`--model PATH|NAME`, default: the installed model package when
the sensor's calibration is made for its input size and the session has frames) run over the
session's frames through the runtime's code, with the sensor's enabled effects and correction; or
the nominal contact law (`--model contact-law` / a JSON file; `--model-from CALIB_SESSION` fits it
and makes it the sensor's default). `--correction-from CALIB_SESSION` fits and stores the sensor's
correction for the network on a calibration session. Effect plugins: `--plugins DIR` (repeatable), the
TENSORTOUCH_EFFECTS_PATH folders and the `tensortouch.effects` entry points.
"""
from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

log = logging.getLogger(__name__)


def _common(p, session: bool = True) -> None:
    if session:
        p.add_argument("session", help="session directory (docs/session.md)")
    p.add_argument("--sensor", help="sensor id in the calibration store (default: the session's)")
    p.add_argument("--store", help="calibration store root (default: calibration_store/)")
    p.add_argument("--plugins", action="append", default=[], metavar="DIR", help="folder of effect plugins")


def _model_args(p) -> None:
    p.add_argument("--model", metavar="PATH|NAME|contact-law",
                   help="the model: a model package (folder or name under exported_models/; default: the "
                        "installed one when the calibration matches its size and the session has frames), "
                        "'contact-law' (the sensor's stored nominal contact law) or a contact-law JSON file")
    p.add_argument("--precision", choices=("int8", "fp32"), default="int8", help="network precision (default int8)")
    p.add_argument("--model-from", metavar="CALIB_SESSION",
                   help="contact law: fit it on this calibration session and make it the sensor's default")
    p.add_argument("--correction-from", metavar="CALIB_SESSION", nargs="+",
                   help="network: fit the sensor's force correction (zero-constrained gain forest, as "
                        "`tensortouch recalibrate` stores) on these calibration sessions (several short "
                        "sessions covering the gel are best), store it as a new calibration version, then compare")
    p.add_argument("--no-cache", action="store_true", help="rebuild the sample table and predictions")


def register(sub) -> None:
    c = sub.add_parser("compare", help="compare the model with a session's measurements (residuals, report)")
    _common(c)
    _model_args(c)
    c.add_argument("--out", required=True, help="folder for residuals.csv, summary.json, report.html, PNGs")
    c.add_argument("--before-after", nargs="?", const="", metavar="DIR",
                   help="show the error change against an earlier comparison (default: the one in --out)")
    c.add_argument("--no-pictures", action="store_true")
    c.set_defaults(func=cmd_compare)
    d = sub.add_parser("diagnose", help="which physical effect is missing? (blocked CV, significance test)")
    _common(d)
    _model_args(d)
    d.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    d.add_argument("--blocks", type=int, help="number of time blocks (default 16)")
    d.add_argument("--alpha", type=float, help="family-wise significance level (default 0.05)")
    d.add_argument("--out", help="also write the diagnosis JSON here")
    d.set_defaults(func=cmd_diagnose)
    e = sub.add_parser("effects", help="physical effects: list the library, add/remove for a sensor")
    esub = e.add_subparsers(dest="effects_cmd", metavar="ACTION", required=True)
    el = esub.add_parser("list", help="library + plugin effects with parameters and units")
    el.add_argument("--json", action="store_true")
    el.add_argument("--plugins", action="append", default=[], metavar="DIR")
    el.set_defaults(func=cmd_effects_list)
    ea = esub.add_parser("add", help="enable an effect for a sensor (new calibration version)")
    ea.add_argument("name")
    _common(ea, session=False)
    ea.add_argument("--from-diagnosis", nargs="?", const="", metavar="FILE",
                    help="take the fitted parameters from a diagnosis (default: the sensor's last one)")
    ea.add_argument("--param", action="append", default=[], metavar="P=V")
    ea.add_argument("--no-refit", action="store_true",
                    help="keep the enabled effects' parameters (default with --from-diagnosis: refit all "
                         "enabled effects jointly with the new one on the diagnosed session)")
    ea.add_argument("--model", metavar="PATH|NAME|contact-law", help="the model for the refit (as compare)")
    ea.add_argument("--precision", choices=("int8", "fp32"), default="int8")
    ea.set_defaults(func=cmd_effects_add)
    er = esub.add_parser("remove", help="disable an effect for a sensor (new calibration version)")
    er.add_argument("name")
    _common(er, session=False)
    er.set_defaults(func=cmd_effects_remove)


# ----- helpers ---------------------------------------------------------------------------------
def _store(args):
    from runtime.calibration import CalibrationStore

    return CalibrationStore(args.store) if args.store else CalibrationStore()


def _registry(args):
    from runtime.effects import Registry
    from runtime.errors import TensorTouchError

    try:
        return Registry.default(plugin_dirs=args.plugins)
    except ValueError as exc:
        raise TensorTouchError(str(exc)) from None


def _sensor(args) -> str:
    if args.sensor:
        return args.sensor
    if getattr(args, "session", None):
        return json.loads((Path(args.session) / "session.json").read_text())["sensor_id"]
    from runtime.errors import TensorTouchError

    raise TensorTouchError("--sensor is required")


def default_model_path(sensor: str) -> Path:
    from tools.workbench.compare import cache_root

    return cache_root() / "models" / f"{sensor}.json"


def last_diagnosis_path(sensor: str) -> Path:
    from tools.workbench.compare import cache_root

    return cache_root() / f"diagnosis-{sensor}.json"


def _contact_law(args, sensor: str, store, path=None):
    from runtime.errors import TensorTouchError
    from tools.workbench.compare import load_table
    from tools.workbench.models import ContactLaw

    if getattr(args, "model_from", None):
        table, _ = load_table(args.model_from, store.load(sensor), cache=not args.no_cache)
        law = ContactLaw.fit(table, source=f"fitted on {args.model_from}")
        law.save(default_model_path(sensor))
        print(f"nominal contact law fitted on {args.model_from} -> {default_model_path(sensor)}")
        return law
    path = Path(path) if path else default_model_path(sensor)
    if not path.is_file():
        raise TensorTouchError(f"{path}: no model for sensor {sensor} (no contact law fitted); fit one on a calibration "
                               "session with --model-from CALIB_SESSION (or give --model FILE)")
    return ContactLaw.load(path)


def _model(args, sensor: str, store):
    """--model: package (path/name) -> the deployed network; 'contact-law' or a .json -> contact law;
    default: the installed package when it fits the calibration and the session has frames."""
    from runtime.errors import ModelPackageError
    from runtime.model import find_package
    from tools.workbench.network import NetworkConfig, NetworkModel

    choice = getattr(args, "model", None)
    cfg = NetworkConfig(precision=getattr(args, "precision", "int8"))
    if choice == "contact-law" or (choice and choice.endswith(".json")) or getattr(args, "model_from", None):
        return _contact_law(args, sensor, store, None if choice in (None, "contact-law") else choice)
    if choice:
        return NetworkModel(find_package(choice), cfg)
    cal = store.load(sensor)
    session = getattr(args, "session", None)
    has_frames = bool(session) and "frames" in json.loads((Path(session) / "session.json").read_text()).get("streams", {})
    try:
        package = find_package()
    except ModelPackageError as exc:
        why = str(exc).split(".")[0]
    else:
        if tuple(package.size) == tuple(cal.model_size) and (has_frames or not session):
            return NetworkModel(package, cfg)
        why = (f"calibration {sensor}/{cal.version} is for {list(cal.model_size)} px, model {package.name} for "
               f"{list(package.size)} px" if tuple(package.size) != tuple(cal.model_size) else "the session has no frames")
    print(f"note: model = the nominal contact law ({why}); use --model PATH|NAME for the network")
    return _contact_law(args, sensor, store)


def _progress(i: int, n: int, seconds: float) -> None:
    print(f"\r  network pass: frame {i}/{n} ({seconds:.0f} s)", end="\n" if i == n else "", flush=True)


def _compare(args, store=None, sensor=None):
    from tools.workbench.compare import run_compare

    sensor = sensor or _sensor(args)
    store = store or _store(args)
    model = _model(args, sensor, store)
    if getattr(args, "correction_from", None):
        from tools.workbench.nominal import fit_and_store_correction

        if not hasattr(model, "build_table"):
            from runtime.errors import TensorTouchError

            raise TensorTouchError("--correction-from needs the network model (the contact law has no correction)")
        version, text = fit_and_store_correction(args.correction_from, sensor, store, model, _registry(args),
                                                 cache=not args.no_cache, progress=_progress)
        print(text)
    return run_compare(args.session, sensor, store, model, _registry(args), cache=not args.no_cache,
                       progress=_progress)


# ----- commands --------------------------------------------------------------------------------
def cmd_compare(args) -> int:
    from tools.workbench.report import write_report
    from tools.workbench.table import write_residuals_csv

    out = Path(args.out)
    previous = None
    if args.before_after is not None:
        prev_dir = Path(args.before_after) if args.before_after else out
        if (prev_dir / "summary.json").is_file():
            previous = json.loads((prev_dir / "summary.json").read_text())
        else:
            print(f"note: no earlier comparison in {prev_dir} (summary.json); nothing to compare against")
    comp = _compare(args)
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

    from tools.workbench.diagnose import DiagnoseConfig, diagnose

    comp = _compare(args)
    cfg = DiagnoseConfig()
    if args.blocks:
        cfg = replace(cfg, n_blocks=args.blocks)
    if args.alpha:
        cfg = replace(cfg, alpha=args.alpha)
    registry = _registry(args)
    baseline = (store_cal_correction(comp) or {}).get("nominal_reductions")
    diag = diagnose(comp.table, registry, comp.chain, cfg, post=comp.post, baseline=baseline)
    result = diag.to_json()
    result.update({"session": str(Path(args.session).resolve()), "sensor_id": comp.summary["sensor_id"],
                   "enabled": diag.enabled, "n_samples": diag.n_samples, "n_blocks": diag.n_blocks,
                   "seconds": round(diag.seconds, 2)})
    text = json.dumps(result, default=float)
    for path in filter(None, [last_diagnosis_path(comp.summary["sensor_id"]), args.out and Path(args.out)]):
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(result, indent=2, default=float))
        tmp.replace(path)
    for line in diag.words():
        print(line)
    print("ranking (held-out error, N):")
    for s in diag.ranking:
        base = f"  (calibration session: {-100 * s.baseline:+.1f} %)" if s.baseline else ""
        print(f"  {s.effect.name:24s} {s.before:.4g} -> {s.after:.4g}  {-100 * s.reduction:+6.1f} %  "
              f"p={s.p_adjusted:.3g}{'  *' if s.significant else ''}{base}")
    if args.json:
        print(text)
    return 0


def store_cal_correction(comp) -> dict | None:
    """The sensor's correction entry, when the comparison applied one."""
    return comp.summary.get("correction") if comp.post is not None else None


def cmd_effects_list(args) -> int:
    reg = _registry(args)
    if args.json:
        print(json.dumps([dict(reg.get(n).spec(), origin=reg.origin[n]) for n in reg.names()]))
        return 0
    for n in reg.names():
        e = reg.get(n)
        params = ", ".join(f"{p.name} [{p.unit}] {p.lo}..{p.hi}" for p in e.params)
        print(f"{n:24s} {e.stage:11s} {e.summary}\n{'':36s}{params}   ({reg.origin[n]})")
    return 0


def _write_effects(args, effects: list, provenance: dict) -> str:
    store = _store(args)
    return store.derive(args.sensor or _sensor(args), {"effects": effects}, provenance=provenance)


def cmd_effects_add(args) -> int:
    from runtime.effects import EnabledEffect
    from runtime.errors import TensorTouchError

    reg = _registry(args)
    sensor = _sensor(args)
    try:
        eff = reg.get(args.name)
    except KeyError as exc:
        raise TensorTouchError(str(exc).strip('"')) from None
    params, source = {}, "manual"
    if args.from_diagnosis is not None:
        path = Path(args.from_diagnosis) if args.from_diagnosis else last_diagnosis_path(sensor)
        if not path.is_file():
            raise TensorTouchError(f"{path}: no diagnosis to take parameters from (run diagnose first)")
        diag = json.loads(path.read_text())
        row = next((r for r in diag.get("ranking", []) if r["effect"] == args.name), None)
        if row is None:
            raise TensorTouchError(f"{path}: effect {args.name} not in that diagnosis' ranking")
        params, source = dict(row["params"]), f"diagnosis of {diag.get('session', path)}"
    for item in args.param:
        key, eq, val = item.partition("=")
        if not eq:
            raise TensorTouchError(f"--param {item!r}: expected P=V")
        params[key.strip()] = float(val)
    try:
        params = eff.resolve(params)
    except ValueError as exc:
        raise TensorTouchError(str(exc)) from None
    store = _store(args)
    current = [e for e in store.load(sensor).effects if e.get("name") != args.name]
    entry = EnabledEffect(eff, params).to_dict(source)
    if args.from_diagnosis is not None and not args.no_refit and current:
        current, entry = _refit(args, sensor, store, reg, current, entry, diag.get("session"))
    version = store.derive(sensor, {"effects": current + [entry]},
                           provenance={"method": "workbench effects add", "effect": args.name, "source": source})
    params = entry["params"]
    words = eff.describe(params)
    print(f"{sensor}: {words} -> calibration {version}")
    if eff.stage == "force":
        spec = ",".join(f"{k}={v:.6g}" for k, v in params.items())
        print(f"twin/FE configuration: --effect {eff.name}:{spec}")
    return 0


def _refit(args, sensor, store, reg, current, entry, session):
    """Joint refit of the enabled effects + the new one on the diagnosed session (same model and
    deployed order as compare/diagnose: force-stage effects, then the sensor's correction)."""
    from runtime.effects import EffectChain
    from runtime.errors import TensorTouchError
    from tools.workbench.compare import run_compare
    from tools.workbench.fit import refit_chain

    if not session or not Path(session, "session.json").is_file():
        print("note: parameters not refitted jointly (diagnosed session not found)")
        return current, entry
    args.session = session
    try:
        model = _model(args, sensor, store)
        comp = run_compare(session, sensor, store, model, reg, progress=_progress)
    except TensorTouchError as exc:
        print(f"note: parameters not refitted jointly ({exc})")
        return current, entry
    chain = EffectChain.from_list(current + [entry], reg)
    new, before, after = refit_chain(comp.table, chain, post=comp.post)
    print(f"joint refit of {', '.join(chain.names)} on {session}: rms |r| {before:.4f} -> {after:.4f} N")
    for old_it, it in zip(chain.items, new.items):
        if old_it.params != it.params:
            print(f"  {it.effect.describe(it.params)}")
    out = new.to_list()
    for o, c in zip(out, current + [entry]):
        o.update({k: v for k, v in c.items() if k not in ("name", "params")})
    return out[:-1], out[-1]


def cmd_effects_remove(args) -> int:
    from runtime.errors import TensorTouchError

    store = _store(args)
    sensor = _sensor(args)
    effects = store.load(sensor).effects
    kept = [e for e in effects if e.get("name") != args.name]
    if len(kept) == len(effects):
        raise TensorTouchError(f"sensor {sensor}: effect {args.name} is not enabled "
                               f"(enabled: {', '.join(e['name'] for e in effects) or 'none'})")
    version = store.derive(sensor, {"effects": kept}, provenance={"method": "workbench effects remove",
                                                                 "effect": args.name})
    print(f"{sensor}: {args.name} removed -> calibration {version}")
    return 0


def main(argv=None) -> int:
    import argparse

    from runtime.errors import TensorTouchError

    parser = argparse.ArgumentParser(prog="tensortouch")
    parser.add_argument("-v", "--verbose", action="store_true")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except TensorTouchError as exc:
        print(f"tensortouch {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
