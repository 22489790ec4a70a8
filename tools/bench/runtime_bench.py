"""`tensortouch bench runtime`: the deploy frame loop, int8 vs fp32, side by side in one run.

Per configuration (model size × precision): frames are decoded from an MJPG video (real OpenCV
capture), run through `SensorPipeline` (the exact deploy code) and published over a real Zenoh
session on loopback; per-stage and end-to-end p50/p99 latency and frames/s are printed. The network
is the shipped model when one is installed at that size, else a synthetic ~2.2 M-parameter conv
U-Net with a 4×4 patch stem (Hiera-like compute) (random weights: timing only — said in the output).
"""
from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def synthetic_frames(n: int, width: int = 320, height: int = 240, seed: int = 0) -> list[np.ndarray]:
    """Gel-like RGB frames: dot pattern, LED shading, a blob pressing and sliding."""
    import cv2

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    cx, cy, r = width / 2, height / 2, min(width, height) * 0.45
    base = np.zeros((height, width, 3), np.float32)
    base[..., 0] = 90 + 40 * (xx / width)
    base[..., 1] = 110 + 30 * (yy / height)
    base[..., 2] = 140
    dots = rng.uniform([cx - r, cy - r], [cx + r, cy + r], size=(300, 2))
    frames = []
    for k in range(n):
        phase = k / max(n - 1, 1)
        depth = max(0.0, np.sin(phase * 2 * np.pi * 3))
        bx, by = cx + 0.4 * r * np.cos(phase * 6), cy + 0.3 * r * np.sin(phase * 4)
        img = base.copy()
        blob = depth * np.exp(-((xx - bx) ** 2 + (yy - by) ** 2) / (2 * (0.12 * r) ** 2))
        img += 60 * blob[..., None]
        shift = 6 * blob
        for (dx, dy) in dots:
            ix, iy = int(dx + shift[int(dy), int(dx)]), int(dy)
            cv2.circle(img, (ix, iy), 2, (20, 20, 20), -1)
        img[(xx - cx) ** 2 + (yy - cy) ** 2 > r * r] = 0
        img += rng.normal(0, 1.5, img.shape).astype(np.float32)
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
    return frames


def write_video(frames: list[np.ndarray], path: Path, fps: float = 60.0) -> Path:
    import cv2

    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    vw.release()
    return path


def _calibration(root: Path, sensor: str, size: int, width: int, height: int):
    from runtime.calibration import CalibrationStore
    from runtime.geometry import DomeProfile, equidistant_theta_phi, surface_tables

    theta, phi = equidistant_theta_phi((size, size), np.deg2rad(100))
    tables = surface_tables(theta, phi, DomeProfile())
    meta = {"camera": {"width": width, "height": height}, "gel_center_px": [width / 2, height / 2],
            "gel_radius_px": min(width, height) * 0.45, "model_size": [size, size],
            "provenance": {"method": "nominal (benchmark)"}}
    store = CalibrationStore(root)
    store.write(sensor, tables, meta)
    return store.load(sensor)


def _package_for(size: int, work: Path):
    """(package, synthetic?) — the shipped model at this size if installed, else a synthetic one."""
    from runtime.model import installed_packages, load_package
    from tools.bench.models import write_package

    for folder in installed_packages():
        try:
            pkg = load_package(folder)
        except Exception:
            continue
        if pkg.size == (size, size) and not pkg.manifest.get("synthetic"):
            return pkg, False
    return load_package(write_package(work / f"synthetic-{size}", size=size, width=32, depth=3, stem=4)), True


def bench_config(pkg, precision: str, video: Path, cal, frames: int, threads: int, publisher) -> dict:
    from drivers.camera import camera_from_uri
    from runtime.loop import LoopConfig, SensorLoop
    from runtime.model import FieldModel
    from runtime.pipeline import SensorPipeline

    model = FieldModel(pkg, precision, threads=threads)
    pipe = SensorPipeline(cal.sensor_id, model, cal)
    cam = camera_from_uri(f"file:{video}", realtime=False, loop=True)
    loop = SensorLoop(cam, pipe, publisher, LoopConfig(status_every_s=1.0))
    loop.latency.n = frames
    with cam:
        loop.run(max_frames=pipe.cfg.baseline.startup_frames + 5)  # warm-up, baseline
        loop.latency = type(loop.latency)(frames)
        loop.frames = 0
        t0 = time.perf_counter()
        loop.run(max_frames=frames)
        wall = time.perf_counter() - t0
    s = loop.latency.summary()
    return {"frames": frames, "hz": frames / wall,
            "stages": {k: {"p50_ms": round(v["p50"], 3), "p99_ms": round(v["p99"], 3)} for k, v in s.items()}}


def run(args) -> int:
    from runtime.publisher import Publisher

    sizes = [int(s) for s in args.sizes.split(",")]
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        frames = synthetic_frames(120)
        video = write_video(frames, work / "bench.avi")
        h, w = frames[0].shape[:2]
        with Publisher("bench-0", listen=["tcp/127.0.0.1:0"]) as pub:
            for size in sizes:
                pkg, synthetic = _package_for(size, work)
                cal = _calibration(work / f"cal{size}", "bench-0", size, w, h)
                params = pkg.manifest.get("metrics", {}).get("params")
                for precision in ("fp32", "int8"):
                    r = bench_config(pkg, precision, video, cal, args.frames, args.threads, pub)
                    r.update(model=pkg.name, synthetic=synthetic, params=params)
                    results[f"{size}/{precision}"] = r
    print(f"runtime benchmark — {args.frames} frames per config, {args.threads} onnxruntime thread(s), "
          f"capture = MJPG {w}x{h} decode, publish = Zenoh loopback; cpu count {os.cpu_count()}")
    for key, r in results.items():
        tag = " (synthetic weights, timing only)" if r["synthetic"] else ""
        tot = r["stages"]["end_to_end"]
        print(f"\n{key}: {r['model']}{tag}, params {r['params']}: {r['hz']:.1f} frames/s, "
              f"end-to-end p50 {tot['p50_ms']:.2f} ms p99 {tot['p99_ms']:.2f} ms")
        for stage, v in r["stages"].items():
            if stage not in ("total", "end_to_end"):
                print(f"    {stage:<11} p50 {v['p50_ms']:7.3f} ms   p99 {v['p99_ms']:7.3f} ms")
    print("\nint8 vs fp32 (same run):")
    for size in sizes:
        f, q = results[f"{size}/fp32"], results[f"{size}/int8"]
        print(f"  {size}²: inference p50 {f['stages']['inference']['p50_ms']:.2f} → "
              f"{q['stages']['inference']['p50_ms']:.2f} ms "
              f"(×{f['stages']['inference']['p50_ms'] / q['stages']['inference']['p50_ms']:.2f}), "
              f"end-to-end {f['hz']:.1f} → {q['hz']:.1f} frames/s")
    shipped = f"{max(sizes)}/int8"
    summary = {"config": shipped, "end_to_end_hz": round(results[shipped]["hz"], 2),
               "p99_ms": results[shipped]["stages"]["end_to_end"]["p99_ms"],
               "synthetic_weights": results[shipped]["synthetic"],
               "results": results}
    if args.json:
        print(json.dumps(summary))
    return 0


def add_arguments(p) -> None:
    p.add_argument("--sizes", default="96,128", help="model input sizes, comma separated")
    p.add_argument("--frames", type=int, default=200, help="timed frames per configuration")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
