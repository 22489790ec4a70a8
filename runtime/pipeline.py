"""One sensor's per-frame processing: frame → baseline → fields → contacts → corrected forces.

`SensorPipeline.process(frame, t)` = `finish(network_pass(frame, t), t)`: the network pass
(preprocess, baseline, inference, clusters, contact ids) and the finish (effects, correction,
wrench), so an offline replay (runtime/offline.py) can keep passes and re-finish them. It is pure
apart from its own state (baseline tracker, contact ids); it never touches devices or the network,
so the frame loop (runtime/apps/loop.py), the benchmark and every offline replay run exactly this code. Every stage is timed (ms) into `FrameResult.timings`.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, fields

import numpy as np

from ..contracts.store import Calibration
from .stages.baseline import BaselineConfig, BaselineTracker
from .stages.contacts import Cluster, ContactConfig, ContactTracker, find_clusters, pixel_forces
from .stages.correction import ForceCorrection
from .stages.effects import EffectChain
from .stages.effects.stage import EffectStage
from .stages.geometry import sample_bilinear
from .stages.model import FieldModel
from .stages.preprocess import Preprocessor

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class PipelineConfig:
    contacts: ContactConfig = field(default_factory=ContactConfig)
    baseline: BaselineConfig = field(default_factory=BaselineConfig)
    black_level: float = 4.0          # mean 0–255 below this: frame flagged "frame_black"
    frozen_frames: int = 30           # identical consecutive frames before "camera_frozen"
    # tare: subtract the network's fields for the baseline against itself from every frame's fields, so an
    # untouched gel reads zero (what the network reads there is its own offset: on frames unlike any it was trained
    # on, the shipped student reads 3-4-pixel cores at the same places in every frame). Recomputed, one extra
    # inference, whenever the baseline changes. A package carries its own choice (manifest `runtime.tare`, written
    # with the contact settings chosen on tared fields by tools/train/threshold.py)
    tare: bool = False

    @staticmethod
    def for_package(package) -> "PipelineConfig":
        """Defaults, with the package's own measured contact settings when its manifest has them
        (`runtime.contacts`: ContactConfig fields such as `threshold_n`, the light-touch rule
        `weak_threshold_n` / `min_total_n`, the cluster support `support_radius_px` / `support_floor_n`
        and merging `merge_n`, written at export by tools/train/threshold.py; null or absent = default) and
        its tare (`runtime.tare`, absent = off)."""
        rt = (getattr(package, "manifest", None) or {}).get("runtime") or {}
        return PipelineConfig(contacts=contact_config(rt), tare=bool(rt.get("tare") or False))


def _finite(fields: np.ndarray) -> tuple[np.ndarray, bool]:
    """(the fields with NaN/inf read as zero — the same array when all are finite, whether all were)."""
    finite = np.isfinite(fields)
    if finite.all():
        return fields, True
    return np.where(finite, fields, 0.0).astype(fields.dtype), False


def contact_config(runtime: dict) -> ContactConfig:
    """ContactConfig from a manifest's `runtime` section: `runtime.contacts` holds ContactConfig fields by
    their own names (null or absent keys keep the defaults)."""
    contacts = runtime.get("contacts") or {}
    ints = {f.name for f in fields(ContactConfig) if f.type in ("int", int)}
    return ContactConfig(**{k: (int(v) if k in ints else float(v)) for k, v in contacts.items() if v is not None})


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


@dataclass
class NetworkPass:
    """One frame's network half (`SensorPipeline.network_pass`): what the model and the contact
    tracker made of it, before effects and correction."""
    seq: int
    t: float
    fields: np.ndarray | None              # (15, H, W), None before the baseline exists (or not kept)
    clusters: list[Cluster]                # raw model forces
    state: str                             # baseline state
    flags: list[str]                       # frame health flags
    timings: dict[str, float]
    force_band: int                        # `force_band` of the force the baseline saw on this frame


def force_band(force_n: float | None, cfg: BaselineConfig) -> int:
    """What the baseline's contact test reads from a force estimate: 0 none, 1 below release,
    2 between release and contact, 3 at or above contact. A pass is valid after any finish that
    feeds the baseline the same bands."""
    if force_n is None:
        return 0
    if force_n >= cfg.force_contact_n:
        return 3
    return 1 if force_n < cfg.force_release_n else 2


def correction_inputs(clusters: list[Cluster], cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """The correction's position inputs of cluster centroids: uv (N, 2) in [0, 1] of the model image
    and θ/φ (N, 2) rad sampled from the calibration's tables."""
    h, w = cal.model_size
    px = np.array([c.uv_px for c in clusters], dtype=np.float64).reshape(-1, 2)
    uv = px * np.array([1.0 / w, 1.0 / h])
    tp = np.array([[sample_bilinear(cal.theta, u - 0.5, v - 0.5), sample_bilinear(cal.phi, u - 0.5, v - 0.5)]
                   for u, v in px], dtype=np.float64).reshape(-1, 2)
    return uv, tp


