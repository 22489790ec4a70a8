"""`tensortouch effects list | add | remove` (thin shell; docs/effects.md)."""
from __future__ import annotations

import json
from pathlib import Path

from .cli_common import last_diagnosis_path, model_of, progress, registry_of, sensor_of, session_args, store_of


def register_effects(sub) -> None:
    e = sub.add_parser("effects", help="physical effects: list the library, add/remove for a sensor")
    esub = e.add_subparsers(dest="effects_cmd", metavar="ACTION", required=True)
    el = esub.add_parser("list", help="library + plugin effects with parameters and units")
    el.add_argument("--json", action="store_true", help="one JSON object instead of the table")
    el.add_argument("--plugins", action="append", default=[], metavar="DIR", help="also list the effects in this plugin folder (repeat)")
    el.set_defaults(func=cmd_effects_list)
    ea = esub.add_parser("add", help="enable an effect for a sensor (new calibration version)")
    ea.add_argument("name", help="effect name (see `tensortouch effects list`)")
    session_args(ea, session=False)
    ea.add_argument("--from-diagnosis", nargs="?", const="", metavar="FILE",
                    help="take the fitted parameters from a diagnosis (default: the sensor's last one)")
    ea.add_argument("--param", action="append", default=[], metavar="P=V", help="fix a parameter instead of fitting it (repeat)")
    ea.add_argument("--no-refit", action="store_true",
                    help="keep the enabled effects' parameters (default with --from-diagnosis: refit all "
                         "enabled effects jointly with the new one on the diagnosed session)")
    ea.add_argument("--model", metavar="PATH|NAME|contact-law", help="the model for the refit (as compare)")
    ea.add_argument("--path", choices=("output", "contact-law", "fe"),
                    help="with a diagnosis of several model paths (diagnose --paths): take the verdict of this "
                         "path (default: the one with a verdict and the smallest MDE)")
    ea.add_argument("--precision", choices=("int8", "fp32"), default="int8", help="network precision of the replay the fit uses")
    ea.set_defaults(func=cmd_effects_add, extra="train")
    er = esub.add_parser("remove", help="disable an effect for a sensor (new calibration version)")
    er.add_argument("name", help="effect name to disable in a new calibration version")
    session_args(er, session=False)
    er.set_defaults(func=cmd_effects_remove, extra="train")


def cmd_effects_list(args) -> int:
    reg = registry_of(args)
    if args.json:
        print(json.dumps([dict(reg.get(n).spec(), origin=reg.origin[n]) for n in reg.names()]))
        return 0
    for n in reg.names():
        e = reg.get(n)
        params = ", ".join(f"{p.name} [{p.unit}] {p.lo}..{p.hi}" for p in e.params)
        print(f"{n:24s} {e.stage:11s} {e.summary}\n{'':36s}{params}   ({reg.origin[n]})")
    return 0


def cmd_effects_add(args) -> int:
    from ...contracts.errors import TensorTouchError
    from ...runtime.stages.effects import EnabledEffect

    reg = registry_of(args)
    sensor = sensor_of(args)
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
        if getattr(args, "path", None):
            if args.path not in diag.get("paths", {}):
                raise TensorTouchError(f"{path}: no diagnosis on the {args.path} path (has: "
                                       f"{', '.join(diag.get('paths', {})) or diag.get('path', 'one path')})")
            diag = diag["paths"][args.path]
        if diag.get("path"):
            print(f"from the diagnosis on the {diag['path']} path"
                  + (" (against the model's own error)" if diag.get("own_error") else ""))
        row = next((r for r in diag.get("ranking", []) if r["effect"] == args.name), None)
        if row is None:
            raise TensorTouchError(f"{path}: effect {args.name} not in that diagnosis' ranking")
        params, source = dict(row["params"]), f"diagnosis of {diag.get('session', path)}"
    for item in args.param:
        key, value = param_value(eff, item)
        params[key] = value
    try:
        params = eff.resolve(params)
    except ValueError as exc:
        raise TensorTouchError(str(exc)) from None
    store = store_of(args)
    with store.locked(sensor):      # read, (refit,) write: no other writer of this sensor in between
        base = store.load(sensor)
        current = [e for e in base.effects if e.get("name") != args.name]
        entry = EnabledEffect(eff, params).to_dict(source)
        if args.from_diagnosis is not None and not args.no_refit and current and diag.get("path") != "fe":
            current, entry = _refit(args, sensor, store, reg, current, entry, diag)
        version = store.derive(sensor, {"effects": current + [entry]}, base_version=base.version,
                               provenance={"method": "workbench effects add", "effect": args.name, "source": source})
    params = entry["params"]
    words = eff.describe(params)
    print(f"{sensor}: {words} -> calibration {version}")
    if eff.stage == "force":
        spec = ",".join(f"{k}={v:.6g}" for k, v in params.items())
        print(f"twin/FE configuration: --effect {eff.name}:{spec}")
    return 0


