"""The frame loop: camera → SensorPipeline → Publisher, with health flags and hot calibration reload.

A camera that stops delivering frames, a black or frozen image, a publish error: the loop keeps
running and says so in `status.flags`; it stops only when the source is exhausted (replay), when
asked to, or after `max_camera_failures` consecutive capture errors (with a clear message).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from ...contracts.errors import CaptureError, TensorTouchError
from ...contracts.store import CalibrationStore
from ...contracts.wire import CONTACT_FIELDS
from ...drivers.camera.camera import EndOfStream
from ..pipeline import FrameResult, SensorPipeline
from ..stages.geometry import surface_grid

log = logging.getLogger(__name__)

FRAME_FLAGS = frozenset({"frame_black", "camera_frozen", "model_output_invalid"})  # re-judged every frame


@dataclass(frozen=True)
class LoopConfig:
    publish_fields: bool = True
    # Publish the dense fields on every n-th frame that has them (1 = every frame, the default);
    # contacts, wrench and status stay at the frame rate. Fields are the largest message (15·H·W
    # float16) and their float16 conversion is the biggest publish cost (docs/runtime.md "Speed").
    fields_every: int = 1
    status_every_s: float = 0.5        # status message period
    calibration_poll_s: float = 1.0    # how often the calibration store's CURRENT is checked
    max_camera_failures: int = 50      # consecutive capture errors before giving up
    retry_wait_s: float = 0.05


def to_wire_contacts(result: FrameResult) -> list[dict]:
    """Pipeline clusters → wire Contact dicts (docs/wire.md): the wire's fields, by the same names."""
    return [{name: getattr(c, name) for name in CONTACT_FIELDS} for c in result.clusters]


class LatencyWindow:
    """Rolling per-stage timings for status messages and benchmarks."""

    def __init__(self, n: int = 300):
        self.samples: dict[str, deque] = {}
        self.n = n

    def add(self, timings: dict[str, float]) -> None:
        for k, v in timings.items():
            self.samples.setdefault(k, deque(maxlen=self.n)).append(v)

    def summary(self) -> dict[str, dict[str, float]]:
        out = {}
        for k, d in self.samples.items():
            a = np.fromiter(d, float)
            p50, p99 = np.percentile(a, (50, 99))        # one partition for both
            out[k] = {"p50": float(p50), "p99": float(p99), "mean": float(a.mean())}
        return out


