"""Twin-only diagnostics of stage 2 (resolve): how the FE re-solved from measured keypoints agrees with
the twin's own physics (its plan's FE solves, read from truth/ and the twin FE cache). Nothing in the
build reads this module; it backs the numbers in docs/train.md.

    tensortouch train resolve-check [--recipe hiera-qup-128] [--sessions NAME ...] [--out FILE]
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def compare_session(b, spec, reference: str = "recorded") -> list[dict]:
    """Per re-solved period and FE frame inside the twin poke's keypoint span: force of each indenter
    (re-solved vs the twin's nominal FE reaction, N) and surface displacement difference (mm).

    reference "recorded": the solves the twin recorded the session with (truth.json `fe_scenarios`: the
    physics of the images and F/T); "plan": the twin's plan solved with the CURRENT tools.fe (isolates
    what building scenarios from measured keypoints costs from any FE change since the recording)."""
    import json as _json

    from ..fe import load_result
    from ..twin.fe_physics import from_fe_result
    from ..twin.geometry import GelSurface
    from ..twin.physics import interpolate
    from ..twin.record import make_physics
    from .sources import recorder, resolved_sources

    rec = recorder(b, spec)
    physics = make_physics(rec.cfg, rec.unit)
    recorded = _json.loads((b.session(spec) / "truth" / "truth.json").read_text())["fe_scenarios"]
    rows = []
    for src in resolved_sources(b, spec):
        t_mid = 0.5 * (src.times[0] + src.times[-1])
        pi = int(np.argmin([0.0 if p.times[0] <= t_mid <= p.times[-1] else min(abs(p.times[0] - t_mid), abs(p.times[-1] - t_mid))
                            for p in rec.plan]))
        poke = rec.plan[pi]
        if reference == "recorded":
            twin = from_fe_result(load_result(physics.cache / f"{recorded[pi]}.npz"), GelSurface.from_fe(physics.gel))
        else:
            twin = physics.solve(poke)
        res = src.result
        sn = np.asarray(res.surface_nodes)
        same_mesh = twin.nodes.shape == np.asarray(res.nodes)[sn].shape and np.allclose(twin.nodes, np.asarray(res.nodes)[sn])
        for j, t in enumerate(src.times):
            if not (poke.times[0] <= t <= poke.times[-1]):
                continue
            tt = np.array([t])
            rf_t = interpolate(twin, poke, tt, "RF")[0]
            row = {"session": spec.name, "period": src.period, "poke": pi, "kind": poke.kind, "t": float(t),
                   "keypoint": bool(src.is_keypoint[j])}
            for k, slot in enumerate(src.slots):
                if slot in poke.slots:
                    kt = poke.slots.index(slot)
                    row.setdefault("force_twin", []).append(rf_t[kt].tolist())
                    row.setdefault("force_resolved", []).append(np.asarray(res.RF)[j, k].tolist())
            if same_mesh:
                u_t = interpolate(twin, poke, tt, "U")[0]
                d = np.linalg.norm(np.asarray(res.U)[j][sn] - u_t, axis=1)
                row.update(u_diff_max=float(d.max()), u_diff_rms=float(np.sqrt(np.mean(d ** 2))),
                           u_max=float(np.linalg.norm(u_t, axis=1).max()))
            rows.append(row)
    return rows


def label_coverage(b, spec) -> dict:
    """Camera frames with labels: twin poke windows (truth/frames.csv) vs the resolve path (labels.py:
    all frames in the FE spans, of which at a stage-1 keypoint — the seed's labels-at-keypoints)."""
    from ...contracts.session import load_session, read_table
    from .labels import BUSY_ID, frame_labels, keypoint_frame_share
    from .resolve import PoseTrack
    from .sources import resolved_sources

    ses = load_session(b.session(spec), check_frames=False)
    fr = ses.table("frames")
    poses = ses.table("poses")
    tracks = {int(k): PoseTrack.from_table(poses, int(k)) for k in np.unique(poses[:, 1])}
    src = resolved_sources(b, spec)
    lab, _ = frame_labels(fr[:, 0], src, tracks, ses.table("wrench"))
    truth = read_table(b.session(spec) / "truth" / "frames.csv", ["t", "index", "poke", "sigma"])
    share = keypoint_frame_share(fr[:, 0], lab, src)
    return {"twin_poke_frames": int((truth[:, 2] >= 0).sum()), "twin_pokes": int(len(set(truth[truth[:, 2] >= 0, 2]))),
            "periods": len(src), **share, "busy_frames": int((lab >= BUSY_ID).sum()),
            "labelled_in_twin_window": int(((lab >= 0) & (lab < BUSY_ID) & (truth[:, 2] >= 0)).sum())}


def summarize(rows: list[dict], contact_n: float = 0.5) -> dict:
    """Force error (N) per component and magnitude over frames where the twin force ≥ contact_n, and
    displacement differences (mm) over the same frames."""
    ft, fr, ud, um, ur = [], [], [], [], []
    for r in rows:
        for a, c in zip(r.get("force_twin", []), r.get("force_resolved", [])):
            if np.linalg.norm(a) >= contact_n:
                ft.append(a)
                fr.append(c)
                if "u_diff_max" in r:
                    ud.append(r["u_diff_max"])
                    ur.append(r["u_diff_rms"])
                    um.append(r["u_max"])
    if not ft:
        return {"frames": 0}
    ft, fr = np.array(ft), np.array(fr)
    err = fr - ft
    mag = np.linalg.norm(fr, axis=1) - np.linalg.norm(ft, axis=1)
    return {"frames": int(len(ft)), "force_twin_mean_n": float(np.linalg.norm(ft, axis=1).mean()),
            "force_err_mae_n": np.abs(err).mean(0).round(4).tolist(), "force_mag_mae_n": float(np.abs(mag).mean()),
            "force_mag_rel_mae": float(np.mean(np.abs(mag) / np.linalg.norm(ft, axis=1))),
            "force_mag_p95_n": float(np.percentile(np.abs(mag), 95)),
            "u_diff_max_mm": {"median": float(np.median(ud)), "p95": float(np.percentile(ud, 95))} if ud else None,
            "u_diff_rms_mm": {"median": float(np.median(ur))} if ur else None,
            "u_max_mm": {"median": float(np.median(um))} if um else None}


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--recipe", default="hiera-qup-128", help="recipe whose build is checked (name, .toml or manifest)")
    ap.add_argument("--root", help="build folder (default: <cache>/train/<recipe name>/)")
    ap.add_argument("--sessions", nargs="*", help="only these sessions (default: all with FE labels)")
    ap.add_argument("--out", help="write the rows and summaries as JSON here")
    ap.add_argument("--reference", choices=("recorded", "plan"), default="recorded",
                    help="recorded: the twin's recorded solves (truth); plan: its plan with the current tools.fe")


def run(args: argparse.Namespace) -> int:
    from .build import recipe_build

    b = recipe_build(args.recipe, (), args.root)
    rows, cover = [], {}
    for spec in b.all_sessions():
        if args.sessions and spec.name not in args.sessions:
            continue
        if not (b.root / "fe" / f"{spec.name}.json").is_file():
            continue
        rows += compare_session(b, spec, args.reference)
        cover[spec.name] = label_coverage(b, spec)
    tot = {k: sum(c[k] for c in cover.values()) for k in next(iter(cover.values()), {})}
    out = {"summary": summarize(rows), "summary_keypoints_only": summarize([r for r in rows if r["keypoint"]]),
           "label_frames_total": tot, "label_frames": cover, "rows": rows}
    text = json.dumps(out, indent=1)
    if args.out:
        Path(args.out).write_text(text)
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}, indent=1))
    return 0

