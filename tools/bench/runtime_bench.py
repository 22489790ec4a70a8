"""`tensortouch bench runtime`: the deploy frame loop, int8 vs fp32, side by side in one run.

Per configuration (model size × precision): frames are decoded from an MJPG video (real OpenCV
capture), run through `SensorPipeline` (the exact deploy code) and published over a real Zenoh
session on loopback; per-stage and end-to-end p50/p99 latency, frames/s and CPU time per frame
(the main thread's; with one onnxruntime thread inference runs on it) are printed. `--source`
chooses the frames: `demo` (default; the shipped demo recording, twin frames of one unit with rest
and contact, through that unit's calibration; packages at its model size only) or `synthetic` (a
drawn gel with a blob pressing and sliding in every frame, at any size; no trained network has seen
such frames, and the contacts stage then times whatever clusters the network makes of them — the
output prints clusters per frame). Configurations
run in alternating chunks so that load from other processes hits them alike. The network is the
shipped model when one is installed at that size, else a synthetic ~2.2 M-parameter conv U-Net
with a 4×4 patch stem (random weights: timing only — said in the output). Shipped packages are
int8 only: the fp32 graph comes from the build cache or is re-exported from the checkpoint
(`fp32_package`), and the output says which.
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
    from ...contracts.store import CalibrationStore
    from ...runtime.stages.geometry import DomeProfile, equidistant_theta_phi, surface_tables

    theta, phi = equidistant_theta_phi((size, size), np.deg2rad(100))
    tables = surface_tables(theta, phi, DomeProfile())
    meta = {"camera": {"width": width, "height": height}, "gel_center_px": [width / 2, height / 2],
            "gel_radius_px": min(width, height) * 0.45, "model_size": [size, size],
            "provenance": {"method": "nominal (benchmark)"}}
    store = CalibrationStore(root)
    store.write(sensor, tables, meta)
    return store.load(sensor)


SOURCES = ("synthetic", "demo")


def demo_size() -> int:
    """The model size of the demo unit's active calibration (what `--source demo` runs at)."""
    from ...contracts import paths
    from ...contracts.session import load_session
    from ...contracts.store import CalibrationStore

    return CalibrationStore().load(load_session(paths.demo_dir()).sensor_id).model_size[0]


def demo_inputs(work: Path, serials: list[str], size: int) -> Path:
    """The shipped demo recording's video, and its unit's active calibration written under each of
    `serials` in the store at `work` (one sensor id per loop, as the hand needs). Raises CalibrationError
    when that calibration's model size is not `size`."""
    from ...contracts import paths
    from ...contracts.errors import CalibrationError
    from ...contracts.session import load_session
    from ...contracts.store import TABLES, CalibrationStore

    session = load_session(paths.demo_dir())
    kind, video = session.image_source()
    if kind != "video":
        raise CalibrationError(f"{paths.demo_dir() / 'session.json'}: streams.frames is {kind}, expected a video")
    cal = CalibrationStore().load(session.sensor_id)
    if cal.model_size != (size, size):
        raise CalibrationError(f"--source demo: the demo unit {session.sensor_id}'s calibration {cal.folder} is at "
                               f"{cal.model_size[0]}x{cal.model_size[1]}, expected the package's {size}x{size} "
                               "(--source synthetic times any size)")
    meta = {k: v for k, v in cal.meta.items() if k in ("camera", "gel_center_px", "gel_radius_px", "model_size")}
    meta["provenance"] = {"method": f"copy of {session.sensor_id}/{cal.version} (benchmark)"}
    store = CalibrationStore(work)
    for serial in serials:
        store.write(serial, {k: getattr(cal, k) for k in TABLES}, meta)
    return Path(video)


def _package_for(size: int, work: Path):
    """(package, synthetic?) — the shipped model at this size if installed, else a synthetic one."""
    from ...runtime.stages.model import installed_packages, load_package
    from .models import write_package

    for folder in installed_packages():
        try:
            pkg = load_package(folder)
        except Exception:
            continue
        if pkg.size == (size, size) and not pkg.manifest.get("synthetic"):
            return pkg, False
    return load_package(write_package(work / f"synthetic-{size}", size=size, width=32, depth=3, stem=4)), True


