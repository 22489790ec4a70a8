"""`tensortouch bench hand`: N replayed sensors in one process (runtime/apps/hand.py), side by side.

Throughput: every finger replays an MJPG recording as fast as it decodes (looping) through the
exact deploy code (camera → SensorPipeline → Zenoh Publisher on one shared session), for each
scheduling mode: one onnxruntime session per finger vs one shared session, with the inference
gate at `--workers` (default = cores) or off. A raw zenoh subscriber in the same process counts
what arrives, so the fields really go over loopback. Prints frames/s per sensor and end-to-end
(capture → publish) p50/p99 per mode.

Soak (`--soak SECONDS`): the default mode at a fixed camera rate (`--soak-fps`, real-time replay);
every `--log-every` s it logs resident memory (VmRSS), per-finger frames/s and latency p50/p99 to a
JSON-lines file under cache/ (latency there = pipeline + publish, without the wait for the next
frame) and prints the drift (linear fit of RSS, first vs last p99) at the end.

Network (`--model`): a package name in exported_models/ or a path to a package folder; default =
the newest shipped package (its own input size), or, when none is installed, the synthetic
~2.1 M-parameter conv U-Net. `--model synthetic` asks for the synthetic net explicitly (random
weights: timing only — said in the output; `--size` sets its input size, for tests).

Frames (`--source`): `demo` (default; every finger replays the shipped demo recording through a copy
of its unit's calibration, so the model runs at that unit's size) or `synthetic` (drawn frames, one
seed per finger, at any size; no trained network has seen them).
"""
from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from ...contracts.files import atomic_write

log = logging.getLogger(__name__)

MODES = {  # name: (share_model, inference_workers or None = --workers)
    "separate": (False, None),
    "shared": (True, None),
    "separate-nogate": (False, 0),
}


def rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


SYNTHETIC = "synthetic"
DEFAULT_SYNTHETIC_SIZE = 128  # input size of the synthetic net when --size is not given


def resolve_model(model: str | None, size: int | None, work: Path):
    """(package, synthetic?) for `--model`: a name/path, `synthetic`, or None = newest shipped one.

    A named package whose size differs from an explicit `--size` is an error (the calibration is
    built at the package's size)."""
    from ...contracts.errors import ModelPackageError
    from ...runtime.stages.model import find_package, installed_packages, load_package
    from .models import write_package

    if model != SYNTHETIC and (model or installed_packages()):
        pkg = find_package(model)
        if pkg.manifest.get("synthetic"):
            log.info("package %s is a synthetic network (timing only)", pkg.folder)
        if size is not None and pkg.size != (size, size):
            raise ModelPackageError(f"{pkg.folder}: input size {pkg.size[0]}x{pkg.size[1]}, but --size {size} "
                                    "was given (drop --size, or use --model synthetic)")
        return pkg, bool(pkg.manifest.get("synthetic"))
    size = size or DEFAULT_SYNTHETIC_SIZE
    folder = write_package(work / f"synthetic-{size}", size=size, width=32, depth=3, stem=4)
    return load_package(folder), True


def _setup(work: Path, n: int, model: str | None, size: int | None, width: int = 320, height: int = 240,
           source: str = "demo"):
    """(package, synthetic?, one video per sensor, sensor ids) with each sensor's calibration in
    `work`/store: synthetic frames (a different seed per sensor) through a nominal calibration, or every
    sensor replaying the shipped demo recording through a copy of the demo unit's calibration."""
    from .runtime_bench import _calibration, demo_inputs, demo_size, synthetic_frames, write_video

    if source == "demo" and size is None and model == "synthetic":
        size = demo_size()                       # the synthetic net at the demo unit's model size
    pkg, synthetic = resolve_model(model, size, work)
    size = pkg.size[0]
    serials = [f"bench-{i}" for i in range(n)]
    if source == "demo":
        video = demo_inputs(work / "store", serials, size)
        return pkg, synthetic, [video] * n, serials
    videos = []
    for i, serial in enumerate(serials):
        videos.append(write_video(synthetic_frames(120, width, height, seed=i), work / f"{serial}.avi"))
        _calibration(work / "store", serial, size, width, height)
    return pkg, synthetic, videos, serials


