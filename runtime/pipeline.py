"""One sensor's per-frame processing: frame → baseline → fields → contacts → corrected forces.

`SensorPipeline.process(frame, t)` is pure apart from its own state (baseline tracker, contact ids);
it never touches devices or the network, so the frame loop (runtime/loop.py), the benchmark and
the workbench all run exactly this code. Every stage is timed (ms) into `FrameResult.timings`.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from runtime.baseline import BaselineConfig, BaselineTracker
from runtime.calibration import Calibration
from runtime.contacts import Cluster, ContactConfig, ContactTracker, find_clusters, pixel_forces
from runtime.correction import ForceCorrection
from runtime.effect_stage import EffectStage
from runtime.geometry import sample_bilinear
from runtime.model import FieldModel
from runtime.preprocess import Preprocessor

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class PipelineConfig:
    contacts: ContactConfig = field(default_factory=ContactConfig)
    baseline: BaselineConfig = field(default_factory=BaselineConfig)
    black_level: float = 4.0          # mean 0–255 below this: frame flagged "frame_black"
    frozen_frames: int = 30           # identical consecutive frames before "camera_frozen"

    @staticmethod
    def for_package(package) -> "PipelineConfig":
        """Defaults, with the package's own measured contact threshold when its manifest has one
        (`runtime.contact_threshold_n`, the light-touch rule `contact_weak_threshold_n` /
        `contact_min_total_n`, the cluster support `contact_support_radius_px` /
        `contact_support_floor_n` and merging `contact_merge_n`, written at export by
        tools/train/threshold.py; null or absent = default)."""
        rt = (getattr(package, "manifest", None) or {}).get("runtime") or {}
        return PipelineConfig(contacts=contact_config(rt))


MANIFEST_CONTACT_KEYS = (("threshold_n", "contact_threshold_n"), ("weak_threshold_n", "contact_weak_threshold_n"),
                         ("min_total_n", "contact_min_total_n"), ("support_radius_px", "contact_support_radius_px"),
                         ("support_floor_n", "contact_support_floor_n"), ("merge_n", "contact_merge_n"))


def contact_config(runtime: dict) -> ContactConfig:
    """ContactConfig from a manifest's `runtime` section (null or absent keys keep the defaults)."""
    return ContactConfig(**{k: float(runtime[m]) for k, m in MANIFEST_CONTACT_KEYS if runtime.get(m) is not None})


@dataclass
class FrameResult:
    seq: int
    t: float
    fields: np.ndarray | None              # (15, H, W) physical units, None before the baseline exists
    clusters: list[Cluster]
    force_n: np.ndarray                    # total contact force (3,), N
    torque_nmm: np.ndarray                 # about the gel origin (3,), N*mm
    state: str
    flags: list[str]
    timings: dict[str, float]              # ms per stage


def _same_geometry(a: Calibration, b: Calibration) -> bool:
    """True when two calibration versions share the crop and every geometry table (same hashes)."""
    keys = ("gel_center_px", "gel_radius_px", "model_size")
    if any(a.meta.get(k) != b.meta.get(k) for k in keys):
        return False
    fa, fb = a.meta.get("files", {}), b.meta.get("files", {})
    return all(fa.get(f) == fb.get(f) and fa.get(f) is not None for f in a.meta["tables"].values())