def fp32_package(pkg, work: Path):
    """(package holding an fp32 model or None, where the fp32 graph came from).

    An int8-only package (docs/model_package.md) records the fp32 graph's SHA-256 and where the export
    left it (`files["model.fp32.onnx"].cache`, under the fit run). The graph is taken from there when its
    hash matches, else re-exported from the run's checkpoint (`training.run`/best.pt; the export is
    deterministic, so the hash is checked again); the package is then assembled in `work`."""
    import shutil

    from ...contracts.paths import ROOT
    from ...contracts.store import sha256_file
    from ...runtime.stages.model import PRECISION_FILES, load_package

    if pkg.has("fp32"):
        return pkg, "shipped in the package"
    name = PRECISION_FILES["fp32"]
    info = pkg.manifest.get("files", {}).get(name)
    if not info:
        return None, "fp32 not recorded in the manifest"
    folder = work / f"{pkg.folder.name}-with-fp32"
    folder.mkdir(parents=True, exist_ok=True)
    cached = Path(info["cache"]) if info.get("cache") else None
    cached = (ROOT / cached) if cached is not None and not cached.is_absolute() else cached
    if cached is not None and cached.is_file() and sha256_file(cached) == info["sha256"]:
        shutil.copyfile(cached, folder / name)
        source = f"build cache ({cached})"
    else:
        run = pkg.manifest.get("training", {}).get("run")
        run = (ROOT / run) if run and not Path(run).is_absolute() else (Path(run) if run else None)
        if run is None or not (run / "best.pt").is_file():
            half = _half_weights_package(pkg, folder, info)
            if half is not None:
                return half
            return None, f"fp32 graph neither in the build cache ({cached}) nor regenerable (fit run {run} has no best.pt); " + (
                f"rebuild the package with its recipe: tensortouch train all --recipe {pkg.folder / 'manifest.json'}"
                if pkg.manifest.get("training", {}).get("recipe") else
                "this package names no recipe, so no fp32 graph can be rebuilt from a checkout; compare int8 only")
        try:
            from ..train.export import export_onnx
            from ..train.model.train import load_trained
        except ImportError as exc:
            return None, f"fp32 graph not in the build cache and the train extra is missing ({exc})"
        model, _ = load_trained(run)
        export_onnx(model, folder / name, pkg.size[0])
        same = sha256_file(folder / name) == info["sha256"]
        source = (f"regenerated from {run / 'best.pt'} (" + ("same SHA-256 as the manifest)" if same else
                  "SHA-256 differs from the manifest: other torch/onnx versions?)"))
        if not same:
            import json

            man = dict(pkg.manifest)
            man["files"] = {**man["files"], name: {"sha256": sha256_file(folder / name)}}
            (folder / "manifest.json").write_text(json.dumps(man))
    for v in pkg.manifest.get("files", {}):          # every other file the manifest lists (int8, fp32-half)
        if v != name and (pkg.folder / v).is_file():
            shutil.copyfile(pkg.folder / v, folder / v)
    if not (folder / "manifest.json").is_file():
        shutil.copyfile(pkg.folder / "manifest.json", folder / "manifest.json")
    return load_package(folder), source


KEEP_FIELDS = 100     # fields kept per configuration for the stage comparison


def stage_ratios(fields: list[np.ndarray], cal, cfg, rounds: int = 5) -> dict:
    """The stages changed for issue #44 before and now, on the same fields: ms per frame of the frozen
    previous core (tools/bench/previous_stages.py) and of the current one, and previous / current.
    Each frame runs through both, alternating, `rounds` times; a frame's time is its fastest round (load
    from other processes only ever adds), and a stage's figure is the mean of those over the frames.
    `contacts` = pixel forces + clustering (before tracking); `fields_encoding` = contracts.wire.encode_fields
    (the bulk of `publish`)."""
    from ...contracts import wire
    from ...runtime.pipeline import contact_stage
    from . import previous_stages as previous

    if not fields:
        return {"frames": 0}
    pairs = {"contacts": (lambda f: previous.contact_stage(f, cal, cfg), lambda f: contact_stage(f, cal, cfg)),
             "fields_encoding": (lambda f: previous.encode_fields(f, 0, 0.0, "bench-0"),
                                 lambda f: wire.encode_fields(f, 0, 0.0, "bench-0"))}
    out = {"frames": len(fields), "frames_with_clusters": sum(bool(contact_stage(f, cal, cfg)) for f in fields)}
    for name, fns in pairs.items():
        best = np.full((2, len(fields)), np.inf)
        for r in range(rounds):
            for i, f in enumerate(fields):
                for j in ((0, 1) if r % 2 == 0 else (1, 0)):
                    t0 = time.perf_counter()
                    fns[j](f)
                    best[j, i] = min(best[j, i], time.perf_counter() - t0)
        before, now = 1e3 * best.mean(axis=1)
        out[name] = {"previous_ms": round(float(before), 4), "current_ms": round(float(now), 4),
                     "ratio": round(float(before / now), 2)}
    return out