def _config(pkg, work, videos, serials, share, workers, precision, camera, endpoint, fields_every: int = 1):
    from ...runtime.apps.hand_config import FingerConfig, HandConfig

    fingers = tuple(FingerConfig(name=f"f{i}", serial=s, source=f"file:{v}")
                    for i, (s, v) in enumerate(zip(serials, videos)))
    return HandConfig(fingers=fingers, name="bench", model=str(pkg.folder), precision=precision,
                      share_model=share, inference_workers=workers, calibration_store=str(work / "store"),
                      listen=(endpoint,), camera_options=camera, status_every_s=1.0, fields_every=fields_every)


class _Counter:
    def __init__(self, session):
        self.n = 0
        self.bytes = 0
        self.sub = session.declare_subscriber("tensortouch/**", self._on)

    def _on(self, sample):
        self.n += 1
        self.bytes += len(sample.payload)


def _free_endpoint() -> str:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def run_mode(cfg, seconds: float, warmup: float) -> dict:
    from ...runtime.apps.hand import Hand
    from ...runtime.apps.publisher import open_session

    hand = Hand(cfg).start()
    listener = open_session(connect=list(cfg.listen))
    counter = _Counter(listener)
    try:
        time.sleep(warmup)
        for f in hand.fingers.values():              # fresh latency windows after warm-up + baseline
            if f.loop is not None:
                f.loop.latency = type(f.loop.latency)(100000)
        start = {n: (f.loop.frames if f.loop else 0) for n, f in hand.fingers.items()}
        msgs0 = counter.n
        t0, cpu0 = time.perf_counter(), time.process_time()
        time.sleep(seconds)
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        per = {}
        for n, f in hand.fingers.items():
            s = f.loop.latency.summary().get("total", {}) if f.loop else {}
            per[n] = {"hz": (f.loop.frames - start[n]) / wall, "p50_ms": s.get("p50"), "p99_ms": s.get("p99"),
                      "inference_p50_ms": f.loop.latency.summary().get("inference", {}).get("p50")}
        received = (counter.n - msgs0) / wall
        frames = sum(f.loop.frames - start[n] for n, f in hand.fingers.items() if f.loop is not None)
    finally:
        counter.sub.undeclare()
        listener.close()
        hand.stop()
    return {"fingers": per, "received_msgs_per_s": received, "load1_end": round(os.getloadavg()[0], 2),
            "cpu_share": round(cpu / wall, 3),                   # CPU-seconds per second this process got
            "cpu_ms_per_frame": round(1e3 * cpu / max(frames, 1), 2),
            "min_hz": min(v["hz"] for v in per.values()),
            "total_hz": sum(v["hz"] for v in per.values()),
            "p99_ms": max(v["p99_ms"] or 0 for v in per.values())}


class _ProcLatency:
    """Per-finger pipeline+publish latency (total minus capture: a real-time replay's read() also
    waits for the next frame to be due, which is idle time, not latency)."""

    def __init__(self):
        from collections import defaultdict

        self.ms = defaultdict(list)
        self.first: dict[str, float] = {}          # monotonic time of each finger's first frame
        self.count: dict[str, int] = defaultdict(int)

    def __call__(self, finger, result):
        t = result.timings
        name = finger.cfg.name
        self.first.setdefault(name, time.monotonic())
        self.count[name] += 1
        self.ms[name].append(t.get("total", 0.0))  # total excludes capture (waiting)

    def behind(self, name, fps: float, now: float) -> float:
        """Frames a camera at `fps` would have delivered since this finger's first frame that it has
        not processed yet (a paced replay's read() never skips: a slow loop falls behind instead;
        a live camera would have dropped these)."""
        if name not in self.first:
            return 0.0
        return max(0.0, fps * (now - self.first[name]) - self.count[name] + 1)

    def take(self, name) -> tuple[float, float]:
        a, self.ms[name] = self.ms[name], []
        if not a:
            return 0.0, 0.0
        return float(np.percentile(a, 50)), float(np.percentile(a, 99))