class SensorLoop:
    """Runs one sensor until the source ends or `stop()` is called."""

    def __init__(self, camera, pipeline: SensorPipeline, publisher=None, config: LoopConfig | None = None,
                 store: CalibrationStore | None = None, on_result=None, temperature=None, ros2=None):
        self.camera, self.pipeline, self.publisher = camera, pipeline, publisher
        # optional second output with the Publisher's calls: ROS 2 topics (runtime/apps/ros2_publisher.py)
        self.ros2 = ros2
        # optional gel temperature source: callable(frame time s) -> °C (runtime/stages/temperature.py)
        self.temperature = temperature
        self.cfg = config or LoopConfig()
        self.store = store
        self.on_result = on_result
        self.latency = LatencyWindow()
        self._stop = threading.Event()
        self.frames = 0
        self.flags: set[str] = set()
        self._field_frames = 0
        self._rejected: str | None = None    # the activated version refused at the last reload

    def stop(self) -> None:
        """Ask the loop to end after the current frame; a replay waiting across a recorded gap ends its wait."""
        self._stop.set()
        interrupt = getattr(self.camera, "interrupt", None)
        if interrupt is not None:
            interrupt()

    def info(self) -> dict:
        p = self.pipeline
        pkg = p.model.package
        return {"sensor_id": p.sensor_id, "model": pkg.name, "model_hash": pkg.sha256(p.model.precision),
                "precision": p.model.precision, "calibration_version": p.cal.version,
                "bounds": pkg.manifest["output"]["bounds"], "model_size": list(pkg.size),
                "channels": pkg.manifest["output"]["channels"], "units": pkg.manifest["output"]["units"],
                "gel_surface": surface_grid(p.cal)}       # viewers draw the calibrated gel

    def run(self, max_frames: int | None = None) -> int:
        failures = 0
        last_status = 0.0
        last_poll = time.monotonic()
        fps_t0, fps_n, fps = time.monotonic(), 0, 0.0
        while not self._stop.is_set() and (max_frames is None or self.frames < max_frames):
            t_cap = time.perf_counter()
            try:
                item = self.camera.read()
            except EndOfStream:
                log.info("%s: source exhausted after %d frames", self.pipeline.sensor_id, self.frames)
                break
            except CaptureError as exc:
                failures += 1
                self.flags.add("camera_stalled")
                if failures == 1:
                    log.warning("%s: %s", self.pipeline.sensor_id, exc)
                self._status(time.monotonic(), fps, force=failures == 1)
                if failures >= self.cfg.max_camera_failures:
                    raise TensorTouchError(f"sensor {self.pipeline.sensor_id}: camera failed "
                                           f"{failures} times in a row, last error: {exc}") from None
                self._stop.wait(self.cfg.retry_wait_s)
                continue
            frame, t = item.image, item.t
            failures = 0
            self.flags.discard("camera_stalled")
            capture_ms = (time.perf_counter() - t_cap) * 1e3
            if self.temperature is not None:
                self.pipeline.set_temperature(self.temperature(t))
            result = self.pipeline.process(frame, t)
            result.timings = {"capture": capture_ms, **result.timings}
            t_pub = time.perf_counter()
            self._publish(result)
            result.timings["publish"] = (time.perf_counter() - t_pub) * 1e3
            # "total": frame in hand → published (what the sensor adds); "end_to_end" adds the capture
            # call, which for a live camera or a paced replay includes waiting for the next frame
            result.timings["total"] = sum(v for k, v in result.timings.items() if k != "capture")
            result.timings["end_to_end"] = result.timings["total"] + capture_ms
            self.latency.add(result.timings)
            self.frames += 1
            fps_n += 1
            now = time.monotonic()
            if now - fps_t0 >= 1.0:
                fps, fps_t0, fps_n = fps_n / (now - fps_t0), now, 0
            self.flags = (self.flags - FRAME_FLAGS) | set(result.flags)
            if self.on_result:
                self.on_result(result)
            if now - last_status >= self.cfg.status_every_s:
                self._status(now, fps, result=result)
                last_status = now
            if self.store is not None and now - last_poll >= self.cfg.calibration_poll_s:
                last_poll = now
                self._maybe_reload()
        self._status(time.monotonic(), fps, force=True)
        return self.frames

    def _outputs(self) -> list:
        return [out for out in (self.publisher, self.ros2) if out is not None]

    def _publish(self, r: FrameResult) -> None:
        outputs = self._outputs()
        if not outputs:
            return
        if r.fields is not None and self.cfg.publish_fields:
            if self._field_frames % max(1, self.cfg.fields_every) == 0:
                for out in outputs:
                    out.publish_fields(r.fields, r.seq, r.t)
            self._field_frames += 1
        contacts = to_wire_contacts(r)
        for out in outputs:
            out.publish_contacts(contacts, r.seq, r.t)
            out.publish_wrench(r.force_n, r.torque_nmm, r.seq, r.t)

    def _status(self, now: float, fps: float, result: FrameResult | None = None, force: bool = False) -> None:
        if not self._outputs():
            return
        p = self.pipeline
        latency = self.latency.summary()
        status = {"state": result.state if result else p.baseline.state.name,
                  "flags": sorted(self.flags), "fps": round(fps, 2),
                  "timings_ms": {k: round(v["p50"], 3) for k, v in latency.items()},
                  "timings_p99_ms": {k: round(v["p99"], 3) for k, v in latency.items()},
                  "frames": self.frames, "model": p.model.package.name,
                  "model_hash": p.model.package.sha256(p.model.precision),
                  "calibration_version": p.cal.version}
        for out in self._outputs():
            out.publish_status(dict(status), seq=p.seq, t=result.t if result else None)

    def _maybe_reload(self) -> None:
        """Load a newly activated version; one that fails (pointer, hashes, types, non-finite or out-of-range
        tables, model size) is refused: the running version stays and `calibration_invalid` is raised
        until CURRENT names a good version again."""
        sid = self.pipeline.sensor_id
        current = None
        try:
            current = self.store.current(sid)
            if current == self.pipeline.cal.version:
                self.flags.discard("calibration_invalid")
                self._rejected = None
            elif current != self._rejected:
                cal = self.store.load(sid, current)
                self.pipeline.set_calibration(cal)
                self.flags.discard("calibration_invalid")
                self._rejected = None
                log.info("%s: calibration %s loaded without restart", sid, current)
        except (TensorTouchError, OSError, ValueError) as exc:
            self._rejected = current
            log.error("%s: calibration %s refused, keeping %s: %s", sid, current or "(unreadable CURRENT)",
                      self.pipeline.cal.version, exc)
            self.flags.add("calibration_invalid")