def _half_weights_package(pkg, folder: Path, info: dict):
    """(package, source) running the package's shipped fp32 graph with float16-stored weights
    (`model.fp32-half.onnx`, tools/train/export.py `half_weights`) as its fp32 model, or None when it
    ships none. Computed in float32 at fp32 speed; its outputs differ from the exact fp32 graph's by the
    weight rounding, whose PSNR the export measured (manifest metrics.fp32_half)."""
    import shutil

    from ...runtime.stages.model import PRECISION_FILES, load_package
    from ..train.package import FP32_HALF

    if not (pkg.folder / FP32_HALF).is_file():
        return None
    shutil.copyfile(pkg.folder / FP32_HALF, folder / PRECISION_FILES["fp32"])
    for name in (FP32_HALF, PRECISION_FILES["int8"]):
        shutil.copyfile(pkg.folder / name, folder / name)
    man = json.loads((pkg.folder / "manifest.json").read_text())
    man["files"] = {**man["files"], PRECISION_FILES["fp32"]: dict(man["files"][FP32_HALF])}
    (folder / "manifest.json").write_text(json.dumps(man))
    psnr = man.get("metrics", {}).get("fp32_half", {}).get("vs_fp32_psnr_min")
    return load_package(folder), ("the package's fp32 graph with float16-stored weights (computed in float32; "
                                  + (f"min PSNR vs the exact fp32 graph at export {psnr:.1f} dB" if psnr is not None
                                     else "identical to the exact fp32 graph at export") + f"; exact one: {info.get('regenerate', '')})")


class _Config:
    """One (model, precision) frame loop of the benchmark, run in chunks alternating with the others."""

    def __init__(self, pkg, precision: str, video: Path, cal, threads: int, publisher, fields_every: int):
        from ...drivers.camera import camera_from_uri
        from ...runtime.apps.loop import LatencyWindow, LoopConfig, SensorLoop
        from ...runtime.pipeline import open_pipeline

        self.pipe = open_pipeline(pkg, cal, precision=precision, threads=threads)
        self.cam = camera_from_uri(f"file:{video}", realtime=False, loop=True)
        self.cam.__enter__()
        self.loop = SensorLoop(self.cam, self.pipe, publisher,
                               LoopConfig(status_every_s=1.0, fields_every=fields_every))
        self.loop.run(max_frames=self.pipe.cfg.baseline.startup_frames + 5)  # warm-up, baseline
        self.loop.latency = LatencyWindow(10 ** 6)
        self.loop.frames = 0
        self.wall = self.cpu = self.cpu_all = 0.0
        self.fields: list[np.ndarray] = []          # the first timed frames' fields (stage_ratios)
        self.clusters = 0                           # clusters published over the timed frames
        self.loop.on_result = self._keep

    def _keep(self, result) -> None:
        self.clusters += len(result.clusters)
        if result.fields is not None and len(self.fields) < KEEP_FIELDS:
            self.fields.append(result.fields.copy())

    def chunk(self, n: int) -> None:
        t0, c0, p0 = time.perf_counter(), time.thread_time(), time.process_time()
        self.loop.run(max_frames=self.loop.frames + n)
        self.wall += time.perf_counter() - t0
        self.cpu += time.thread_time() - c0
        self.cpu_all += time.process_time() - p0     # + zenoh's and decoder threads

    def close(self) -> None:
        self.cam.__exit__(None, None, None)

    def result(self) -> dict:
        n = self.loop.frames
        s = self.loop.latency.summary()
        return {"frames": n, "hz": n / self.wall, "clusters_per_frame": self.clusters / max(n, 1),
                "cpu_ms_per_frame": 1e3 * self.cpu / n, "process_cpu_ms_per_frame": 1e3 * self.cpu_all / n,
                "stages": {k: {"p50_ms": round(v["p50"], 3), "p99_ms": round(v["p99"], 3)} for k, v in s.items()}}