def model_of_diagnosis(diag: dict) -> str | None:
    """The --model a refit of this diagnosis uses: the model of the path it was found on (the contact
    law, or the network package it ran), not whatever the default would be now."""
    if diag.get("path") == "contact-law":
        return "contact-law"
    return diag.get("model_source") or None


def _refit(args, sensor, store, reg, current, entry, diag: dict):
    """Joint refit of the enabled effects + the new one on the diagnosed session (same model and
    deployed order as compare/diagnose: force-stage effects, then the sensor's correction)."""
    session, own_error = diag.get("session"), diag.get("own_error")
    from ...contracts.errors import TensorTouchError
    from ...runtime.stages.effects import EffectChain
    from .compare import run_compare
    from .fit import refit_chain

    if not session or not Path(session, "session.json").is_file():
        print("note: parameters not refitted jointly (diagnosed session not found)")
        return current, entry
    args.session = session
    if getattr(args, "model", None) is None:
        args.model = model_of_diagnosis(diag)
    try:
        model = model_of(args, sensor, store)
        comp = run_compare(session, sensor, store, model, reg, progress=progress)
    except TensorTouchError as exc:
        print(f"note: parameters not refitted jointly ({exc})")
        return current, entry
    chain = EffectChain.from_list(current + [entry], reg)
    post = comp.post
    if own_error:      # fitted as diagnosed: against the model's own error
        from .own_error import OwnError

        post = OwnError.from_json(own_error).post(comp.table.cov(), comp.post)
    new, before, after = refit_chain(comp.table, chain, post=post)
    print(f"joint refit of {', '.join(chain.names)} on {session}: rms |r| {before:.4f} -> {after:.4f} N")
    for old_it, it in zip(chain.items, new.items):
        if old_it.params != it.params:
            print(f"  {it.effect.describe(it.params)}")
    out = new.to_list()
    for o, c in zip(out, current + [entry]):
        o.update({k: v for k, v in c.items() if k not in ("name", "params")})
    return out[:-1], out[-1]


def cmd_effects_remove(args) -> int:
    from ...contracts.errors import TensorTouchError

    store = store_of(args)
    sensor = sensor_of(args)
    def without(cal) -> dict:       # evaluated on the current version, under the sensor's lock
        kept = [e for e in cal.effects if e.get("name") != args.name]
        if len(kept) == len(cal.effects):
            raise TensorTouchError(f"sensor {sensor}: effect {args.name} is not enabled "
                                   f"(enabled: {', '.join(e['name'] for e in cal.effects) or 'none'})")
        return {"effects": kept}

    version = store.derive(sensor, without, provenance={"method": "workbench effects remove", "effect": args.name})
    print(f"{sensor}: {args.name} removed -> calibration {version}")
    return 0


def param_value(eff, item: str) -> tuple[str, float]:
    """`--param P=V` or `P=V UNIT` (e.g. tau=1900ms, t_ref=295.15K): V in the parameter's own unit,
    or converted to it from UNIT (contracts/units.py). TensorTouchError naming what was expected."""
    import re

    from ...contracts.errors import TensorTouchError
    from ...contracts.units import convert

    key, eq, val = item.partition("=")
    key = key.strip()
    m = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(\S*)\s*", val)
    if not eq or not m:
        raise TensorTouchError(f"--param {item!r}: expected P=V or P=V UNIT, e.g. tau=1.9 or tau=1900ms")
    declared = {q.name: q.unit for q in eff.params}
    if key not in declared:
        raise TensorTouchError(f"--param {item!r}: effect {eff.name} has no parameter {key!r} "
                               f"(has {sorted(declared)})")
    number, unit = float(m.group(1)), m.group(2)
    if not unit:
        return key, number
    try:
        return key, convert(number, unit, declared[key])
    except ValueError:
        raise TensorTouchError(f"--param {item!r}: {key} is in {declared[key]!r}; {unit!r} does not convert "
                               "to it") from None
