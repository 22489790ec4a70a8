"""`tensortouch bench contacts`: the contact clustering step with and without the light-touch rule, with
the rule and merging, and with splitting too (tools/train/support.py), side by side in one run, on a unit's real
calibration tables (128² for the demo unit); with the model package's own settings (its manifest's
runtime.contacts through tools.scoring.contact_config: what `tensortouch run` clusters with), and with
those at a lower core threshold (`--low-threshold`, 0.00125 N: the int8 student's, issue #44).

Fields are synthetic contact-force maps (docs/runtime.md): a 1.5 N touch (σ = 4 px) with and without a
0.3 N light touch spread thinner than the strong threshold (σ = 5.5 px), and a sliding contact split
into two peaks 12 px apart (1.0 + 0.6 N, σ = 2 px) joined by a ridge below the core threshold, and two
heavy presses 22 px apart (4 + 3 N, σ = 6 px) whose fields join above it, plus 0.2 mN/pixel noise; and
a network's rest-frame rim (25 pixels on the gel's rim at 1–2 mN each), the same with a 2 N press, and
a 0.8 N press (σ = 6 px) in 0.6 mN/pixel noise (many weak pixels). Each configuration's mean over the
fields is printed last ("all fields").
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
    p.add_argument("--low-threshold", type=float, default=0.00125,
                   help="core threshold (N per pixel) of the sixth configuration: the package's settings otherwise")
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


def rim_field(cal, count: int = 25, level=(0.001, 0.002), noise_n: float = 2e-4, seed: int = 0) -> np.ndarray:
    """(3, H, W) noise plus `count` pixels on the gel's rim (the mask's border) at `level` N each."""
    import cv2

    mask = np.asarray(cal.mask, bool)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                      borderValue=0).astype(bool)
    rim = np.argwhere(mask & ~inner)
    rng = np.random.default_rng(seed)
    fp = touch_field(cal, [], noise_n, seed)
    for v, u in rim[rng.choice(len(rim), count, replace=False)]:
        fp[:, v, u] = rng.uniform(*level) * np.array([0.3, 0.2, -0.933])
    return fp


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
    spots = {"one touch": [(0.3 * w, 0.5 * h, 1.5, 4.0)],
             "one touch + light touch": [(0.3 * w, 0.5 * h, 1.5, 4.0), (0.7 * w, 0.47 * h, 0.3, 5.5)],
             "split sliding contact": [(0.45 * w, 0.5 * h, 1.0, 2.0), (0.45 * w + 12, 0.5 * h, 0.6, 2.0),
                                       (0.45 * w + 6, 0.5 * h, 0.045, 3.0)],
             "two presses joined": [(0.5 * w - 11, 0.5 * h, 4.0, 6.0), (0.5 * w + 11, 0.5 * h, 3.0, 6.0)]}
    fields = {name: touch_field(cal, t) for name, t in spots.items()}
    fields["rim noise"] = rim_field(cal)
    fields["press + rim noise"] = rim_field(cal, seed=1) + touch_field(cal, [(0.6 * w, 0.4 * h, 2.0, 5.0)], 0.0)
    fields["many weak pixels"] = touch_field(cal, [(0.5 * w, 0.5 * h, 0.8, 6.0)], noise_n=6e-4, seed=2)
    fields = {name: fp.astype(np.float32) for name, fp in fields.items()}     # the runtime's precision
    rule = ContactConfig(weak_threshold_n=args.weak, min_total_n=args.min_total)
    shipped = contact_config(package)
    cfgs = {"strong only": ContactConfig(), "with rule": rule, "rule+merge": replace(rule, merge_n=args.merge),
            "rule+merge+split": replace(rule, merge_n=args.merge, split_dip=args.split),
            "package": shipped, "package, low core": replace(shipped, threshold_n=args.low_threshold)}
    out = {"bench": "contacts", "sensor": args.sensor, "size": [h, w], "package": package.name, "rows": []}
    print(f"bench contacts ({args.sensor}, {h}x{w}, {args.frames} calls each)")
    mean = dict.fromkeys(cfgs, 0.0)
    for fname, fp in fields.items():
        ms = {}
        for cname, cfg in cfgs.items():
            ms[cname], found = _time(fp, args_, cfg, args.frames)
            mean[cname] += ms[cname] / len(fields)
            out["rows"].append({"field": fname, "config": cname, "ms": round(ms[cname], 4), "clusters_n": found})
            print(f"  {fname:24s} {cname:17s} {ms[cname]:.3f} ms  clusters |F| {found}")
        print(f"  {fname:24s} with rule / strong only: {ms['with rule'] / ms['strong only']:.2f}, "
              f"rule+merge / strong only: {ms['rule+merge'] / ms['strong only']:.2f}, "
              f"rule+merge+split / rule+merge: {ms['rule+merge+split'] / ms['rule+merge']:.2f}")
    out["mean_ms"] = {c: round(v, 4) for c, v in mean.items()}
    print("  all fields (mean)         " + ", ".join(f"{c} {v:.3f} ms" for c, v in mean.items()))
    if args.json:
        print(json.dumps(out))
    return 0
