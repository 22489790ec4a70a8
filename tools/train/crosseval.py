"""Several model packages side by side on the same held-out sessions, through the runtime (stage 8's
`evaluate_session`), each with the protocol's scorecard (tools/train/scorecard.py): e.g. the shipped
package against a rebuild, on the validation units.

    tensortouch train crosseval --package exported_models/hiera-qup-128 --units validation [--json OUT]
    tensortouch train crosseval --package A --package B --recipe hiera-qup-128 \\
        --session cache/demo_v2/demo --store cache/demo_v2/store

Targets: `--units SET` the recorded sessions of a protocol set (`tensortouch train units record SET`,
each unit with its true calibration); `--recipe` the recipe build's held-out sessions with their unit
calibrations (as stage 8 uses them); `--session`/`--store` pairs any other session, calibrated from that
store (sensor = the session's sensor_id). Per (package, session) one JSON line with the stage-8 summary;
per package the scorecard over all targets: miss rate (contacts ≥ --contact-n, 0.2 N) and phantoms (% of
rest frames) apart from |F| MAE on detected contacts and the direction error (degrees), with 95 %
bootstrap CIs over units and pokes, by indenter, single/multi contact and force bin. Packages built from
one recipe but different fit seeds get their mean ± spread.

`--units sealed` scores the sealed set, whole, alone, once per package and scorer version: a package
already in its `sealed_scores.json` under this scorer is refused, and the score is appended there.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_arguments(ap: argparse.ArgumentParser) -> None:
    from .scorecard import ScoreConfig

    ap.add_argument("--package", action="append", required=True, help="model package folder (repeat)")
    ap.add_argument("--units", help="a protocol unit set as recorded by `train units record`: train | validation | sealed")
    ap.add_argument("--units-root", help="where recorded sets live (default <cache>/units)")
    ap.add_argument("--protocol", help="protocol file of --units (default tools/train/protocol.toml)")
    ap.add_argument("--recipe", help="add this recipe build's held-out sessions (<cache>/train/<recipe name>/)")
    ap.add_argument("--session", action="append", default=[], help="a session folder (repeat, with --store)")
    ap.add_argument("--store", action="append", default=[], help="calibration store root for each --session")
    ap.add_argument("--precision", choices=("int8", "fp32"), default="int8", help="network graph to run")
    ap.add_argument("--contact-n", type=float, default=ScoreConfig.contact_n,
                    help="contacts at or above this measured |F| (N) are scored")
    ap.add_argument("--boot", type=int, default=ScoreConfig.n_boot, help="bootstrap replicates")
    ap.add_argument("--boot-seed", type=int, default=ScoreConfig.seed, help="bootstrap generator seed")
    ap.add_argument("--json", help="write all summaries and scorecards here")


def recipe_key(package) -> str | None:
    """The recipe a package was built from, its fit seed left out (packages that differ only by fit seed
    share it); None when it was not built from a recipe."""
    import hashlib

    doc = ((package.manifest.get("training") or {}).get("recipe") or {}).get("doc")
    if not isinstance(doc, dict):
        return None
    doc = json.loads(json.dumps(doc))
    for table in [doc.get("build") or {}] + [s.get("build") or {} for s in doc.get("steps") or []]:
        table.pop("fit_seed", None)
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def format_card(card: dict) -> str:
    """The scorecard as a few plain lines: mean [95 % CI] per number, overall and by breakdown."""
    def cell(s, scale=1.0, unit=""):
        if not s or not s.get("n"):
            return "—"
        lo, hi = s["ci"]
        return f"{s['mean'] * scale:.3g}{unit} [{lo * scale:.3g}, {hi * scale:.3g}]"

    def line(label, b):
        if b["pokes"] < 2:      # one poke: no interval to speak of
            b = {**b, **{k: {**v, "ci": [v.get("mean", 0.0)] * 2} for k, v in b.items() if isinstance(v, dict) and v.get("n")}}
        note = "  (one poke: no CI)" if b["pokes"] < 2 else "  (one unit: CI over pokes only)" if b["units"] < 2 else ""
        return (f"  {label:18s} n={b['contacts']:<5d} units={b['units']:<3d} pokes={b['pokes']:<4d} "
                f"miss {cell(b['miss_rate'], 100, '%')}  |F| MAE {cell(b['force_mae_n'], 1, ' N')} "
                f"(bias {cell(b.get('force_bias_n'), 1, ' N')})  "
                f"dir {cell(b['direction_error_deg'], 1, '°')}  (misses as 0: {cell(b['force_mae_with_misses_n'], 1, ' N')}; "
                f"field split at the tips: {cell(b.get('split_force_mae_n'), 1, ' N')}){note}")

    o = card["overall"]
    out = [(f"  {card['units']} units, {card['pokes']} pokes; phantoms {cell(o['phantom_rate'], 100, '%')} "
           f"of {o['phantom_rate'].get('n', 0)} rest frames"), line("all", o)]
    for group in ("by indenter", "by contacts", "by force", "by indenter and contacts"):
        for k, b in card.get(group, {}).items():
            if b["contacts"]:
                out.append(line(k, b))
    ceil = card.get("scale ceilings") or {}
    if ceil:
        out.append("  |F| MAE with the best force gain (fitted on these contacts: a ceiling) "
                   + "; ".join(f"{k} {v:.3f} N" for k, v in ceil.items()))
    return "\n".join(out)


def run(args: argparse.Namespace) -> int:
    from ...contracts.errors import TensorTouchError
    from ...contracts.session import load_session
    from ...contracts.store import CalibrationStore
    from ...runtime.stages.model import load_package
    from .evaluate import EvalConfig, evaluate_session, summarize
    from .scorecard import ScoreConfig, concat_tables, fit_seed_spread, headline, scorecard, session_table

    out: dict = {}
    try:
        if len(args.store) != len(args.session):
            raise TensorTouchError("crosseval: give one --store per --session")
        if args.contact_n <= 0 or args.boot < 1:
            raise TensorTouchError("crosseval: --contact-n must be > 0 N and --boot ≥ 1")
        sealed = args.units == "sealed"
        if sealed and (args.recipe or args.session):
            raise TensorTouchError("crosseval: the sealed set is scored alone (no --recipe / --session beside it)")
        targets, protocol = [], None
        if args.units:
            from .protocol import check_not_scored, load_protocol
            from .units import unit_targets, units_root

            protocol = load_protocol(args.protocol)
            targets += unit_targets(protocol, args.units, units_root(args.units_root), check_whole=sealed)
            if sealed:
                for pk in args.package:
                    check_not_scored(pk, protocol.hash)
        if args.recipe:
            from .build import recipe_build, unit_calibration

            b = recipe_build(args.recipe)
            targets += [(s.name, b.session(s), unit_calibration(b, s.serial)) for s in b.cfg.heldout]
        for folder, store in zip(args.session, args.store):
            sensor = load_session(folder, check_frames=False).sensor_id
            targets.append((f"{Path(folder).name}:{sensor}", Path(folder), CalibrationStore(Path(store)).load(sensor)))
        if not targets:
            raise TensorTouchError("crosseval: nothing to evaluate: give --units, --recipe and/or --session/--store")
        scfg = ScoreConfig(contact_n=args.contact_n, n_boot=args.boot, seed=args.boot_seed)
        ecfg = EvalConfig(precision=args.precision, contact_n=args.contact_n)
        cards, keys = {}, {}
        for pk in args.package:
            package = load_package(pk)
            keys[pk] = recipe_key(package)
            tables = []
            for name, path, cal in targets:
                r = evaluate_session(path, package, cal, ecfg)
                s = summarize(r["rows"], r["rest"], r["phantoms"])
                out[f"{pk} | {name}"] = s
                print(json.dumps({"package": pk, "session": name, **s}), flush=True)
                tables.append(session_table(r["sensor"], r, r["indenters"], scfg))
            cards[pk] = scorecard(*concat_tables(tables), scfg)
            print(f"scorecard {pk} ({args.units or 'sessions'}; 95 % CI, hierarchical bootstrap over units and "
                  f"pokes, {scfg.n_boot} replicates)\n{format_card(cards[pk])}", flush=True)
            if sealed:
                from .protocol import log_sealed_score

                entry = log_sealed_score(pk, protocol.hash, [t[0] for t in targets], headline(cards[pk]))
                print(f"sealed score logged in {Path(pk) / 'sealed_scores.json'} at {entry['when']}")
        out["scorecards"] = cards
        groups: dict[str, list[str]] = {}
        for pk, k in keys.items():
            if k is not None:
                groups.setdefault(k, []).append(pk)
        spread = {k: {"packages": pks, **fit_seed_spread([headline(cards[p]) for p in pks])}
                  for k, pks in groups.items() if len(pks) > 1}
        for k, s in spread.items():
            n = len(s["packages"])
            print(f"fit seeds of recipe {k}: {n} package(s){' (fewer than 3)' if n < 3 else ''}: " + "; ".join(
                f"{m} {v['mean']:.4g} ± {v['sd']:.2g} [{v['min']:.4g}, {v['max']:.4g}]"
                for m, v in s.items() if m != "packages"))
        out["fit_seeds"] = spread
    except TensorTouchError as exc:
        print(f"crosseval: {exc}" if not str(exc).startswith("crosseval:") else str(exc))
        return 2
    if args.json:
        from ...contracts.files import atomic_write_json

        atomic_write_json(args.json, out)
    return 0
