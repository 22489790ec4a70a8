"""Several model packages side by side on the same held-out sessions, through the runtime (stage 8's
`evaluate_session`): e.g. the shipped package against a rebuild, on sessions of today's twin.

    tensortouch train crosseval --package exported_models/hiera-qup-128 \\
        --package cache/models/hiera-qup-128 --recipe hiera-qup-128 \\
        --session cache/demo_v2/demo --store cache/demo_v2/store [--json OUT]

`--recipe` adds the recipe build's held-out sessions with their unit calibrations (as stage 8 uses them);
`--session`/`--store` pairs add any other session, calibrated from that store (sensor = the
session's sensor_id). One JSON line per (package, session) with the stage-8 summary, plus the fraction
of single-contact frames (one indenter ≥ --contact-n, the others at rest) with a phantom second cluster.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_arguments(ap: argparse.ArgumentParser) -> None:
    from .evaluate import EvalConfig

    ap.add_argument("--package", action="append", required=True, help="model package folder (repeat)")
    ap.add_argument("--recipe", help="add this recipe build's held-out sessions (<cache>/train/<recipe name>/)")
    ap.add_argument("--session", action="append", default=[], help="a session folder (repeat, with --store)")
    ap.add_argument("--store", action="append", default=[], help="calibration store root for each --session")
    ap.add_argument("--precision", choices=("int8", "fp32"), default="int8", help="network graph to run")
    ap.add_argument("--contact-n", type=float, default=EvalConfig.contact_n,
                    help="contacts at or above this measured |F| (N) are scored")
    ap.add_argument("--json", help="write all summaries here")


def run(args: argparse.Namespace) -> int:
    from ...contracts.store import CalibrationStore
    from ...contracts.errors import TensorTouchError
    from ...runtime.stages.model import load_package
    from ...contracts.session import load_session
    from .build import recipe_build, unit_calibration
    from .evaluate import EvalConfig, evaluate_session, summarize

    if len(args.store) != len(args.session):
        raise TensorTouchError("crosseval: give one --store per --session")
    targets = []
    if args.recipe:
        b = recipe_build(args.recipe)
        targets += [(s.name, b.session(s), unit_calibration(b, s.serial)) for s in b.cfg.heldout]
    for folder, store in zip(args.session, args.store):
        sensor = load_session(folder, check_frames=False).sensor_id
        targets.append((f"{Path(folder).name}:{sensor}", Path(folder), CalibrationStore(Path(store)).load(sensor)))
    if not targets:
        raise TensorTouchError("crosseval: nothing to evaluate: give --recipe and/or --session/--store")
    out = {}
    try:
        for pk in args.package:
            package = load_package(pk)
            for name, path, cal in targets:
                r = evaluate_session(path, package, cal, EvalConfig(precision=args.precision, contact_n=args.contact_n))
                s = summarize(r["rows"], r["rest"], r["phantoms"])
                out[f"{pk} | {name}"] = s
                print(json.dumps({"package": pk, "session": name, **s}), flush=True)
    except TensorTouchError as exc:
        print(f"crosseval: {exc}")
        return 2
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0

