"""Twin units: per-unit manufacturing variation from a serial, and each unit's TRUE calibration.

A serial (e.g. "TWIN-0001") seeds a generator (sha256 of the serial), which draws the unit's gel
stiffness scale, image centre offset, focal length scale and per-LED brightness. The true
calibration (θ/φ, surface_xyz, normals, pixel_area, mask per model pixel, gel centre/radius in
px) is what the calibration stage must later recover; `write_true_calibration` stores it with
contracts.store.CalibrationStore (provenance method "twin-truth").
"""
from __future__ import annotations

import hashlib
import logging
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ...runtime.calib.bringup import GelShape
from .camera import CameraConfig, FisheyeModel, LEDConfig, NoiseConfig, PatternConfig, Renderer
from .geometry import GelSurface

log = logging.getLogger(__name__)


@dataclass
class VariationConfig:
    """Spread of manufacturing variation between units (uniform ranges, ± around nominal)."""

    stiffness: float = 0.12      # relative
    center_px: float = 6.0       # px, each axis
    focal: float = 0.04          # relative
    led: float = 0.10            # relative, per LED


@dataclass
class UnitParams:
    serial: str
    seed: int
    stiffness_scale: float
    center_offset_px: tuple[float, float]
    focal_scale: float
    led_brightness: list[float]

    def to_dict(self) -> dict:
        return asdict(self)


UNIT_OVERRIDES = ("stiffness_scale", "center_offset_px", "focal_scale", "led_brightness")


def serial_seed(serial: str) -> int:
    return int(hashlib.sha256(serial.encode()).hexdigest()[:12], 16)


def unit_params(serial: str, var: VariationConfig | None = None, n_leds: int = 9) -> UnitParams:
    var = var or VariationConfig()
    seed = serial_seed(serial)
    rng = np.random.default_rng(seed)
    return UnitParams(serial, seed,
                      float(1 + rng.uniform(-var.stiffness, var.stiffness)),
                      (float(rng.uniform(-var.center_px, var.center_px)),
                       float(rng.uniform(-var.center_px, var.center_px))),
                      float(1 + rng.uniform(-var.focal, var.focal)),
                      [float(1 + rng.uniform(-var.led, var.led)) for _ in range(n_leds)])


