"""In-process Python API: a camera frame in, fields, contacts and the wrench out. No Zenoh, no threads.

    from tensortouch.runtime.sensor import Sensor

    sensor = Sensor.open(sensor_id="TWIN-DEMO")            # newest installed model, active calibration
    out = sensor.process(frame_rgb, t)                     # (H, W, 3) uint8 RGB, time in s
    out.contacts                                           # list of dicts, as on the wire (docs/wire.md)
    out.force_n, out.torque_nmm, out.fields                # (3,) N, (3,) N·mm, (15, h, w) or None

    with Sensor.open(sensor_id="AB12") as s:                # frames from a camera (--source forms)
        for out in s.stream("usb:AB12"):
            ...

It builds the same objects `tensortouch run` does (model package lookup, calibration store, the
pipeline from `runtime.pipeline.open_pipeline`) and converts contacts with the same function the publisher's loop
uses, so a frame gives the same contacts and forces here as over Zenoh.
"""
from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Self

import numpy as np

from .apps.loop import to_wire_contacts
from .pipeline import FrameResult, SensorPipeline, open_pipeline

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SensorOutput:
    """One processed frame. Units: mm, N, N·mm, s (docs/fields.md)."""

    seq: int
    t: float
    state: str                       # baseline state (STARTUP while collecting the first frames)
    fields: np.ndarray | None        # (15, h, w) float32 in physical units; None before the baseline exists
    contacts: list[dict]             # wire Contact dicts: id, position_mm, normal, force_n, force_mag_n, area_mm2, ...
    force_n: np.ndarray              # total contact force (3,)
    torque_nmm: np.ndarray           # about the gel origin (3,)
    flags: list[str]                 # per-frame health flags (frame_black, camera_frozen, effects')
    result: FrameResult              # the pipeline's full result (timings, clusters)


class Sensor:
    """One sensor's model + calibration + per-sensor state (baseline, contact ids)."""

    def __init__(self, pipeline: SensorPipeline):
        self.pipeline = pipeline

    @classmethod
    def open(cls, sensor_id: str, model: str | Path | None = None, store: str | Path | None = None,
             precision: str = "int8", threads: int = 1, version: str | None = None) -> Sensor:
        """Load the model package (name or path; default the newest installed) and the sensor's
        calibration (active version, or `version`) from `store` (default calibration_store/)."""
        from ..contracts.store import CalibrationStore
        from .stages.model import find_package

        package = find_package(None if model is None else str(model))
        cal = CalibrationStore(store).load(sensor_id, version)
        return cls(open_pipeline(package, cal, precision=precision, threads=threads, sensor_id=sensor_id))

    # -- properties -------------------------------------------------------------------------
    @property
    def sensor_id(self) -> str:
        return self.pipeline.sensor_id

    @property
    def calibration_version(self) -> str:
        return self.pipeline.cal.version

    @property
    def channels(self) -> list[str]:
        return list(self.pipeline.model.package.manifest["output"]["channels"])

    @property
    def units(self) -> list[str]:
        return list(self.pipeline.model.package.manifest["output"]["units"])

    # -- frames -----------------------------------------------------------------------------
    def process(self, frame: np.ndarray, t: float, temperature_c: float | None = None) -> SensorOutput:
        """One (H, W, 3) uint8 RGB frame at time t (s); `temperature_c` feeds temperature effects."""
        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            from ..contracts.errors import CaptureError

            raise CaptureError(f"frame: shape {frame.shape} dtype {frame.dtype}, expected (H, W, 3) uint8 RGB")
        if temperature_c is not None:
            self.pipeline.set_temperature(temperature_c)
        r = self.pipeline.process(frame, float(t))
        return SensorOutput(r.seq, r.t, r.state, r.fields, to_wire_contacts(r), r.force_n, r.torque_nmm,
                            list(r.flags), r)

    def stream(self, source: str, max_frames: int | None = None) -> Iterator[SensorOutput]:
        """Process frames from a camera source string (usb:SERIAL, v4l2:..., replay:DIR?realtime=0)
        until it ends or `max_frames` were processed."""
        from ..drivers.camera import camera_from_uri
        from ..drivers.camera.camera import EndOfStream

        n = 0
        with camera_from_uri(source) as cam:
            while max_frames is None or n < max_frames:
                try:
                    frame = cam.read()
                except EndOfStream:
                    return
                n += 1
                yield self.process(frame.image, frame.t)

    def close(self) -> None:
        """Nothing to release (no devices, no network); kept for `with` blocks."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
