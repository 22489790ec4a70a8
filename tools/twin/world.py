"""The twin's world: the physics and the rig a recording is made in, as opposed to what the labels assume.

World `label` is the twin as it always was: the recording's FE is the label solver's FE (nominal gel,
nominal Yeoh silicone times one per-unit force factor, the same mesh and locking cap), its noise is
white, its mocap is already in the sensor frame and every clock is the camera's. It is the ceiling:
labels and measurements share one physics.

World `rig` differs from the labels in named, sized ways (`WorldConfig`, docs/twin.md "Worlds"), each
drawn per unit from a generator seeded by the unit's serial (`draw_world`):

- gel geometry the images show: cap height (thickness), base radius, gel axis off the camera axis;
- stiffness: each Yeoh constant of the unit's silicone, not one force factor;
- mocap: poses recorded in the mocap frame; the session carries a calibrated but imperfect extrinsic;
- F/T: a bias and cross-talk between its axes;
- clocks: the mocap and F/T stamps run ahead of / behind the camera's;
- coloured noise: AR(1) F/T and mocap noise (same stationary σ as the rig's white noise);
- FE of the world at a finer mesh (and, optionally, quadratic tets with the material's true bulk).

The pure cores below (`ar1_filter`, `distort_ft`, `sensor_to_mocap`, `calibrated_extrinsic`,
`stamp`) are what record.py applies; the recipe estimates what a rig would from the session's data
(tools/train/rig_estimate.py).
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np
from scipy.spatial.transform import Rotation

from ...contracts.errors import TensorTouchError
from .geometry import GelSurface

WORLDS = ("label", "rig")
MODULES = 2               # indentation modules of the twin's rig (tools.twin.signals.RigConfig.park)
WORLD_STREAM = 42          # the world's draws use their own generator stream, so the unit's old draws stay


@dataclass(frozen=True)
class WorldConfig:
    """Sizes of the rig world's differences from the label solver. `U ±a`: uniform in [-a, a] per unit;
    `N σ`: normal. Nominal values are the label solver's (tools.fe defaults, tools.twin.signals.RigConfig)."""

    # gel geometry (nominal: base radius 12 mm, cap height 6 mm, skirt 2 mm)
    cap_height_mm: float = 0.3          # U ± : gel thickness above the skirt
    radius_mm: float = 0.2              # U ± : base radius
    center_mm: float = 0.25             # U ± per axis: gel axis off the camera's optical axis
    # stiffness (nominal Yeoh C10 0.03, C20 0.002, C30 0.0002 MPa), relative, each independently
    c10: float = 0.12                   # U ± (the label world's one force factor had the same ±12 %)
    c20: float = 0.30                   # U ±
    c30: float = 0.30                   # U ±
    # mocap: where the mocap origin sits (fixed rig layout), then the extrinsic calibration's error
    mocap_origin_mm: tuple = (150.0, -80.0, -40.0)   # mocap origin in the sensor frame
    mocap_yaw_deg: float = 90.0                       # mocap axes turned about the sensor's z
    extrinsic_rotation_deg: float = 0.3               # N σ per axis, about the sensor origin
    extrinsic_translation_mm: float = 0.3             # N σ per axis
    # F/T
    ft_bias_n: float = 0.2              # U ± per force axis
    ft_bias_nmm: float = 4.0            # U ± per torque axis
    ft_crosstalk: float = 0.02          # U ± each off-diagonal term inside the force and the torque block
    # clocks, against the camera's (a stream stamped +δ reports an event δ late)
    clock_mocap_s: float = 0.015        # U ±
    clock_ft_s: float = 0.015           # U ±
    # coloured noise: AR(1) coefficient per sample of the F/T and mocap noise (0 = white)
    noise_ar1: float = 0.9
    # FE of the world (the twin's label-world FE: 1.0 / 2.5 mm linear tets, bulk capped at 5 µ0)
    fe_mesh_top: float = 0.7
    fe_mesh_inside: float = 2.0
    fe_order: int = 1                   # 2 = quadratic u/p/J tets with the material's own D1 (slow)
    fe_max_bulk_ratio: float = 5.0

    @classmethod
    def with_overrides(cls, overrides: dict | None, where: str = "world") -> "WorldConfig":
        names = {f.name for f in fields(cls)}
        bad = sorted(set(overrides or {}) - names)
        if bad:
            raise TensorTouchError(f"{where}: unknown world parameters {bad} (known: {sorted(names)})")
        defaults, o = cls(), {}
        for k, v in (overrides or {}).items():
            want = getattr(defaults, k)
            try:
                if isinstance(want, tuple):
                    if len(v) != len(want):
                        raise ValueError
                    o[k] = tuple(float(x) for x in v)
                elif isinstance(want, int):
                    o[k] = int(v) if float(v) == int(v) else None
                else:
                    o[k] = float(v)
            except (TypeError, ValueError):
                o[k] = None
            if o[k] is None or not np.all(np.isfinite(o[k])):
                raise TensorTouchError(f"{where}.{k} is {v!r}, expected {type(want).__name__} like {want!r}")
        cfg = replace(defaults, **o)
        bad = [f.name for f in fields(cls) if f.name not in ("mocap_origin_mm", "mocap_yaw_deg")
               and np.any(np.asarray(getattr(cfg, f.name)) < 0)]
        if bad or not cfg.noise_ar1 < 1.0 or cfg.fe_order not in (1, 2):
            raise TensorTouchError(f"{where}: {bad or ['noise_ar1', 'fe_order']} out of range (sizes >= 0, "
                                   "0 <= noise_ar1 < 1, fe_order 1 or 2)")
        return cfg