def contact_stage(fields: np.ndarray, cal: Calibration, cfg: ContactConfig) -> list[Cluster]:
    """The contacts stage on one frame's (15, H, W) physical fields: per-pixel forces, then the clusters
    of `cfg` (the package's `PipelineConfig.for_package(...).contacts` in the runtime), before tracking."""
    fp = pixel_forces(fields, cal.pixel_area)
    return find_clusters(fp, cal.surface_xyz, cal.normals, cal.pixel_area, cal.mask, disp=fields[0:3], cfg=cfg)


def apply_correction(clusters: list[Cluster], correction: ForceCorrection, cal: Calibration) -> None:
    """The correction stage on one frame's clusters (forces changed in place): the calibration's force
    correction of each cluster force at its centroid (`correction_inputs`); a no-op when disabled."""
    if clusters and correction.enabled:
        forces = np.array([c.force_n for c in clusters])
        uv, tp = correction_inputs(clusters, cal)
        for c, f in zip(clusters, correction(forces, uv, tp)):
            c.force_n = tuple(map(float, f))
            c.force_mag_n = float(np.linalg.norm(f))


def wrench_sum(clusters: list[Cluster]) -> tuple[np.ndarray, np.ndarray]:
    """Total force (3,) N and torque about the gel origin (3,) N*mm of clusters: Σ f and Σ p × f, in cluster
    order, in float64. Plain float arithmetic in np.cross's order (a1·b2 − a2·b1, a2·b0 − a0·b2,
    a0·b1 − a1·b0, each product rounded), so the same bits as `force += f; torque += np.cross(p, f)` from
    zeros, without numpy's per-call overhead; a cluster holding other number types (e.g. float32) takes
    that numpy way."""
    fx = fy = fz = tx = ty = tz = 0.0
    for c in clusters:
        p, f = c.position_mm, c.force_n
        if len(p) == len(f) == 3 and all(isinstance(v, float) for v in (*p, *f)):
            (p0, p1, p2), (f0, f1, f2) = p, f
            fx, fy, fz = fx + f0, fy + f1, fz + f2
            tx, ty, tz = tx + (p1 * f2 - p2 * f1), ty + (p2 * f0 - p0 * f2), tz + (p0 * f1 - p1 * f0)
        else:
            force, torque = np.array([fx, fy, fz]), np.array([tx, ty, tz])
            force += f
            torque += np.cross(p, f)
            (fx, fy, fz), (tx, ty, tz) = force.tolist(), torque.tolist()
    return np.array([fx, fy, fz]), np.array([tx, ty, tz])


