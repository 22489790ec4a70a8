"""The evaluation protocol's unit sets (tools/train/protocol.toml) on the command line.

    tensortouch train units check                      # the protocol, and every recipe against it
    tensortouch train units list [SET]                 # units, seeds, indenter pairs, pokes
    tensortouch train units record SET [--first N] [--pokes N] [--root DIR]
    tensortouch train units rim SET                    # each unit's rim found in rest frames vs its true rim

`record` plays the twin for a set's sessions into `<root>/<set>/sessions/<serial>-s<seed>/` and writes each
unit's true calibration into `<root>/<set>/calibration_store/` (default root `<cache>/units`), as a
build's stage 1 does; a session already recorded is kept. `--first`/`--pokes` record a part of a set
(smoke runs); the sealed set is recorded whole or not at all. `tensortouch train crosseval --units SET`
scores what is recorded.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("action", choices=("check", "list", "record", "rim"), help="what to do")
    ap.add_argument("set", nargs="?", help="train | validation | sealed (list: all when not given)")
    ap.add_argument("--protocol", help="protocol file (default tools/train/protocol.toml)")
    ap.add_argument("--first", type=int, help="record only the set's first N units")
    ap.add_argument("--pokes", type=int, help="record only the first N pokes of each plan")
    ap.add_argument("--root", help="where recorded sets live (default <cache>/units)")
    ap.add_argument("--physics", default="fe", choices=("fe", "hertz-fallback"),
                    help="twin physics (fe; hertz-fallback only for tests)")
    ap.add_argument("--size", type=int, default=128, help="calibration table size (the model's input size)")


def units_root(root: str | None) -> Path:
    from ...contracts.paths import cache_dir

    return Path(root) if root else cache_dir() / "units"


def set_paths(root: Path, name: str) -> tuple[Path, Path]:
    """(sessions folder, calibration store root) of a recorded set."""
    return root / name / "sessions", root / name / "calibration_store"


def set_sessions(protocol, name: str, first=None, pokes=None) -> list:
    """The set's sessions as SessionSpec (tools/train/build.py)."""
    from .build import SessionSpec

    return [SessionSpec(**d) for d in protocol.sessions(name, first, pokes)]


def record_set(protocol, name: str, root: Path, first=None, pokes=None, physics: str = "fe", size: int = 128) -> list[Path]:
    """Record the set's sessions (or the first units / pokes) with the twin; returns their folders."""
    from ..progress import stage_progress
    from ..twin.record import Recorder
    from ..twin.unit import write_true_calibration
    from .protocol import ProtocolError
    from .rig_estimate import prepare

    if name == "sealed" and (first or pokes):
        raise ProtocolError("units record sealed: the sealed set is recorded whole (no --first / --pokes)")
    sessions, store = set_paths(root, name)
    out = []
    specs = set_sessions(protocol, name, first, pokes)
    for i, spec in enumerate(specs):
        path = sessions / spec.name
        rec = Recorder(spec.record_config(physics, size), path, progress=stage_progress(spec.name))
        write_true_calibration(rec.unit, store, size)
        if (path / "session.json").is_file():
            log.info("[%s %d/%d] %s already recorded", name, i + 1, len(specs), spec.name)
        else:
            log.info("[%s %d/%d] recording %s (%d pokes, indenters %s)", name, i + 1, len(specs), spec.name,
                     spec.pokes, spec.trajectory["indenters"])
            rec.run()
        if spec.world == "rig":
            prepare(path)
        out.append(path)
    return out


def rim_check(serial: str, frames: int = 3, seed: int = 0) -> dict:
    """A twin unit's rim as stage 3 finds it (`crop = "rim"`: `fit_rim` on `frames` averaged rest frames,
    rendered with the unit's noise) against its true rim and the design's radius (px)."""
    import numpy as np

    from ...runtime.calib.rim import fit_rim, rest_image
    from ..twin.unit import TwinUnit, VariationConfig

    unit, nominal = TwinUnit(serial), TwinUnit(serial, variation=VariationConfig(0.0, 0.0, 0.0, 0.0))
    rng = np.random.default_rng(seed)
    fit = fit_rim(rest_image([unit.renderer.render(None, rng=rng) for _ in range(frames)]),
                  nominal.gel_center_px, nominal.gel_radius_px, where=f"{serial} rest frames")
    return {"serial": serial, "true_px": unit.gel_radius_px, "design_px": nominal.gel_radius_px, "rim_px": fit.radius,
            "centre_err_px": float(np.hypot(*(np.asarray(fit.center) - unit.gel_center_px)))}


