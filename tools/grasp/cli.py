"""`tensortouch mount` (fingertip pose selection) and `tensortouch grasp` (selective grasp trials)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

DEFAULT_OUT = Path("cache/hand")


def _floats(text: str, name: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"--{name}: expected comma-separated numbers, got {text!r}") from None
    if not vals:
        raise SystemExit(f"--{name}: expected at least one number")
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
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_mount)


def cmd_mount(args) -> int:
    import numpy as np

    from runtime.errors import TensorTouchError
    from tools.grasp import figures, graph, hand_model, mount
    from tools.grasp.workspace import WorkspaceConfig

    if args.samples < 10:
        print(f"--samples: expected at least 10, got {args.samples}", file=sys.stderr)
        return 2
    cfg = mount.MountConfig(z_cm=_floats(args.z_cm, "z-cm"), pitch_deg=_floats(args.pitch_deg, "pitch-deg"),
                            workspace=WorkspaceConfig(samples=args.samples, seed=args.seed))
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
            g = graph.build(model, spec, (ch.z_cm, ch.pitch_deg), graph.GraphConfig(nodes=args.graph_nodes),
                            progress=lambda i, n: print(f"\r  contact graph: {i}/{n} nodes", end="",
                                                        file=sys.stderr, flush=True))
            print(file=sys.stderr)
            graph.save(g, out / "contact_graph.npz")
            summary["graph"] = {"nodes": len(g), "edges": len(g.edges)}
        hand_model.atomic_write_bytes(out / "mount.json", (json.dumps(summary, indent=1) + "\n").encode())
    except TensorTouchError as exc:
        print(f"tensortouch mount: {exc}", file=sys.stderr)
        return 2
    print(f"chosen: z = {ch.z_cm:g} cm, pitch = {ch.pitch_deg:g}° (mean w {ch.mean_w:.3g}, {ch.inliers} inliers "
          f"of {ch.n_contacts} contacts); {len(res.variants)} variants × {args.samples} configurations in "
          f"{res.seconds:.1f} s; wrote {out}/mount.json, mount_heatmaps.png, mount_contacts_3d.png, "
          f"hand_mounted.urdf" + (", contact_graph.npz" if args.graph_nodes > 0 else ""))
    return 0
