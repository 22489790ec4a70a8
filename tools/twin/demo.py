"""Regenerate the shipped demo session (runtime/demo/) and its unit's true calibration.

    tensortouch twin demo [--out runtime/demo] [--store calibration_store]

= `tensortouch twin record --unit TWIN-DEMO --pokes 3 --seed 7 --frames mjpg --calibration` with
shorter rests between pokes, FE physics (solves cached under cache/twin/fe), JPEG quality 65 so the
session stays under ~5 MB. The new demo is recorded under the cache (`staging_dir`: a run that is
stopped resumes there and leaves nothing in the source tree) and swapped in at the end, so an
interrupted run leaves the old demo.
"""
from __future__ import annotations

import argparse
import logging
import shutil
from pathlib import Path

from ...contracts import paths

log = logging.getLogger(__name__)
SERIAL, POKES, SEED, QUALITY = "TWIN-DEMO", 3, 7, 65


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--out", default=str(paths.demo_dir()), help="session folder to (re)write")
    ap.add_argument("--store", default=None, help="calibration store root (default: calibration_store/)")


def staging_dir(out: Path) -> Path:
    """Where a new demo for `out` is recorded before it is swapped in: under the cache, never beside `out`."""
    return paths.cache_dir() / "twin" / "demo-staging" / Path(out).name


def run(args: argparse.Namespace) -> int:
    from ..progress import stage_progress
    from .record import RecordConfig, Recorder
    from .unit import write_true_calibration

    out = Path(args.out)
    staging = staging_dir(out)
    staging.parent.mkdir(parents=True, exist_ok=True)
    cfg = RecordConfig(serial=SERIAL, pokes=POKES, seed=SEED, physics="fe", frame_format="mjpg",
                       mjpg_quality=QUALITY)
    cfg.trajectory.t_gap = (0.4, 0.7)   # short rests keep the demo under ~5 MB
    cfg.trajectory.t_lead = 0.6
    rec = Recorder(cfg, staging, progress=stage_progress(SERIAL))
    rec.run()
    old = out.with_name(out.name + ".old")
    if out.exists():
        out.rename(old)
    shutil.move(str(staging), str(out))     # a rename when the cache is on the same file system
    shutil.rmtree(old, ignore_errors=True)
    version = write_true_calibration(rec.unit, args.store, cfg.model_size)
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    print(f"demo session {out} ({size / 1e6:.2f} MB), true calibration {SERIAL}/{version}")
    return 0

