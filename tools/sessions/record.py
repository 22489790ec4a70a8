"""`tensortouch record`: camera frames, and a force gauge / mocap pose stream when given, into a session.

No ROS: frames come through the camera layer (drivers/camera, any `--source` form), the force from
the serial gauge driver (drivers/gauge.py), poses from the mocap line stream (drivers/mocap.py).
Everything is stamped on one clock, `time.monotonic()` at arrival, as seconds from the first frame.
The session is written with the session writer (tools/sessions/writer.py) in the documented format
(docs/session.md): frames, then `wrench` (a single-axis gauge: its reading along the F/T z axis,
F/T frame = indenter frame) and `poses`, then the manifest last.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...contracts.errors import SessionError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RecordLimits:
    max_frames: int | None = None
    duration_s: float | None = None


def _wrench_rows(readings, t0: float, t_end: float, indenter: int) -> np.ndarray:
    rows = [(r.t - t0, indenter, 0.0, 0.0, r.force_n, 0.0, 0.0, 0.0) for r in readings if t0 <= r.t <= t0 + t_end]
    return _increasing(np.array(rows, float).reshape(-1, 8))


def _pose_rows(poses, t0: float, t_end: float) -> np.ndarray:
    rows = [(p.t - t0, p.indenter, *p.xyz_mm, *p.q_wxyz) for p in poses if t0 <= p.t <= t0 + t_end]
    return _increasing(np.array(rows, float).reshape(-1, 9))


def _increasing(rows: np.ndarray) -> np.ndarray:
    """Sorted by time then indenter; per indenter, rows whose time does not advance are dropped."""
    if len(rows) == 0:
        return rows
    rows = rows[np.lexsort((rows[:, 1], rows[:, 0]))]
    keep = np.ones(len(rows), bool)
    last: dict[float, float] = {}
    for i, (t, ind) in enumerate(rows[:, :2]):
        if ind in last and t <= last[ind]:
            keep[i] = False
        else:
            last[ind] = t
    return rows[keep]


def record(camera, out: str | Path, sensor_id: str, gauge=None, mocap=None, limits: RecordLimits = RecordLimits(),
           frame_format: str = "ffv1", ft_indenter: int = 0, stop: threading.Event | None = None,
           provenance: dict | None = None, say=print) -> Path:
    """Record until the source ends, `limits` are reached, `stop` is set or Ctrl-C. `camera` is a connected
    drivers.camera Camera; `gauge` a started drivers.gauge.ForceGauge; `mocap` a started
    drivers.mocap.PoseStream. Returns the session folder."""
    import cv2

    from ...drivers.camera.camera import EndOfStream
    from .writer import SessionWriter

    out = Path(out)
    if (out / "session.json").exists():
        raise SessionError(f"{out}: already holds a session; choose a new --out folder")
    writer = SessionWriter(out, sensor_id, frame_format=frame_format)
    stop = stop or threading.Event()
    times: list[float] = []
    t0 = None
    while not stop.is_set():
        if limits.max_frames is not None and len(times) >= limits.max_frames:
            break
        try:
            frame = camera.read()
        except EndOfStream:
            break
        except KeyboardInterrupt:          # Ctrl-C ends a live recording; the session is still finished
            break
        now = time.monotonic()
        if t0 is None:
            t0 = now
        if limits.duration_s is not None and now - t0 > limits.duration_s:
            break
        writer.frame(len(times), cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR))
        times.append(now - t0)
        for dev in (gauge, mocap):
            if dev is not None:
                dev.check()
        if len(times) % 300 == 0:
            say(f"record: {len(times)} frames, {times[-1]:.1f} s")
    if not times:
        raise SessionError(f"{out}: no frames arrived from {camera.name}")
    t = np.array(times)
    fps = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 30.0
    writer.finish_frames(t, fps, source=camera.name)
    t_end = float(t[-1]) + 1.0 / fps                   # streams are kept up to one frame after the last
    n_wrench = n_poses = 0
    if gauge is not None:
        rows = _wrench_rows(list(gauge.readings), t0, t_end, ft_indenter)
        n_wrench = len(rows)
        if len(rows) == 0:
            raise SessionError(f"{out}: the force gauge {gauge.cfg.url} sent no reading during the recording")
        writer.table("wrench", rows, frame="ft", device=gauge.cfg.url, protocol=gauge.cfg.protocol,
                     ft_to_indenter={"rotation_wxyz": [1.0, 0.0, 0.0, 0.0], "translation_mm": [0.0, 0.0, 0.0]},
                     sign="single-axis gauge: its reading in fz (F/T frame = indenter frame); fx, fy, torques 0")
    if mocap is not None:
        rows = _pose_rows(mocap.poses(), t0, t_end)
        n_poses = len(rows)
        if len(rows) == 0:
            raise SessionError(f"{out}: the mocap stream {mocap.cfg.url} sent no pose during the recording")
        if gauge is not None and ft_indenter not in set(rows[:, 1].astype(int)):
            raise SessionError(f"{out}: the gauge is on indenter {ft_indenter} but the mocap stream sent no pose "
                               f"for it (ids {sorted(set(rows[:, 1].astype(int)))}); set --ft-indenter")
        writer.table("poses", rows, frame="sensor", device=mocap.cfg.url,
                     indenters={str(i): f"indenter {i}" for i in sorted(set(rows[:, 1].astype(int)))})
    path = writer.finish(provenance={"generator": "tensortouch record", "source": camera.name, **(provenance or {})},
                         clock={"source": "monotonic", "t0": 0.0, "unit": "s",
                                "note": "seconds from the first frame's arrival; gauge and mocap on the same clock"})
    say(f"record: {len(t)} frames ({t[-1]:.1f} s, {fps:.1f} fps)"
        + (f", {n_wrench} force readings" if gauge else "") + (f", {n_poses} poses" if mocap else "") + f" -> {out}")
    return path