class SensorPipeline:
    """Holds one sensor's model, calibration and per-sensor state."""

    def __init__(self, sensor_id: str, model: FieldModel, calibration: Calibration,
                 config: PipelineConfig | None = None, correction: ForceCorrection | None = None):
        self.sensor_id = sensor_id
        self.cfg = config or PipelineConfig.for_package(model.package)
        self.model = model
        self.seq = 0
        self.set_calibration(calibration, correction)

    def set_calibration(self, calibration: Calibration, correction: ForceCorrection | None = None) -> None:
        """Swap calibration (e.g. a new version after recalibration) without a restart."""
        if tuple(calibration.model_size) != tuple(self.model.package.size):
            from runtime.errors import CalibrationError

            raise CalibrationError(
                f"calibration {calibration.sensor_id}/{calibration.version}: model_size "
                f"{list(calibration.model_size)} does not match model {self.model.package.name} "
                f"input size {list(self.model.package.size)}")
        previous = getattr(self, "cal", None)
        # build everything that can fail before swapping anything: a refused version leaves the old one whole
        correction = correction if correction is not None else ForceCorrection.from_calibration(calibration)
        effects = EffectStage(calibration)
        temperature = self.effects.temperature if previous is not None else None
        max_depth = self.effects.max_depth if previous is not None else 0.0   # the gel's memory stays
        self.cal, self.correction, self.effects = calibration, correction, effects
        self.effects.temperature, self.effects.max_depth = temperature, max_depth
        if previous is not None and _same_geometry(previous, calibration):
            return  # only correction/effects changed: keep the baseline and the contact ids
        cx, cy = calibration.gel_center_px
        self.pre = Preprocessor(cx, cy, calibration.gel_radius_px, calibration.model_size)
        self.baseline = BaselineTracker(self.cfg.baseline)
        self.tracker = ContactTracker(self.cfg.contacts)
        self._last_force = None
        self._prev_frame_sig = None
        self._frozen = 0
        h, w = calibration.model_size
        self._uv_scale = np.array([1.0 / w, 1.0 / h])

    def process(self, frame: np.ndarray, t: float) -> FrameResult:
        """frame: (H, W, 3) uint8 RGB camera image at time t (s)."""
        timings: dict[str, float] = {}
        flags: list[str] = []
        t0 = time.perf_counter()
        img = self.pre.apply(frame)                      # (3, h, w) float32 in [0, 1]
        t1 = time.perf_counter()
        timings["preprocess"] = (t1 - t0) * 1e3
        flags += self._health(frame)
        step = self.baseline.update(img, self._last_force, t)
        t2 = time.perf_counter()
        timings["baseline"] = (t2 - t1) * 1e3
        self.seq += 1
        if step.baseline is None:                        # still collecting startup frames
            timings.update(inference=0.0, contacts=0.0, effects=0.0, correction=0.0)
            return FrameResult(self.seq, t, None, [], np.zeros(3), np.zeros(3), step.state.name, flags, timings)
        x = np.concatenate([step.baseline, img], axis=0)
        fields = self.model(x)
        finite = np.isfinite(fields)
        if not finite.all():                             # NaN/inf from the model: flagged, read as zero
            flags.append("model_output_invalid")
            fields = np.where(finite, fields, 0.0).astype(fields.dtype)
        t3 = time.perf_counter()
        timings["inference"] = (t3 - t2) * 1e3
        cal = self.cal
        fp = pixel_forces(fields, cal.pixel_area)
        clusters = find_clusters(fp, cal.surface_xyz, cal.normals, cal.pixel_area, cal.mask,
                                 disp=fields[0:3], cfg=self.cfg.contacts)
        clusters = self.tracker.update(clusters)
        t35 = time.perf_counter()
        timings["contacts"] = (t35 - t3) * 1e3
        flags += self.effects.apply(clusters, t)
        t4 = time.perf_counter()
        timings["effects"] = (t4 - t35) * 1e3
        if clusters and self.correction.enabled:
            forces = np.array([c.force_n for c in clusters])
            uv = np.array([c.centroid_px for c in clusters]) * self._uv_scale
            tp = np.array([[sample_bilinear(cal.theta, u - 0.5, v - 0.5), sample_bilinear(cal.phi, u - 0.5, v - 0.5)]
                           for u, v in (c.centroid_px for c in clusters)])
            corrected = self.correction(forces, uv, tp)
            for c, f in zip(clusters, corrected):
                c.force_n = tuple(map(float, f))
                c.force_mag_n = float(np.linalg.norm(f))
        force = np.zeros(3)
        torque = np.zeros(3)
        for c in clusters:
            force += c.force_n
            torque += np.cross(c.centroid_mm, c.force_n)
        self._last_force = float(np.linalg.norm(force))
        timings["correction"] = (time.perf_counter() - t4) * 1e3
        return FrameResult(self.seq, t, fields, clusters, force, torque, step.state.name, flags, timings)

    def set_temperature(self, celsius: float | None) -> None:
        """Gel temperature from a sensor (°C), for effects that need it (None = unknown)."""
        self.effects.temperature = celsius

    def _health(self, frame: np.ndarray) -> list[str]:
        flags = []
        small = frame[::16, ::16]
        if float(small.mean()) < self.cfg.black_level:
            flags.append("frame_black")
        sig = small.tobytes()
        self._frozen = self._frozen + 1 if sig == self._prev_frame_sig else 0
        self._prev_frame_sig = sig
        if self._frozen >= self.cfg.frozen_frames:
            flags.append("camera_frozen")
        return flags