def run(args) -> int:
    import cv2

    from ...runtime.apps.publisher import Publisher

    cv2.setNumThreads(1)           # as `tensortouch run` does: one core for the whole sensor loop

    if args.sizes is None:
        sizes = [demo_size()] if args.source == "demo" else [96, 128]
    else:
        sizes = [int(s) for s in args.sizes.split(",")]
    results, notes, stages, tags = {}, [], {}, {}
    named = _named_packages(args.package or [], sizes)
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if args.source == "demo":
            from ...contracts.errors import CommandError
            from ...contracts.store import CalibrationStore

            if len(sizes) != 1:
                raise CommandError(f"--source demo (the default): one model size, the demo unit's ({demo_size()}), got "
                                   f"--sizes {args.sizes}; --source synthetic times any sizes")
            video = demo_inputs(work / "demo", ["bench-0"], sizes[0])
            cap = cv2.VideoCapture(str(video))
            w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            cap.release()
        else:
            frames = synthetic_frames(120)
            video = write_video(frames, work / "bench.avi")
            h, w = frames[0].shape[:2]
        with Publisher("bench-0", listen=["tcp/127.0.0.1:0"]) as pub:
            for size in sizes:
                chosen = [(p, False) for p in named if p.size == (size, size)] if named else [_package_for(size, work)]
                cal = (CalibrationStore(work / "demo").load("bench-0") if args.source == "demo"
                       else _calibration(work / f"cal{size}", "bench-0", size, w, h))
                configs, meta = {}, {}
                for i, (pkg, synthetic) in enumerate(chosen):
                    tag = f"{size}" if i == 0 else f"{size}/{pkg.name}"
                    pkg32, source = fp32_package(pkg, work)
                    notes.append(f"{size}² {pkg.name} fp32 model: {source}")
                    if pkg32 is not None:
                        configs[f"{tag}/fp32"] = _Config(pkg32, "fp32", video, cal, args.threads, pub, 1)
                    configs[f"{tag}/int8"] = _Config(pkg, "int8", video, cal, args.threads, pub, 1)
                    if args.fields_every > 1:
                        configs[f"{tag}/int8/fields÷{args.fields_every}"] = _Config(
                            pkg, "int8", video, cal, args.threads, pub, args.fields_every)
                    for key in configs:
                        meta.setdefault(key, (pkg, synthetic))
                    tags.setdefault(size, []).append((tag, pkg.name, source))
                done = 0
                while done < args.frames:          # alternate chunks: load from other processes hits all alike
                    n = min(args.chunk, args.frames - done)
                    for c in configs.values():
                        c.chunk(n)
                    done += n
                q = configs[f"{size}/int8"]
                stages[size] = stage_ratios(q.fields, q.pipe.cal, q.pipe.cfg.contacts)
                for key, c in configs.items():
                    c.close()
                    pkg, synthetic = meta[key]
                    results[key] = {**c.result(), "model": pkg.name, "synthetic": synthetic,
                                    "params": pkg.manifest.get("metrics", {}).get("params")}
    load_after = os.getloadavg()
    frames_are = ("the shipped demo recording (twin frames, rest and contact) through its unit's calibration"
                  if args.source == "demo" else "synthetic gel frames, a blob pressing and sliding in every frame")
    print(f"runtime benchmark — {args.frames} frames per config (interleaved in chunks of {args.chunk}) of {frames_are}, "
          f"{args.threads} onnxruntime thread(s), OpenCV 1 thread, capture = MJPG {w}x{h} decode, publish = Zenoh loopback; "
          f"cpu count {os.cpu_count()}, load average {load_before[0]:.2f} → {load_after[0]:.2f}")
    for note in notes:
        print(f"  {note}")
    for key, r in results.items():
        tag = " (synthetic weights, timing only)" if r["synthetic"] else ""
        tot = r["stages"]["end_to_end"]
        print(f"\n{key}: {r['model']}{tag}, params {r['params']}: {r['hz']:.1f} frames/s, "
              f"end-to-end p50 {tot['p50_ms']:.2f} ms p99 {tot['p99_ms']:.2f} ms; "
              f"CPU {r['cpu_ms_per_frame']:.2f} ms/frame (= {1e3 / r['cpu_ms_per_frame']:.0f} frames/s on a free core; "
              f"all threads {r['process_cpu_ms_per_frame']:.2f} ms); {r['clusters_per_frame']:.2f} clusters per frame")
        for stage, v in r["stages"].items():
            if stage not in ("total", "end_to_end"):
                print(f"    {stage:<11} p50 {v['p50_ms']:7.3f} ms   p99 {v['p99_ms']:7.3f} ms")
    print("\nint8 vs fp32 (same run, interleaved):")
    for size in sizes:
        for tag, name, source in tags[size]:
            q = results[f"{tag}/int8"]
            f = results.get(f"{tag}/fp32")
            if f is None:
                print(f"  {size}² {name}: fp32 unavailable ({source})")
                continue
            fi, qi = f["stages"]["inference"]["p50_ms"], q["stages"]["inference"]["p50_ms"]
            print(f"  {size}² {name}: inference p50 {fi:.2f} → {qi:.2f} ms (×{fi / qi:.2f}); end-to-end {f['hz']:.1f} → "
                  f"{q['hz']:.1f} frames/s (×{q['hz'] / f['hz']:.2f}); CPU/frame {f['cpu_ms_per_frame']:.2f} → "
                  f"{q['cpu_ms_per_frame']:.2f} ms (×{f['cpu_ms_per_frame'] / q['cpu_ms_per_frame']:.2f})")
            r = results.get(f"{tag}/int8/fields÷{args.fields_every}")
            if r is not None:
                print(f"  {size}² int8, fields every {args.fields_every}th frame (wrench/contacts every frame): "
                      f"{r['hz']:.1f} frames/s, CPU/frame {r['cpu_ms_per_frame']:.2f} ms, publish p50 "
                      f"{r['stages']['publish']['p50_ms']:.3f} ms vs {q['stages']['publish']['p50_ms']:.3f} ms")
    side = {size: t for size, t in tags.items() if len(t) > 1}
    if side:
        print("\npackages side by side (int8, same run, interleaved; ratio against the first --package):")
    for size, t in side.items():
        a = results[f"{t[0][0]}/int8"]
        for tag, name, _ in t[1:]:
            b = results[f"{tag}/int8"]
            print(f"  {size}² {name} vs {t[0][1]}: {b['hz']:.1f} vs {a['hz']:.1f} frames/s (×{b['hz'] / a['hz']:.2f}); "
                  f"CPU/frame {b['cpu_ms_per_frame']:.2f} vs {a['cpu_ms_per_frame']:.2f} ms "
                  f"(×{a['cpu_ms_per_frame'] / b['cpu_ms_per_frame']:.2f}); end-to-end p99 "
                  f"{b['stages']['end_to_end']['p99_ms']:.2f} vs {a['stages']['end_to_end']['p99_ms']:.2f} ms")
    print("\nchanged stages, previous → current core on the same fields (int8 run's first "
          f"{KEEP_FIELDS} frames, alternating, each frame's fastest of 5 rounds; tools/bench/previous_stages.py):")
    for size, st in stages.items():
        if not st["frames"]:
            print(f"  {size}²: no frame with fields was kept (baseline never ready)")
        for name in ("contacts", "fields_encoding") if st["frames"] else ():
            v = st[name]
            print(f"  {size}² {name:<16} {v['previous_ms']:.3f} → {v['current_ms']:.3f} ms/frame (×{v['ratio']:.2f}); "
                  f"{st['frames']} frames, {st['frames_with_clusters']} with clusters")
    shipped = f"{max(sizes)}/int8"
    summary = {"config": shipped, "end_to_end_hz": round(results[shipped]["hz"], 2),
               "p99_ms": results[shipped]["stages"]["end_to_end"]["p99_ms"],
               "cpu_ms_per_frame": round(results[shipped]["cpu_ms_per_frame"], 3),
               "synthetic_weights": results[shipped]["synthetic"], "source": args.source, "load_average": [load_before[0], load_after[0]],
               "fp32_source": notes, "results": results, "stages_previous_vs_current": stages}
    if args.json:
        print(json.dumps(summary))
    return 0


