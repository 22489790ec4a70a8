"""`tensortouch bench workbench`: compare -> diagnose -> add -> compare on a ~10k-sample twin session.

Records (once, cached) a calibration session and a session with one hidden effect, fits the
nominal contact law, then times through the CLI commands, in this process:
  first compare   cold: sample table from the streams (+ frame brightness), model prediction,
                  report with pictures
  cycle           compare (warm) -> diagnose -> effects add -> compare --before-after
Target (issue 6): the cycle < 60 s on the 2-core dev machine.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

log = logging.getLogger(__name__)

TARGET_S = 60.0


def add_arguments(p) -> None:
    p.add_argument("--pokes", type=int, default=30, help="pokes in the test session (30 ≈ 10k samples)")
    p.add_argument("--seed", type=int, default=77)
    p.add_argument("--effect", default="viscoelastic_relaxation:g1=0.3,tau=1.0",
                   help="hidden effect NAME:p=v,... switched on in the twin's truth")
    p.add_argument("--out", help="work folder (default: cache/workbench/bench)")


def _parse_effect(text: str) -> tuple:
    name, _, rest = text.partition(":")
    params = {}
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        params[k.strip()] = float(v)
    return ((name.strip(), params),)


def _cli(argv: list[str]) -> tuple[int, float]:
    from tools.workbench import cli

    parser = argparse.ArgumentParser(prog="tensortouch")
    cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    code = args.func(args)
    return code, time.perf_counter() - t0


def run(args) -> int:
    import os

    from runtime import paths
    from tools.workbench.scenarios import Scenario, fresh_store, record

    work = Path(args.out) if args.out else paths.cache_dir() / "workbench" / "bench"
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    calib = record(Scenario(100, pokes=30))
    session = record(Scenario(args.seed, pokes=args.pokes, effects=_parse_effect(args.effect)))
    t_record = time.perf_counter() - t0
    store = fresh_store(work / "store")
    os.environ["TENSORTOUCH_CACHE"] = str(work / "cache")   # cold caches for this run
    for sub in (work / "cache",):
        if sub.exists():
            import shutil

            shutil.rmtree(sub)
    common = ["--sensor", "TWIN-WB01", "--store", str(store)]
    out = work / "compare"
    _, t_fit = _cli(["compare", str(calib), *common, "--out", str(work / "calib"), "--model-from", str(calib),
                     "--no-pictures"])
    _, t_first = _cli(["compare", str(session), *common, "--out", str(out)])
    timings = {}
    _, timings["compare"] = _cli(["compare", str(session), *common, "--out", str(out)])
    _, timings["diagnose"] = _cli(["diagnose", str(session), *common, "--json", "--out", str(work / "diagnosis.json")])
    diag = json.loads((work / "diagnosis.json").read_text())
    if diag["verdict"] is None:
        print("bench workbench: diagnosis found nothing; the cycle stops here")
        return 1
    _, timings["add"] = _cli(["effects", "add", diag["verdict"], "--from-diagnosis", str(work / "diagnosis.json"), *common])
    _, timings["compare_after"] = _cli(["compare", str(session), *common, "--out", str(out), "--before-after"])
    summary = json.loads((out / "summary.json").read_text())
    cycle = sum(timings.values())
    before = summary["before"]["force_error"]["rms_vector"]
    after = summary["force_error"]["rms_vector"]
    print("\nbench workbench")
    print(f"  session: {summary['n_samples']} samples, {summary['duration_s']:.0f} s, hidden {args.effect}")
    print(f"  recording (cached after the first run): {t_record:.1f} s; law fit on calibration session: {t_fit:.1f} s")
    print(f"  first compare (cold caches, pictures): {t_first:.1f} s")
    for k, v in timings.items():
        print(f"  {k:14s} {v:6.1f} s")
    print(f"  cycle compare->diagnose->add->compare: {cycle:.1f} s (target < {TARGET_S:.0f} s: "
          f"{'met' if cycle < TARGET_S else 'MISSED'}), {cycle / TARGET_S:.2f} x target")
    print(f"  verdict {diag['verdict']}: rms |r| {before:.4f} -> {after:.4f} N ({100 * (after / before - 1):+.0f} %)")
    print(json.dumps({"bench": "workbench", "samples": summary["n_samples"], "first_compare_s": round(t_first, 2),
                      "cycle_s": round(cycle, 2), **{f"{k}_s": round(v, 2) for k, v in timings.items()},
                      "verdict": diag["verdict"], "rms_before_n": before, "rms_after_n": after}))
    return 0 if cycle < TARGET_S else 1


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="tensortouch bench workbench")
    add_arguments(p)
    logging.basicConfig(level=logging.WARNING)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
