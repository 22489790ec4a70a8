"""`tensortouch mount` (fingertip pose selection) and `tensortouch grasp` (selective grasp trials)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

DEFAULT_OUT = Path("cache/hand")


def _floats(text: str, name: str) -> tuple[float, ...]:
    """Comma-separated numbers of option --`name`; ValueError naming the option otherwise."""
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--{name}: expected comma-separated numbers, got {text!r}") from None
    return vals


def register(sub) -> None:
    p = sub.add_parser("mount", help="choose where to mount the thumb's sensor on a hand URDF (Pinocchio + coal)",
                       description="Sweep the thumb distal joint over z-offset × pitch, sample thumb+index "
                                   "configurations, keep thumb–index contacts (coal, shrunk fingertip spheres), "
                                   "score mean manipulability and principal-axis inliers, write the heatmaps, "
                                   "a 3D figure, the chosen variant (JSON), its URDF and the contact graph.")
    p.add_argument("--urdf", help="hand URDF (default: the Allegro right hand from example-robot-data)")
    p.add_argument("--out", default=str(DEFAULT_OUT), help=f"output folder (default {DEFAULT_OUT})")
    p.add_argument("--samples", type=int, default=10_000, help="joint configurations per variant (default 10000)")
    p.add_argument("--z-cm", default="3.5,3.9,4.3,4.7,5.1,5.5", help="thumb distal z-offsets in cm")
    p.add_argument("--pitch-deg", default="-30,-20,-10,0,10,20,30", help="thumb distal pitches in degrees")
    p.add_argument("--graph-nodes", type=int, default=2700, help="contact-graph nodes (0: no graph)")
    p.add_argument("--refine-nodes", type=int, default=1300,
                   help="extra contact-graph nodes around the start pinch (default 1300; 0: none)")
    p.add_argument("--refine-radius-mm", type=float, default=14.0,
                   help="the refined region: pinch points within this of the start pinch (default 14)")
    p.add_argument("--seed", type=int, default=0, help="seed of the joint-configuration samples")
    p.set_defaults(func=cmd_mount, extra="hand")

    g = sub.add_parser("grasp", help="selective grasp trials in simulation, closed through the sensor runtime",
                       description="MuJoCo trials of the seed's selective grasp: two objects pinched between "
                                   "thumb and index, one pulled; the simulated fingertip sensors render frames "
                                   "that the runtime turns into contacts on Zenoh; the controller subscribes, "
                                   "decides which object moved and follows the contact graph. Writes the table "
                                   "of success / false detection / other beside the seed's.")
    g.add_argument("--pair", action="append", choices=["A+A", "A+B", "cable+rigid", "rigid+rigid"],
                   help="object pair (repeatable; default: all four)")
    g.add_argument("--trials", type=int, default=20, help="trials per pair (default 20)")
    g.add_argument("--hand", default=str(DEFAULT_OUT),
                   help=f"folder of `tensortouch mount`'s outputs: hand_mounted.urdf, contact_graph.npz "
                        f"(default {DEFAULT_OUT}; made by `tensortouch mount` when missing)")
    g.add_argument("--out", default=str(DEFAULT_OUT), help="where the table, trials JSON and pictures go")
    g.add_argument("--model", help="model package folder or name (default: TrialConfig.model, hiera-qup-128, the package "
                                   "the controller was tuned with)")
    g.add_argument("--seed", type=int, default=0, help="first trial seed")
    g.add_argument("--picture", action="store_true", help="draw the first trial as a picture sequence")
    g.add_argument("--randomize", action="store_true",
                   help="draw each trial's task from the task distribution (tools/grasp/task.py: placement ±5 mm, "
                        "yaw ±15°, diameters, pull force and direction, friction, soft or stiff contact) instead of "
                        "the fixed scene")
    g.add_argument("--arm", action="store_true",
                   help="the hand's palm on an arm that translates it (TrialConfig.arm): with --randomize the arm "
                        "brings the start pinch to where the objects are seen, and the controller's goals may move it")
    g.add_argument("--squeeze-mm", default="0",
                   help="close the pinch this far past the graph's touching poses, each fingertip (TrialConfig.squeeze_mm; "
                        "default 0)")
    g.add_argument("--merge", nargs="+", action="extend", metavar="DIR",
                   help="run no trials: merge the grasp_trials.json of these earlier --out folders (e.g. one run "
                        "per seed range) into one table and trials file in --out")
    g.add_argument("--perception", action="store_true",
                   help="run no trials: the table of what the fingertip sensor publishes for two parallel objects "
                        "of each diameter pressed side by side to each depth (grasp_perception.md in --out)")
    g.add_argument("--diameters-mm", default="1,1.5,2,3,6,8", help="with --perception: object diameters")
    g.add_argument("--depths-mm", default="0.25,0.5,1", help="with --perception: depths into the gel")
    g.set_defaults(func=cmd_grasp, extra="hand")


def _extra_missing() -> str | None:
    import importlib.util

    missing = [m for m in ("pinocchio", "coal", "mujoco", "matplotlib") if importlib.util.find_spec(m) is None]
    if not missing:
        return None
    from ...contracts.extras import hint

    return hint("hand", ", ".join(missing))


def cmd_mount(args) -> int:
    import numpy as np

    why = _extra_missing()
    if why:
        print(f"tensortouch mount: {why}", file=sys.stderr)
        return 2

    from ...contracts.errors import TensorTouchError
    from ...contracts.files import atomic_write
    from . import figures, graph, hand_model, mount
    from .workspace import WorkspaceConfig

    if args.samples < 10:
        print(f"--samples: expected at least 10, got {args.samples}", file=sys.stderr)
        return 2
    if not args.refine_radius_mm > 0:
        print(f"--refine-radius-mm: expected a positive number, got {args.refine_radius_mm}", file=sys.stderr)
        return 2
    try:
        cfg = mount.MountConfig(z_cm=_floats(args.z_cm, "z-cm"), pitch_deg=_floats(args.pitch_deg, "pitch-deg"),
                                workspace=WorkspaceConfig(samples=args.samples, seed=args.seed))
    except ValueError as exc:
        print(f"tensortouch mount: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)

    def progress(i, n, v):
        print(f"\r  variant {i}/{n}: z {v.z_cm:g} cm, pitch {v.pitch_deg:+g}°, {v.n_contacts} contacts, "
              f"{v.inliers} inliers   ", end="\n" if i == n else "", file=sys.stderr, flush=True)

    try:
        urdf = Path(args.urdf) if args.urdf else hand_model.default_urdf()
        res = mount.select(urdf, cfg=cfg, progress=progress)
        spec = hand_model.HandSpec()
        ch = res.chosen
        figures.heatmaps(res, out / "mount_heatmaps.png")
        figures.contacts_3d(res, out / "mount_contacts_3d.png")
        hand_model.write_urdf(urdf, out / "hand_mounted.urdf", spec, ch.z_cm / 100, np.radians(ch.pitch_deg))
        summary = {"urdf": str(urdf), "chosen": {"z_cm": ch.z_cm, "pitch_deg": ch.pitch_deg,
                                                 "mean_manipulability": ch.mean_w, "contacts": ch.n_contacts,
                                                 "inliers": ch.inliers},
                   "samples_per_variant": args.samples, "seconds": round(res.seconds, 2),
                   "grid": {"z_cm": list(cfg.z_cm), "pitch_deg": list(cfg.pitch_deg),
                            "mean_manipulability": res.grid("mean_w").tolist(),
                            "inliers": res.grid("inliers").astype(int).tolist(),
                            "contacts": res.grid("n_contacts").astype(int).tolist()}}
        if args.graph_nodes > 0:
            model = hand_model.load(urdf, spec)
            hand_model.apply_variant(model, spec, hand_model.nominal_placement(model, spec),
                                     ch.z_cm / 100, np.radians(ch.pitch_deg))
            gcfg = graph.GraphConfig(nodes=args.graph_nodes, refine_nodes=max(0, args.refine_nodes),
                                     refine_radius_mm=args.refine_radius_mm)
            g = graph.build(model, spec, (ch.z_cm, ch.pitch_deg), gcfg,
                            progress=lambda i, n: print(f"\r  contact graph: {i}/{n} nodes", end="",
                                                        file=sys.stderr, flush=True))
            print(file=sys.stderr)
            graph.save(g, out / "contact_graph.npz")
            summary["graph"] = {"nodes": len(g), "edges": len(g.edges)}
        atomic_write(out / "mount.json", (json.dumps(summary, indent=1) + "\n").encode())
    except TensorTouchError as exc:
        print(f"tensortouch mount: {exc}", file=sys.stderr)
        return 2
    print(f"chosen: z = {ch.z_cm:g} cm, pitch = {ch.pitch_deg:g}° (mean w {ch.mean_w:.3g}, {ch.inliers} inliers "
          f"of {ch.n_contacts} contacts); {len(res.variants)} variants × {args.samples} configurations in "
          f"{res.seconds:.1f} s; wrote {out}/mount.json, mount_heatmaps.png, mount_contacts_3d.png, "
          f"hand_mounted.urdf" + (", contact_graph.npz" if args.graph_nodes > 0 else ""))
    return 0


def cmd_grasp(args) -> int:
    import time

    from ...contracts.errors import TensorTouchError
    from . import trial

    if args.merge:
        return _merge([Path(d) for d in args.merge], Path(args.out))
    if args.perception:
        return _perception(args)
    if args.trials < 1:
        print(f"--trials: expected at least 1, got {args.trials}", file=sys.stderr)
        return 2
    try:
        squeeze = float(args.squeeze_mm)
    except ValueError:
        squeeze = float("nan")
    if not 0 <= squeeze <= 5:
        print(f"tensortouch grasp: --squeeze-mm: expected one number from 0 to 5 (mm), got {args.squeeze_mm!r}",
              file=sys.stderr)
        return 2
    why = _extra_missing()
    if why:
        print(f"tensortouch grasp: {why}", file=sys.stderr)
        return 2
    hand, out = Path(args.hand), Path(args.out)
    graph_path, urdf = hand / "contact_graph.npz", hand / "hand_mounted.urdf"
    try:
        if not graph_path.is_file() or not urdf.is_file():
            print(f"tensortouch grasp: no mounted hand in {hand}; running `tensortouch mount --out {hand}` first",
                  file=sys.stderr)
            import argparse

            margs = argparse.Namespace(urdf=None, out=str(hand), samples=10_000, z_cm="3.5,3.9,4.3,4.7,5.1,5.5",
                                       pitch_deg="-30,-20,-10,0,10,20,30", graph_nodes=2700, refine_nodes=1300,
                                       refine_radius_mm=14.0, seed=0)
            if cmd_mount(margs) != 0:
                return 2
        bench = trial.Bench(graph_path, urdf, cfg=trial.TrialConfig(randomize=args.randomize, arm=args.arm, squeeze_mm=squeeze), model=args.model)
    except TensorTouchError as exc:
        print(f"tensortouch grasp: {exc}", file=sys.stderr)
        return 2
    pairs = args.pair or list(trial.PAPER)
    results: dict = {}
    t0 = time.monotonic()
    try:
        for pair in pairs:
            results[pair] = []
            for i in range(args.trials):
                frames = [] if (args.picture and i == 0 and pair == pairs[0]) else None
                r = bench.trial(pair, args.seed + i, frames)
                results[pair].append(r)
                n_ok = sum(x.outcome == "success" for x in results[pair])
                why = f" ({trial.failure_class(r)})" if r.outcome == "other" else ""
                print(f"  {pair} trial {i + 1}/{args.trials}: pulled {r.pulled}, judged {r.judged}, {r.outcome}{why} "
                      f"({r.seconds:.1f} s; {n_ok} successes so far; {time.monotonic() - t0:.0f} s total)",
                      file=sys.stderr, flush=True)
                if frames:
                    from .pictures import trial_sequence

                    trial_sequence(frames, r, out / f"grasp_trial_{pair.replace('+', '_')}.png")
                trial.save_results(results, out)
    finally:
        bench.close()
    print(trial.table(results) + ("\n" + trial.factor_table(results) if args.randomize else ""), end="")
    print(f"wrote {out}/grasp_table.md and grasp_trials.json", file=sys.stderr)
    return 0


def _merge(dirs: list[Path], out: Path) -> int:
    """`tensortouch grasp --merge DIR ...`: one table from several runs' grasp_trials.json."""
    from . import trial

    results: dict = {}
    for d in dirs:
        path = d / "grasp_trials.json"
        try:
            body = json.loads(path.read_text())
            for pair, rows in body.items():
                if pair not in trial.PAPER:
                    raise ValueError(f"unknown pair {pair!r}")
                results.setdefault(pair, []).extend(trial.TrialResult(**r) for r in rows)
        except (OSError, ValueError, TypeError, AttributeError) as exc:
            print(f"tensortouch grasp --merge: {path}: expected the grasp_trials.json of a `tensortouch grasp` run "
                  f"({exc})", file=sys.stderr)
            return 2
    out.mkdir(parents=True, exist_ok=True)
    trial.save_results(results, out)
    randomized = any(r.randomized for rs in results.values() for r in rs)
    print(trial.table(results) + ("\n" + trial.factor_table(results) if randomized else ""), end="")
    print(f"merged {sum(len(r) for r in results.values())} trials from {len(dirs)} runs; wrote {out}/grasp_table.md "
          f"and grasp_trials.json", file=sys.stderr)
    return 0