@dataclass
class WorldUnit:
    """One unit's draw of the rig world (everything `record.py` needs, in house units)."""

    serial: str
    gel: GelSurface
    camera_offset_mm: tuple[float, float]        # optical centre relative to the gel axis (x, y)
    yeoh: tuple[float, float, float]             # C10, C20, C30 (MPa)
    mocap_rotvec: tuple                           # true extrinsic p_sensor = R p_mocap + t
    mocap_translation_mm: tuple
    extrinsic_error_rotvec: tuple                 # calibration error: a rigid motion of the sensor frame
    extrinsic_error_mm: tuple
    ft_bias: list                                 # per indentation module: 6 (N, N*mm)
    ft_crosstalk: list                            # per module: 6x6 matrix, reading = C @ true + bias
    clock_offset_s: dict                          # {"poses": δ, "wrench": δ}
    noise_ar1: float
    config: WorldConfig = field(default_factory=WorldConfig)

    def extrinsic_true(self) -> tuple[np.ndarray, np.ndarray]:
        return Rotation.from_rotvec(self.mocap_rotvec).as_matrix(), np.asarray(self.mocap_translation_mm, float)

    def extrinsic_calibrated(self) -> tuple[np.ndarray, np.ndarray]:
        return calibrated_extrinsic(*self.extrinsic_true(), Rotation.from_rotvec(self.extrinsic_error_rotvec).as_matrix(),
                                    np.asarray(self.extrinsic_error_mm, float))

    def material(self):
        """The unit's tools.fe Material: its own Yeoh constants, the nominal bulk/shear ratio."""
        from ..fe import Material

        nominal = Material()
        c10, c20, c30 = self.yeoh
        ratio = nominal.bulk_modulus / nominal.shear_modulus
        return replace(nominal, C10=c10, C20=c20, C30=c30, D1=2.0 / (ratio * 2.0 * c10))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["gel"] = asdict(self.gel)
        R, t = self.extrinsic_calibrated()
        d["extrinsic_calibrated"] = {"rotation_wxyz": quat_wxyz_of(R), "translation_mm": [float(v) for v in t]}
        return _plain(d)


def _plain(x):
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def world_seed(serial: str) -> list[int]:
    return [int(hashlib.sha256(serial.encode()).hexdigest()[:12], 16), WORLD_STREAM]