def soak(cfg, seconds: float, log_every: float, log_path: Path, fps: float) -> dict:
    from ...runtime.apps.hand import Hand

    lat = _ProcLatency()
    hand = Hand(cfg, on_result=lat).start()
    rows = []
    t_start, cpu_start = time.monotonic(), time.process_time()
    try:
        with open(log_path, "w") as log:
            last = {n: 0 for n in hand.fingers}
            t_last, cpu_last = time.monotonic(), time.process_time()
            while time.monotonic() - t_start < seconds:
                time.sleep(log_every)
                now = time.monotonic()
                cpu = time.process_time()
                row = {"t_s": round(now - t_start, 1), "rss_mb": round(rss_mb(), 2),
                       "load1": round(os.getloadavg()[0], 2),
                       "cpu_share": round((cpu - cpu_last) / (now - t_last), 3), "fingers": {}}
                cpu_last = cpu
                for n, f in hand.fingers.items():
                    frames = f.loop.frames if f.loop else 0
                    p50, p99 = lat.take(n)
                    row["fingers"][n] = {"hz": round((frames - last[n]) / (now - t_last), 2),
                                         "p50_ms": round(p50, 3), "p99_ms": round(p99, 3), "state": f.state,
                                         "frames": frames, "behind": round(lat.behind(n, fps, now), 1)}
                    last[n] = frames
                t_last = now
                rows.append(row)
                log.write(json.dumps(row) + "\n")
                log.flush()
                print(f"  soak t={row['t_s']:7.1f} s  RSS {row['rss_mb']:7.1f} MB  load {row['load1']:5.2f} cpu {row['cpu_share']:4.2f}  " + "  ".join(
                    f"{n} {v['hz']:5.1f} Hz p99 {v['p99_ms']:6.1f} ms" for n, v in row["fingers"].items()),
                    flush=True)
        # the whole soak's CPU seconds per wall second (every thread of the process: decode, pipelines, zenoh)
        cpu_total = (time.process_time() - cpu_start) / max(time.monotonic() - t_start, 1e-9)
    finally:
        hand.stop()
    return {**summarize_soak(rows, fps, log_path), "cpu_share_total": round(cpu_total, 3)}