def _perception(args) -> int:
    """`tensortouch grasp --perception`: what the fingertip sensor publishes for two parallel objects."""
    from ...contracts.errors import TensorTouchError
    from ...contracts.files import atomic_write
    from ...contracts.store import CalibrationStore
    from ...runtime.stages.model import find_package
    from ..twin.unit import TwinUnit
    from . import perception, trial

    try:
        cfg = perception.PerceptionConfig(diameters_mm=_floats(args.diameters_mm, "diameters-mm"),
                                          depths_mm=_floats(args.depths_mm, "depths-mm"))
    except ValueError as exc:
        print(f"tensortouch grasp --perception: {exc}", file=sys.stderr)
        return 2
    tc = trial.TrialConfig()
    try:
        package = find_package(args.model or tc.model)
        cal = CalibrationStore().load(tc.sensor_unit)
        rows = perception.run(package, cal, TwinUnit(tc.sensor_unit), cfg, tc.sensor_unit)
    except TensorTouchError as exc:
        print(f"tensortouch grasp --perception: {exc}", file=sys.stderr)
        return 2
    text = perception.table(rows, package.name)
    out = Path(args.out)
    atomic_write(out / "grasp_perception.md", text.encode())
    print(text, end="")
    print(f"wrote {out}/grasp_perception.md", file=sys.stderr)
    return 0