def run(args: argparse.Namespace) -> int:
    from ...contracts.errors import TensorTouchError
    from .protocol import SET_NAMES, check_recipe_sessions, expand_recipe_sessions, load_protocol
    from .recipe import RECIPES_DIR, load_recipe

    try:
        protocol = load_protocol(args.protocol)
        for flag, v in (("--first", args.first), ("--pokes", args.pokes), ("--size", args.size)):
            if v is not None and v < 1:
                raise TensorTouchError(f"units: {flag} {v}; expected a positive integer")
        if args.set is not None and args.set not in SET_NAMES:
            raise TensorTouchError(f"units: set {args.set!r}; expected one of {', '.join(SET_NAMES)}")
        if args.action == "check":
            for path in sorted(RECIPES_DIR.glob("*.toml")):
                sessions = expand_recipe_sessions(protocol, load_recipe(path).doc.get("sessions") or {}, str(path))
                check_recipe_sessions(protocol, sessions, str(path))
            n = {k: len(v) for k, v in protocol.units.items()}
            print(f"protocol {protocol.hash}: {n} units, seed ranges {protocol.seed_ranges}; "
                  f"{len(list(RECIPES_DIR.glob('*.toml')))} recipe(s) agree with it")
        elif args.action == "list":
            for name in ([args.set] if args.set else SET_NAMES):
                for s in set_sessions(protocol, name):
                    print(f"{name:10s} {s.serial:10s} seed {s.seed:5d}  {s.pokes} pokes  "
                          f"{'+'.join(s.trajectory['indenters']):18s} q{s.quality}  world {s.world}")
        elif args.action == "rim":
            if args.set is None:
                raise TensorTouchError("units rim: name the set (train, validation or sealed)")
            errs = []
            for s in set_sessions(protocol, args.set, args.first):
                r = rim_check(s.serial)
                errs.append((r["rim_px"] - r["true_px"], r["design_px"] - r["true_px"]))
                print(f"{s.serial:10s} true rim {r['true_px']:7.2f} px  design {r['design_px']:7.2f} "
                      f"({errs[-1][1]:+.2f})  found {r['rim_px']:7.2f} ({errs[-1][0]:+.2f})  centre {r['centre_err_px']:.2f} px off")
            e = [abs(a) for a, _ in errs]
            d = [abs(b) for _, b in errs]
            print(f"{len(errs)} units: found - true |mean| {sum(e) / len(e):.2f}, max {max(e):.2f} px; "
                  f"design - true |mean| {sum(d) / len(d):.2f}, max {max(d):.2f} px")
        else:
            if args.set is None:
                raise TensorTouchError("units record: name the set (train, validation or sealed)")
            paths = record_set(protocol, args.set, units_root(args.root), args.first, args.pokes, args.physics, args.size)
            print(f"{len(paths)} session(s) of set {args.set} in {set_paths(units_root(args.root), args.set)[0]}")
    except TensorTouchError as exc:
        print(f"units: {exc}")
        return 2
    return 0


def unit_targets(protocol, name: str, root: Path, check_whole: bool) -> list[tuple]:
    """(name, session folder, calibration) of a recorded protocol set; `check_whole`: every unit of the
    set recorded with its full plan (the sealed set is scored whole)."""
    from ...contracts.errors import TensorTouchError
    from ...contracts.session import load_session
    from ...contracts.store import CalibrationStore

    sessions, store_root = set_paths(root, name)
    store = CalibrationStore(store_root)
    out = []
    for spec in set_sessions(protocol, name):
        path = sessions / spec.name
        if not (path / "session.json").is_file():
            if check_whole:
                raise TensorTouchError(f"{path} is not recorded; the {name} set is scored whole "
                                       f"(tensortouch train units record {name})")
            continue
        if check_whole:
            got = load_session(path, check_frames=False).manifest.get("provenance", {}).get("planned_pokes")
            if got != spec.pokes:
                raise TensorTouchError(f"{path} holds {got} planned pokes, the protocol {spec.pokes}; "
                                       f"the {name} set is scored whole")
        out.append((spec.name, path, store.load(spec.serial)))
    if not out:
        raise TensorTouchError(f"no session of set {name} recorded under {sessions} "
                               f"(tensortouch train units record {name})")
    return out