def finish_clusters(clusters: list[Cluster], t: float, effects: EffectStage, correction: ForceCorrection,
                    cal: Calibration, timings: dict | None = None) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The pipeline's last steps on one frame's clusters (forces changed in place): the enabled
    effects, then the force correction, then the wrench. Returns (status flags, total force (3,) N,
    torque about the gel origin (3,) N*mm); `timings` gets "effects" and "correction" in ms."""
    t0 = time.perf_counter()
    flags = effects.apply(clusters, t)
    t1 = time.perf_counter()
    apply_correction(clusters, correction, cal)
    force, torque = wrench_sum(clusters)
    if timings is not None:
        timings["effects"] = (t1 - t0) * 1e3
        timings["correction"] = (time.perf_counter() - t1) * 1e3
    return flags, force, torque


def open_pipeline(package, calibration: Calibration, *, precision: str = "int8", threads: int = 1,
                  sensor_id: str | None = None, correction: ForceCorrection | None = None,
                  effects: bool = True, model=None) -> SensorPipeline:
    """The one constructor of a pipeline: what `tensortouch run` builds for a model package and a
    calibration version (the package's pipeline configuration). `correction` replaces the
    calibration's (ForceCorrection(None, None): raw model force); effects=False runs without the
    enabled effects; `model` is a loaded network of `package` to use (e.g. one shared by the fingers
    of a hand) instead of a new FieldModel(package, precision, threads)."""
    if model is None:
        model = FieldModel(package, precision, threads)
    pipe = SensorPipeline(sensor_id or calibration.sensor_id, model, calibration, correction=correction)
    if not effects:
        pipe.effects.chain = EffectChain()
    return pipe


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
            from ..contracts.errors import CalibrationError

            raise CalibrationError(
                f"calibration {calibration.sensor_id}/{calibration.version}: model_size "
                f"{list(calibration.model_size)} does not match model {self.model.package.name} "
                f"input size {list(self.model.package.size)}")
        previous = getattr(self, "cal", None)
        # build everything that can fail before swapping anything: a refused version leaves the old one whole
        correction = correction if correction is not None else ForceCorrection.from_calibration(calibration)
        effects = EffectStage(calibration)
        same = previous is not None and _same_geometry(previous, calibration)
        if not same:
            cx, cy = calibration.gel_center_px
            pre = Preprocessor(cx, cy, calibration.gel_radius_px, calibration.model_size)
            shape = self.pre.frame_shape if previous is not None else None
            if shape is not None:
                pre.prepare(shape)       # the circle must fit the frames this camera delivers
        temperature = self.effects.temperature if previous is not None else None
        max_depth = self.effects.max_depth if previous is not None else 0.0   # the gel's memory stays
        self.cal, self.correction, self.effects = calibration, correction, effects
        self.effects.temperature, self.effects.max_depth = temperature, max_depth
        if same:
            return  # only correction/effects changed: keep the baseline and the contact ids
        self.pre = pre
        self.baseline = BaselineTracker(self.cfg.baseline)
        self.tracker = ContactTracker(self.cfg.contacts)
        self._last_force = None
        self._prev_frame_sig = None
        self._frozen = 0
        self._zero, self._zero_of = None, None         # the tare and the baseline it was computed for

    def process(self, frame: np.ndarray, t: float) -> FrameResult:
        """frame: (H, W, 3) uint8 RGB camera image at time t (s)."""
        return self.finish(self.network_pass(frame, t), t)

    def network_pass(self, frame: np.ndarray, t: float) -> NetworkPass:
        """The expensive half of a frame: preprocess, baseline, inference, clusters and contact ids.
        It reads the force published for the previous frame (the baseline's contact test), so passes
        must be finished in order."""
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        img = self.pre.apply(frame)                      # (3, h, w) float32 in [0, 1]
        t1 = time.perf_counter()
        timings["preprocess"] = (t1 - t0) * 1e3
        flags = self._health(frame)
        band = force_band(self._last_force, self.cfg.baseline)
        step = self.baseline.update(img, self._last_force, t, owned=True)   # img is this frame's own array
        t2 = time.perf_counter()
        timings["baseline"] = (t2 - t1) * 1e3
        self.seq += 1
        if step.baseline is None:                        # still collecting startup frames
            timings.update(inference=0.0, contacts=0.0)
            return NetworkPass(self.seq, t, None, [], step.state.name, flags, timings, band)
        if self.cfg.tare and self._zero_of is not step.baseline:
            self._zero = _finite(self.model(np.concatenate([step.baseline, step.baseline], axis=0)))[0].copy()
            self._zero_of = step.baseline
        fields, valid = _finite(self.model(np.concatenate([step.baseline, img], axis=0)))
        if not valid:                                    # NaN/inf from the model: flagged, read as zero
            flags.append("model_output_invalid")
        if self.cfg.tare:
            if fields.flags.writeable and fields.dtype == self._zero.dtype:
                np.subtract(fields, self._zero, out=fields)
            else:
                fields = fields - self._zero
        t3 = time.perf_counter()
        timings["inference"] = (t3 - t2) * 1e3
        clusters = self.tracker.update(contact_stage(fields, self.cal, self.cfg.contacts))
        timings["contacts"] = (time.perf_counter() - t3) * 1e3
        return NetworkPass(self.seq, t, fields, clusters, step.state.name, flags, timings, band)

    def finish(self, passed: NetworkPass, t: float) -> FrameResult:
        """The cheap half: the enabled effects, the force correction and the wrench, on a pass's
        clusters (changed in place). Before the baseline exists no stage runs."""
        timings = dict(passed.timings)
        flags = list(passed.flags)
        clusters = passed.clusters
        if passed.state == "STARTUP":
            timings.update(effects=0.0, correction=0.0)
            return FrameResult(passed.seq, t, None, [], np.zeros(3), np.zeros(3), passed.state, flags, timings)
        more, force, torque = finish_clusters(clusters, t, self.effects, self.correction, self.cal, timings)
        flags += more
        self._last_force = float(np.linalg.norm(force))
        return FrameResult(passed.seq, t, passed.fields, clusters, force, torque, passed.state, flags, timings)

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