def read_soak_log(path: Path) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def summarize_soak(rows: list[dict], fps: float, log_path=None) -> dict:
    """Drift summary of soak windows: RSS linear fit (after the first 10 %), worst-finger p99 in the
    first vs last quarter, mean rate and frames behind per finger, median load average."""
    if not rows:
        return {"duration_s": 0.0, "windows": 0, "fps_target": fps, "log": str(log_path)}
    t = np.array([r["t_s"] for r in rows])
    rss = np.array([r["rss_mb"] for r in rows])
    p99 = np.array([max(v["p99_ms"] for v in r["fingers"].values()) for r in rows])
    skip = max(1, len(rows) // 10)                    # ignore the first 10 % (allocator warm-up)
    slope = float(np.polyfit(t[skip:], rss[skip:], 1)[0] * 3600) if len(rows) - skip >= 3 else float("nan")
    q = max(1, len(rows) // 4)
    last = rows[-1]["fingers"]
    return {"duration_s": float(t[-1]), "windows": len(rows), "fps_target": fps,
            "mean_hz": {n: v.get("frames", 0) / t[-1] for n, v in last.items()},
            "behind_frames": {n: v.get("behind", 0.0) for n, v in last.items()},
            "load1_median": float(np.median([r.get("load1", np.nan) for r in rows])),
            "cpu_share_median": float(np.median([r.get("cpu_share", np.nan) for r in rows])),
            "rss_first_mb": float(rss[skip]) if len(rss) > skip else float(rss[0]),
            "rss_last_mb": float(rss[-1]), "rss_max_mb": float(rss.max()),
            "rss_slope_mb_per_h": slope, "p99_first_quarter_ms": float(np.median(p99[:q])),
            "p99_last_quarter_ms": float(np.median(p99[-q:])), "log": str(log_path)}


def plot_soak(rows: list[dict], png: Path, title: str = "") -> Path:
    """Small PNG: RSS, worst-finger window p99 and per-sensor rate vs time (needs matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([r["t_s"] for r in rows]) / 60.0
    fig, ax = plt.subplots(4, 1, figsize=(6.4, 6.4), sharex=True, dpi=80)
    ax[0].plot(t, [r["rss_mb"] for r in rows], color="k")
    ax[0].set_ylabel("RSS (MB)")
    ax[1].plot(t, [max(v["p99_ms"] for v in r["fingers"].values()) for r in rows], color="tab:red",
               label="worst-finger p99")
    ax[1].plot(t, [np.median([v["p50_ms"] for v in r["fingers"].values()]) for r in rows], color="tab:blue",
               label="median p50")
    ax[1].set_ylabel("latency (ms)")
    ax[1].legend(fontsize=7, loc="upper right")
    for name in rows[0]["fingers"]:
        ax[2].plot(t, [r["fingers"][name]["hz"] for r in rows], lw=0.8, label=name)
    ax[2].set_ylabel("frames/s")
    ax[2].legend(fontsize=7, loc="upper left", ncol=4)
    if "cpu_share" in rows[0]:
        ax[3].plot(t, [r["cpu_share"] for r in rows], color="tab:green", label="CPU-s/s this process got")
        ax[3].set_ylabel("CPU share")
        ax[3].legend(fontsize=7, loc="upper left")
    if "load1" in rows[0]:
        ax3 = ax[3].twinx()
        ax3.plot(t, [r["load1"] for r in rows], color="0.5", ls=":")
        ax3.set_ylabel("load avg (dotted)", color="0.4")
    ax[3].set_xlabel("time (min)")
    if title:
        ax[0].set_title(title, fontsize=9)
    fig.tight_layout()
    try:
        return atomic_write(png, lambda fh: fig.savefig(fh, format="png"))
    finally:
        plt.close(fig)


def _print_soak(s: dict) -> None:
    print(f"soak done: {s['duration_s']:.0f} s, RSS {s['rss_first_mb']:.1f} → {s['rss_last_mb']:.1f} MB "
          f"(fit {s['rss_slope_mb_per_h']:+.2f} MB/h), worst-finger p99 first quarter "
          f"{s['p99_first_quarter_ms']:.1f} ms, last quarter {s['p99_last_quarter_ms']:.1f} ms; mean rate "
          + ", ".join(f"{v:.2f}" for v in s["mean_hz"].values()) + f" Hz (target {s['fps_target']:g}), "
          "frames behind at the end " + ", ".join(f"{v:.0f}" for v in s["behind_frames"].values())
          + f", median load {s['load1_median']:.2f}, median CPU share {s['cpu_share_median']:.2f} CPU-s/s"
          + (f", whole soak {s['cpu_share_total']:.2f} CPU-s/s" if "cpu_share_total" in s else ""))


def from_log(args) -> int:
    rows = read_soak_log(args.from_log)
    s = summarize_soak(rows, args.soak_fps, args.from_log)
    _print_soak(s)
    if args.plot:
        print(f"plot: {plot_soak(rows, args.plot, args.plot_title)}")
    if args.json:
        print(json.dumps({"soak": s}))
    return 0


def run(args) -> int:
    import tempfile

    from ...contracts import paths

    if args.from_log:
        return from_log(args)
    if args.fields_every < 1:
        from ...contracts.errors import CommandError

        raise CommandError(f"--fields-every {args.fields_every}: expected 1 or more")
    workers = args.workers or os.cpu_count() or 2
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        pkg, synthetic, videos, serials = _setup(work, args.sensors, args.model, args.size, source=args.source)
        params = pkg.manifest.get("metrics", {}).get("params")
        tag = " (synthetic weights, timing only)" if synthetic else ""
        print(f"hand benchmark — {args.sensors} replayed sensors in one process, model {pkg.name}{tag}, "
              f"params {params}, {args.precision}, {pkg.size[0]}², cpu count {os.cpu_count()}, inference gate "
              f"{workers}; frames: {'the shipped demo recording' if args.source == 'demo' else 'synthetic'}, "
              "capture = MJPG 320x240 decode, publish = Zenoh loopback with a counting subscriber")
        results = {}
        if not args.soak_only:
            modes = [m.strip() for m in args.modes.split(",")]
            for mode in modes:
                share, gate = MODES[mode]
                cfg = _config(pkg, work, videos, serials, share, workers if gate is None else gate,
                              args.precision, {"realtime": False, "loop": True}, _free_endpoint(), args.fields_every)
                r = run_mode(cfg, args.seconds, args.warmup)
                results[mode] = r
                print(f"\n{mode}: per sensor " + ", ".join(f"{v['hz']:.1f}" for v in r["fingers"].values())
                      + f" frames/s (total {r['total_hz']:.1f}), end-to-end p50 "
                      + ", ".join(f"{v['p50_ms']:.1f}" for v in r["fingers"].values())
                      + f" ms, worst p99 {r['p99_ms']:.1f} ms, subscriber got {r['received_msgs_per_s']:.0f} msg/s"
                      + f" (load average {r['load1_end']:.2f}; this process got {r['cpu_share']:.2f} CPU-s/s, "
                      f"{r['cpu_ms_per_frame']:.1f} CPU-ms per frame)")
        summary = {"sensors": args.sensors, "model": pkg.name, "model_folder": str(pkg.folder),
                   "size": pkg.size[0], "precision": args.precision, "synthetic_weights": synthetic,
                   "params": params, "source": args.source, "fields_every": args.fields_every, "modes": results}
        if args.soak:
            camera = {"realtime": True, "loop": True, "fps": args.soak_fps}
            share, gate = MODES[args.soak_mode]
            cfg = _config(pkg, work, videos, serials, share, workers if gate is None else gate, args.precision,
                          camera, _free_endpoint(), args.fields_every)
            log_path = paths.cache_dir() / "hand" / f"soak-{time.strftime('%Y%m%d-%H%M%S')}.jsonl"
            log_path.parent.mkdir(parents=True, exist_ok=True)
            print(f"\nsoak: {args.soak:.0f} s at {args.soak_fps} frames/s per sensor, mode {args.soak_mode}, "
                  f"log {log_path}")
            s = soak(cfg, args.soak, args.log_every, log_path, args.soak_fps)
            summary["soak"] = dict(s, mode=args.soak_mode)
            _print_soak(s)
            if args.plot:
                print(f"plot: {plot_soak(read_soak_log(log_path), args.plot, args.plot_title)}")
    if args.json:
        print(json.dumps(summary))
    return 0


def add_arguments(p) -> None:
    p.add_argument("--sensors", type=int, default=4, help="fingertip sensors in the one process")
    p.add_argument("--model", default=None,
                   help="model package name in exported_models/ or a folder; 'synthetic' = the synthetic "
                        "net (timing only); default: the newest shipped package, else synthetic")
    p.add_argument("--size", type=int, default=None,
                   help=f"input size of the synthetic net (default {DEFAULT_SYNTHETIC_SIZE}); with a package: "
                        "must match it")
    p.add_argument("--precision", choices=("int8", "fp32"), default="int8", help="network precision")
    p.add_argument("--fields-every", type=int, default=1, metavar="N",
                   help="each finger publishes fields on every N-th frame (hand.fields_every; contacts every frame)")
    from .runtime_bench import SOURCES

    p.add_argument("--source", choices=SOURCES, default="demo",
                   help="frames: demo (default: every sensor replays the shipped demo recording through a copy of its "
                        "unit's calibration; its model size only) or synthetic (drawn frames with a blob pressing in "
                        "every frame, one seed per sensor, any size)")
    p.add_argument("--seconds", type=float, default=20.0, help="timed seconds per mode")
    p.add_argument("--warmup", type=float, default=5.0, help="seconds before timing (baseline startup)")
    p.add_argument("--workers", type=int, default=0, help="inference gate (default: cpu count)")
    p.add_argument("--modes", default=",".join(MODES), help=f"comma separated, from: {', '.join(MODES)}")
    p.add_argument("--soak", type=float, default=0.0, help="then soak this many seconds at --soak-fps")
    p.add_argument("--soak-only", action="store_true", help="skip the throughput modes")
    p.add_argument("--soak-fps", type=float, default=10.0, help="camera rate per sensor during the soak")
    p.add_argument("--soak-mode", choices=tuple(MODES), default="separate", help="scheduling mode of the soak")
    p.add_argument("--log-every", type=float, default=10.0, help="soak log period, s")
    p.add_argument("--plot", type=Path, default=None, help="after the soak: PNG of RSS, p99 and rate vs time")
    p.add_argument("--plot-title", default="", help="title of the --plot figure")
    p.add_argument("--from-log", type=Path, default=None,
                   help="summarize (and --plot) an existing soak log instead of running (--soak-fps = its rate)")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