@dataclass
class TwinUnit:
    """One simulated sensor: nominal design + its unit's variation."""

    serial: str
    gel: GelSurface = field(default_factory=GelSurface)
    camera: CameraConfig = field(default_factory=CameraConfig)
    leds: LEDConfig = field(default_factory=LEDConfig)
    pattern: PatternConfig = field(default_factory=PatternConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    variation: VariationConfig = field(default_factory=VariationConfig)
    override: dict | None = None   # explicit values for UNIT_OVERRIDES keys (e.g. an acceptance unit)
    world: object = None           # a tools.twin.world.WorldUnit (world "rig"): its gel and camera offset

    def __post_init__(self):
        self.params = unit_params(self.serial, self.variation, self.leds.count)
        if self.override:
            bad = sorted(set(self.override) - set(UNIT_OVERRIDES))
            if bad:
                raise ValueError(f"TwinUnit {self.serial}: override keys {bad} not in {UNIT_OVERRIDES}")
            o = {k: (tuple(float(x) for x in v) if k == "center_offset_px" else
                     [float(x) for x in v] if k == "led_brightness" else float(v)) for k, v in self.override.items()}
            self.params = replace(self.params, **o)
        p = self.params
        self.camera_true = replace(self.camera, cx=self.camera.cx + p.center_offset_px[0],
                                   cy=self.camera.cy + p.center_offset_px[1],
                                   focal_px=self.camera.focal_px * p.focal_scale)
        self.model = FisheyeModel(self.camera_true)
        self.design_gel = self.gel            # what the unit's drawings say (its calibration's meta.gel)
        if self.world is not None:            # the rig world's gel, and the camera beside the gel axis
            self.gel = self.world.gel
            dx, dy = self.world.camera_offset_mm
            self.model.center = np.array([float(dx), float(dy), self.camera_true.cam_z])
        self._renderer = None

    @property
    def renderer(self) -> Renderer:
        if self._renderer is None:
            self._renderer = Renderer(self.model, self.gel, self.leds, self.pattern, self.noise,
                                      np.asarray(self.params.led_brightness))
        return self._renderer

    @property
    def gel_center_px(self) -> tuple[float, float]:
        """Image of the gel apex = the optical centre (camera on the dome axis)."""
        uv = self.model.project(np.array([0.0, 0.0, self.gel.top_z]))
        return float(uv[0]), float(uv[1])

    @property
    def gel_radius_px(self) -> float:
        return self.model.rim_radius_px(self.gel)

    def describe(self) -> dict:
        d = {"serial": self.serial, "params": self.params.to_dict(), "gel": asdict(self.gel),
             "camera_nominal": asdict(self.camera), "camera_true": asdict(self.camera_true),
             "leds": asdict(self.leds), "pattern": asdict(self.pattern), "noise": asdict(self.noise)}
        if self.world is not None:
            d["world"] = self.world.to_dict()
        return d


def true_tables(unit: TwinUnit, model_size: int = 128) -> dict[str, np.ndarray]:
    """The unit's exact per-model-pixel tables (calibration store contract)."""
    from ...runtime.stages.preprocess import Preprocessor

    cx, cy = unit.gel_center_px
    pre = Preprocessor(cx, cy, unit.gel_radius_px, model_size)
    S = model_size
    v, u = np.mgrid[0:S, 0:S].astype(np.float64)

    def surface(uu, vv):
        x, y = pre.to_raw(uu, vv)
        dirs, fov = unit.model.rays(np.stack([x, y], -1))
        pts, ok = unit.gel.intersect(unit.model.center, dirs)
        return pts, ok & fov

    pts, ok = surface(u, v)
    theta, phi = unit.design_gel.theta_phi(pts)     # θ about the design's cap sphere centre, as meta.gel says
    normals = unit.gel.normals(pts)
    h = 0.5
    dxu = (surface(u + h, v)[0] - surface(u - h, v)[0]) / (2 * h)
    dxv = (surface(u, v + h)[0] - surface(u, v - h)[0]) / (2 * h)
    area = np.linalg.norm(np.cross(dxu, dxv), axis=-1)
    for arr in (pts, normals):
        arr[~ok] = 0.0
    return {"theta": np.where(ok, theta, 0.0), "phi": np.where(ok, phi, 0.0), "surface_xyz": pts,
            "normals": normals, "pixel_area": np.where(ok, area, 0.0), "mask": ok}


def calibration_meta(unit: TwinUnit, model_size: int = 128) -> dict:
    """The calibration's metadata. `gel` is the gel's design (what a rig's store holds and the label FE
    uses), also for a rig-world unit whose own gel differs: that one is in provenance.unit_gel."""
    g = unit.design_gel
    meta = {"camera": {"width": unit.camera.width, "height": unit.camera.height},
            "gel_center_px": list(unit.gel_center_px), "gel_radius_px": unit.gel_radius_px,
            "model_size": [model_size, model_size],
            "gel": GelShape(g.radius, g.cap_height, g.skirt).meta(),
            "provenance": {"method": "twin-truth", "pokes": 0,
                           "notes": f"exact tables of twin unit {unit.serial} (tools.twin.unit)",
                           "unit": unit.params.to_dict()}}
    if unit.world is not None:
        w = unit.gel
        meta["provenance"]["unit_gel"] = GelShape(w.radius, w.cap_height, w.skirt).meta()
    return meta


def write_true_calibration(unit: TwinUnit, root=None, model_size: int = 128, force: bool = False) -> str:
    """Store the unit's true calibration as a new version under calibration_store/<serial>/;
    when the current version already holds exactly these tables, keep it (unless `force`)."""
    from ...contracts.store import CalibrationStore

    store = CalibrationStore(root)
    tables = true_tables(unit, model_size)
    with store.locked(unit.serial):      # compare with the current version and write in one step
        return _write_truth(store, unit, tables, model_size, force)


def _write_truth(store, unit: TwinUnit, tables: dict, model_size: int, force: bool) -> str:
    from ...contracts.errors import CalibrationError

    if not force and unit.serial in store.sensors():
        try:
            cur = store.load(unit.serial)
            same = all(np.array_equal(getattr(cur, k), np.asarray(v).astype(bool if k == "mask" else np.float32))
                       for k, v in tables.items()) and cur.meta.get("provenance", {}).get("method") == "twin-truth"
        except CalibrationError:
            same = False
        if same:
            log.info("true calibration of %s unchanged (%s)", unit.serial, cur.version)
            return cur.version
    version = store.write(unit.serial, tables, calibration_meta(unit, model_size))
    log.info("true calibration of %s written as %s", unit.serial, version)
    return version
