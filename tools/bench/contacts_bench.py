"""`tensortouch bench contacts`: the contact clustering step with and without the light-touch rule, with
the rule and merging, and with splitting too (tools/train/support.py), side by side in one run, on a unit's real
calibration tables (128² for the demo unit); and with the model package's own settings (its manifest's
runtime.contacts through tools.scoring.contact_config: what `tensortouch run` clusters with).

Fields are synthetic contact-force maps (docs/runtime.md): a 1.5 N touch (σ = 4 px) with and without a
0.3 N light touch spread thinner than the strong threshold (σ = 5.5 px), and a sliding contact split
into two peaks 12 px apart (1.0 + 0.6 N, σ = 2 px) joined by a ridge below the core threshold, and two
heavy presses 22 px apart (4 + 3 N, σ = 6 px) whose fields join above it, plus 0.2 mN/pixel noise.
"""
from __future__ import annotations

import json
import time
from dataclasses import replace

import numpy as np


def add_arguments(p) -> None:
    p.add_argument("--store", default="calibration_store", help="calibration store root")
    p.add_argument("--sensor", default="TWIN-DEMO", help="sensor whose calibration (tables) the clustering uses")
    p.add_argument("--frames", type=int, default=500, help="timed calls per configuration and field")
    p.add_argument("--weak", type=float, default=0.0012, help="weak threshold (N per pixel)")
    p.add_argument("--min-total", type=float, default=0.041, help="min_total_n (N)")
    p.add_argument("--merge", type=float, default=0.0012, help="merge_n (N per pixel) of the third configuration")
    p.add_argument("--split", type=float, default=0.5, help="split_dip of the fourth configuration (with merging)")
    p.add_argument("--model", help="model package (name or folder) whose contact settings are the fifth "
                                   "configuration (default: the newest installed)")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")


def touch_field(cal, touches, noise_n: float = 2e-4, seed: int = 0) -> np.ndarray:
    """(3, H, W) contact force per pixel (N) of Gaussian touches [(u, v, |F| N, σ px)] into the gel."""
    h, w = cal.model_size
    yy, xx = np.mgrid[0:h, 0:w]
    fp = np.zeros((3, h, w))
    for u, v, f, s in touches:
        g = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * s * s)) * cal.mask
        fp[2] -= f * g / g.sum()
    return fp + np.random.default_rng(seed).normal(0.0, noise_n, fp.shape) * cal.mask


def _time(fp, args_, cfg, n: int) -> tuple[float, list]:
    from ...runtime.stages.contacts import find_clusters

    for _ in range(20):
        cl = find_clusters(fp, *args_, cfg=cfg)
    t0 = time.perf_counter()
    for _ in range(n):
        find_clusters(fp, *args_, cfg=cfg)
    return (time.perf_counter() - t0) / n * 1e3, [round(c.force_mag_n, 3) for c in cl]


def run(args) -> int:
    from ...contracts.store import CalibrationStore
    from ...runtime.stages.contacts import ContactConfig
    from ...runtime.stages.model import find_package
    from ..scoring import contact_config

    cal = CalibrationStore(args.store).load(args.sensor)
    package = find_package(getattr(args, "model", None))
    args_ = (cal.surface_xyz, cal.normals, cal.pixel_area, cal.mask)
    h, w = cal.model_size
    fields = {"one touch": [(0.3 * w, 0.5 * h, 1.5, 4.0)],
              "one touch + light touch": [(0.3 * w, 0.5 * h, 1.5, 4.0), (0.7 * w, 0.47 * h, 0.3, 5.5)],
              "split sliding contact": [(0.45 * w, 0.5 * h, 1.0, 2.0), (0.45 * w + 12, 0.5 * h, 0.6, 2.0),
                                        (0.45 * w + 6, 0.5 * h, 0.045, 3.0)],
              "two presses joined": [(0.5 * w - 11, 0.5 * h, 4.0, 6.0), (0.5 * w + 11, 0.5 * h, 3.0, 6.0)]}
    rule = ContactConfig(weak_threshold_n=args.weak, min_total_n=args.min_total)
    cfgs = {"strong only": ContactConfig(), "with rule": rule, "rule+merge": replace(rule, merge_n=args.merge),
            "rule+merge+split": replace(rule, merge_n=args.merge, split_dip=args.split),
            "package": contact_config(package)}
    out = {"bench": "contacts", "sensor": args.sensor, "size": [h, w], "package": package.name, "rows": []}
    print(f"bench contacts ({args.sensor}, {h}x{w}, {args.frames} calls each)")
    for fname, touches in fields.items():
        fp = touch_field(cal, touches)
        ms = {}
        for cname, cfg in cfgs.items():
            ms[cname], found = _time(fp, args_, cfg, args.frames)
            out["rows"].append({"field": fname, "config": cname, "ms": round(ms[cname], 4), "clusters_n": found})
            print(f"  {fname:24s} {cname:16s} {ms[cname]:.3f} ms  clusters |F| {found}")
        print(f"  {fname:24s} with rule / strong only: {ms['with rule'] / ms['strong only']:.2f}, "
              f"rule+merge / strong only: {ms['rule+merge'] / ms['strong only']:.2f}, "
              f"rule+merge+split / rule+merge: {ms['rule+merge+split'] / ms['rule+merge']:.2f}")
    if args.json:
        print(json.dumps(out))
    return 0