def draw_world(serial: str, cfg: WorldConfig = WorldConfig(), gel: GelSurface = GelSurface()) -> WorldUnit:
    """The rig world of unit `serial` (same serial and config → same world, always)."""
    from ..fe import Material

    rng = np.random.default_rng(world_seed(serial))
    u = lambda a, n=None: rng.uniform(-a, a, n)          # noqa: E731 — one draw helper, in a fixed order
    g = GelSurface(radius=gel.radius + float(u(cfg.radius_mm)), cap_height=gel.cap_height + float(u(cfg.cap_height_mm)),
                   skirt=gel.skirt)
    cam = tuple(float(v) for v in u(cfg.center_mm, 2))
    m = Material()
    yeoh = (m.C10 * (1 + float(u(cfg.c10))), m.C20 * (1 + float(u(cfg.c20))), m.C30 * (1 + float(u(cfg.c30))))
    err_rot = tuple(float(v) for v in np.radians(rng.normal(0.0, cfg.extrinsic_rotation_deg, 3)))
    err_t = tuple(float(v) for v in rng.normal(0.0, cfg.extrinsic_translation_mm, 3))
    bias, cross = [], []
    for _ in range(MODULES):              # each indentation module carries its own F/T
        bias.append([float(v) for v in np.concatenate([u(cfg.ft_bias_n, 3), u(cfg.ft_bias_nmm, 3)])])
        C = np.eye(6)
        for blk in (slice(0, 3), slice(3, 6)):
            off = u(cfg.ft_crosstalk, (3, 3))
            C[blk, blk] += off - np.diag(np.diag(off))
        cross.append(C.tolist())
    clocks = {"poses": float(u(cfg.clock_mocap_s)), "wrench": float(u(cfg.clock_ft_s))}
    return WorldUnit(serial, g, cam, yeoh, (0.0, 0.0, float(np.radians(cfg.mocap_yaw_deg))),
                     tuple(float(v) for v in cfg.mocap_origin_mm), err_rot, err_t, bias, cross, clocks,
                     float(cfg.noise_ar1), cfg)


# ------------------------------------------------------------------------------------- pure cores

def ar1_filter(white: np.ndarray, phi: float) -> np.ndarray:
    """AR(1) noise along axis 0 from white innovations of std σ: y₀ = e₀, yₖ = φ yₖ₋₁ + √(1 − φ²) eₖ — its
    stationary std is σ (the white noise's), its autocorrelation at lag k is φᵏ (coloured: power at
    low frequencies). φ = 0 returns the white noise itself."""
    e = np.asarray(white, np.float64)
    if not 0.0 <= phi < 1.0:
        raise ValueError(f"ar1_filter: φ = {phi}, expected 0 <= φ < 1")
    if phi == 0.0 or len(e) == 0:
        return e
    from scipy.signal import lfilter

    y = np.empty_like(e)
    y[0] = e[0]
    if len(e) > 1:
        y[1:] = lfilter([np.sqrt(1.0 - phi * phi)], [1.0, -phi], e[1:], axis=0, zi=phi * e[:1])[0]
    return y


def distort_ft(ft: np.ndarray, crosstalk: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """An F/T's reading (T, 6) of the true load (T, 6): cross-talk matrix then bias, r = C f + b."""
    ft = np.asarray(ft, np.float64)
    if ft.ndim != 2 or ft.shape[1] != 6:
        raise ValueError(f"distort_ft: expected (T, 6) loads, got {ft.shape}")
    return ft @ np.asarray(crosstalk, np.float64).T + np.asarray(bias, np.float64)


def calibrated_extrinsic(R: np.ndarray, t: np.ndarray, R_err: np.ndarray, t_err: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """The extrinsic a calibration reports when its error is the rigid motion (R_err, t_err) of the sensor
    frame: p_cal = R_err (R p + t) + t_err, i.e. (R_err R, R_err t + t_err)."""
    return R_err @ R, R_err @ np.asarray(t, float) + np.asarray(t_err, float)


def sensor_to_mocap(pos: np.ndarray, rotvec: np.ndarray, R: np.ndarray, t: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Poses (positions (T, 3) mm, rotation vectors (T, 3) indenter → sensor) in the mocap frame, for the
    extrinsic p_sensor = R p_mocap + t: p_mocap = Rᵀ (p − t), R_mocap = Rᵀ R_pose."""
    p = (np.asarray(pos, float) - np.asarray(t, float)) @ np.asarray(R, float)
    rv = (Rotation.from_matrix(np.asarray(R, float).T) * Rotation.from_rotvec(np.asarray(rotvec, float))).as_rotvec()
    return p, rv


def stamp(t: np.ndarray, offset_s: float) -> np.ndarray:
    """The stamps a stream whose clock runs `offset_s` ahead of the camera's puts on samples taken at
    camera times t."""
    return np.asarray(t, float) + float(offset_s)


def quat_wxyz_of(R: np.ndarray) -> list[float]:
    q = Rotation.from_matrix(np.asarray(R, float)).as_quat()
    q = q if q[3] >= 0 else -q
    return [float(q[3]), float(q[0]), float(q[1]), float(q[2])]