def _named_packages(names: list[str], sizes: list[int]) -> list:
    """The --package packages (a name in exported_models/ or a folder), each at one of `sizes`."""
    from ...contracts.errors import ModelPackageError
    from ...runtime.stages.model import find_package

    out = [find_package(n) for n in names]
    for n, p in zip(names, out):
        if p.size[0] not in sizes or p.size[0] != p.size[1]:
            raise ModelPackageError(f"--package {n}: input {p.size}, expected a square size among --sizes {sizes}")
    return out


def add_arguments(p) -> None:
    p.add_argument("--sizes", default=None,
                   help="model input sizes, comma separated (default: the demo unit's; with --source synthetic 96,128)")
    p.add_argument("--package", action="append", metavar="NAME|DIR",
                   help="run this model package (repeat: side by side in one run, ratios against the first); "
                        "default: the installed package at each size, else a synthetic net")
    p.add_argument("--frames", type=int, default=200, help="timed frames per configuration")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads")
    p.add_argument("--chunk", type=int, default=25, help="frames per turn when alternating configurations")
    p.add_argument("--fields-every", type=int, default=1,
                   help="also run int8 publishing fields every N-th frame only (LoopConfig.fields_every)")
    p.add_argument("--source", choices=SOURCES, default="demo",
                   help="frames: demo (default: the shipped demo recording through its unit's calibration, looped; "
                        "its model size only) or synthetic (drawn frames with a blob pressing in every frame, any "
                        "size; no trained network has seen them)")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
