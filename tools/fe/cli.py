"""`tensortouch fe ...`: solve one scenario, run a batch, fit materials, make indenters, export .inp.

Registered through the entry point `fe = "tensortouch.tools.fe.cli:register"`; also `python -m tools.fe.cli`.
Heavy libraries are imported inside the handlers.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..command_group import add_commands, arg, command_group
from ..progress import stage_progress
from .study import STUDIES

log = logging.getLogger(__name__)


def _progress(desc="fe solve"):
    bar = stage_progress(desc, "frame")
    return lambda j, n, msg: bar("", j + 1, n)


def _cmd_solve(args) -> int:
    from .result import save_result
    from .scenario import load_scenario, save_scenario, standard_dome
    from .solver import solve

    scenario = standard_dome() if args.scenario == "standard" else load_scenario(args.scenario)
    if args.write_scenario:
        save_scenario(scenario, args.write_scenario)
    result = solve(scenario, progress=_progress())
    save_result(result, args.out)
    print(f"wrote {args.out}: {result.n_frames} frames, {result.n_nodes} nodes, "
          f"final RF {result.RF[-1].round(4).tolist()} N")
    return 0


def _cmd_batch(args) -> int:
    from .batch import run_batch

    report = run_batch(args.scenarios, out_dir=args.out_dir, workers=args.workers, retry_failed=args.retry_failed,
                       cluster=args.cluster)
    print(f"batch: {report['solved']} solved, {report['cached']} cached, {report['failed']} failed "
          f"-> {report['out_dir']}")
    return 0 if report["failed"] == 0 else 1


def _cmd_fit(args) -> int:
    from .fitting import fit_report, load_test_data, synthetic_test_data

    data = synthetic_test_data() if args.data == "synthetic" else load_test_data(args.data)
    report = fit_report(data, models=args.models.split(","), plot=args.plot)
    print(report["table"])
    if args.json_out:
        import json

        Path(args.json_out).write_text(json.dumps(report["fits"], indent=2))
    return 0


def _cmd_ind_generate(args) -> int:
    from .procedural import generate_set

    paths = generate_set(args.out_dir, seed=args.seed, count=args.count)
    for p in paths:
        print(p)
    return 0


def _cmd_ind_list(args) -> int:
    from .procedural import OBJECT_KINDS

    for name, doc in OBJECT_KINDS.items():
        print(f"{name:16s} {doc}")
    return 0


def _cmd_inp(args) -> int:
    from .inp import export_inp
    from .scenario import load_scenario, standard_dome

    scenario = standard_dome() if args.scenario == "standard" else load_scenario(args.scenario)
    path = export_inp(scenario, args.out, dialect=args.dialect, bulk=args.bulk,
                      max_increment_mm=args.max_increment_mm)
    print(f"wrote {path}")
    return 0


def _cmd_crosscheck(args) -> int:
    from .ccx import crosscheck
    from .scenario import load_scenario, standard_dome

    scenario = standard_dome() if args.scenario == "standard" else load_scenario(args.scenario)
    out = crosscheck(scenario, args.work_dir, bulk=args.bulk, threads=args.threads,
                     max_increment_mm=args.max_increment_mm)
    print(f"{out['nodes']} nodes; deck {out['deck']}")
    print("frame  indenter  RF tools.fe (N)               RF ccx (N)                    |RF| ratio")
    for j in range(out["ours"].shape[0]):
        for k in range(out["ours"].shape[1]):
            a, b = out["ours"][j, k], out["ccx"][j, k]
            ratio = float(np.linalg.norm(a) / max(np.linalg.norm(b), 1e-12))
            print(f"{j + 1:5d}  {k:8d}  {np.array2string(a, precision=4):28s}  "
                  f"{np.array2string(b, precision=4):28s}  {ratio:.4f}")
    print(f"wall time: tools.fe {out['seconds_ours']:.1f} s, ccx {out['seconds_ccx']:.1f} s")
    return 0


def _cmd_study(args) -> int:
    import json

    from .study import fz_table, run_study

    rows = []
    for name in args.names:
        rows += run_study(name, args.work_dir, emit=lambda r: print(json.dumps(r), flush=True))
    print(fz_table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


def _positive_mm(text: str) -> float:
    import argparse

    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a length in mm > 0, got {text!r}")
    return value


# export-inp and crosscheck: a scenario written as a deck, with the deck's bulk modulus and increments
DECK = (arg("scenario", help="scenario file, or 'standard'"),
        arg("--bulk", choices=("solver", "material"), default="solver",
            help="bulk modulus in the deck: tools.fe's (P1 cap, default) or the material's D1"),
        arg("--max-increment-mm", type=_positive_mm, default=None, metavar="MM",
            help="ccx deck: increments of at most MM of indenter travel (default: the scenario's "
                 "solver.max_increment_mm; 0.25 for C3D10 at the true D1, docs/fe.md)"))
COMMANDS = (
    ("solve", "solve one scenario file (JSON/TOML) -> result .npz", _cmd_solve, (
        arg("scenario", help="scenario file, or 'standard' for the standard dome"),
        arg("--out", required=True, help="result .npz path"),
        arg("--write-scenario", help="also write the scenario as JSON here"))),
    ("batch", "solve many scenarios with an on-disk cache (resumable)", _cmd_batch, (
        arg("scenarios", nargs="+", help="scenario files or folders of *.json/*.toml"),
        arg("--out-dir", default=None, help="cache folder (default <cache>/fe)"),
        arg("--workers", type=int, default=2, help="parallel processes (default 2)"),
        arg("--retry-failed", action="store_true", help="re-run scenarios that failed before"),
        arg("--cluster", default=None, metavar="tcp://HOST:8786",
            help="run on this Dask.distributed scheduler instead of local processes (extra 'cluster')"))),
    ("fit-material", "fit Yeoh/NH/MR/Ogden to uniaxial+biaxial data", _cmd_fit, (
        arg("data", help="CSV (mode,stretch,stress_MPa) or 'synthetic'"),
        arg("--models", default="yeoh,neo_hookean,mooney_rivlin,ogden", help="hyperelastic models to fit, comma separated"),
        arg("--plot", help="write a PNG of the fits here (needs matplotlib)"),
        arg("--json-out", help="write the fitted constants as JSON here"))),
    ("export-inp", "write the scenario as a CalculiX (or Abaqus) .inp deck", _cmd_inp, (
        *DECK,
        arg("--out", required=True, help="deck (.inp) to write"),
        arg("--dialect", choices=("ccx", "abaqus"), default="ccx",
            help="ccx: runs in CalculiX 2.20 as written (default); abaqus: parts/instances, C3D4H, R3D3"))),
    ("crosscheck", "solve a scenario in tools.fe and in CalculiX (ccx), same mesh", _cmd_crosscheck, (
        *DECK,
        arg("--work-dir", required=True, help="folder for the deck and ccx's output"),
        arg("--threads", type=int, default=1, help="ccx solver threads (default 1)"))),
    ("study", "convergence / CalculiX study (" + ", ".join(STUDIES) + ")", _cmd_study, (
        arg("names", nargs="+", choices=STUDIES, help="studies to run"),
        arg("--work-dir", required=True, help="folder for the decks and ccx's output"),
        arg("--json", help="write all rows here"))),
)
INDENTER_COMMANDS = (
    ("generate", "write the standardized indenter STL files", _cmd_ind_generate, (
        arg("--out-dir", default=None, help="folder (default <cache>/fe/indenters)"),
        arg("--seed", type=int, default=0, help="random seed of the generated shapes"),
        arg("--count", type=int, default=12, help="number of indenters"))),
    ("list", "list the procedural object kinds", _cmd_ind_list, ()),
)


def register(sub) -> None:
    """Add the `fe` command and its subcommands to an argparse subparsers object."""
    fsub = command_group(sub, "fe", "hyperelastic FE of the gel (solve, batch, fit-material, indenters)",
                         "fe_command", "SUBCOMMAND", extra="train")
    add_commands(fsub, COMMANDS)
    add_commands(command_group(fsub, "indenters", "procedural indenter set (seed III.B standardization)",
                               "ind_command", "ACTION"), INDENTER_COMMANDS)
