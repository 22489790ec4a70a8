"""Stage 2 core — FE scenarios from the stage-1 keypoints of MEASURED streams (seed §III.C–E).

What a real rig has: the mocap pose of every indentation module (session `poses`, already in the
sensor frame per docs/session.md — the bag importer maps the mocap world into it through the rig's
base/extrinsic transform), the F/T readings, the names of the mounted indenters (session metadata
`streams.poses.indenters`) and the gel's design geometry (the unit's calibration `meta.gel`). No
plan, no truth. Per stage-1 contact period this module builds one tools.fe scenario:

- **poses**: the measured tip pose at a time is a local quadratic least-squares fit of the mocap
  samples within ±`pose_half_window_s` (position) and the chordal mean of the rotations in the same
  window (mocap noise ~0.05 mm / 0.002 rad per sample, seed appendix);
- **initial pose**: stage 1 starts a period 0.3 s before the 1.5 N crossing, which for a slow press
  is already in contact, while an FE scenario must start clear of the gel; so the initial pose is the
  latest measured pose before the first keypoint at which every indenter of the period clears the
  rest gel by ≥ `clear_gap_mm` (indenter SDF of tools.fe at the rest surface samples);
- **FE frames** = the stage-1 keypoints (≤ 12 per contact, start and end kept), plus intermediate
  measured poses wherever two consecutive keypoints are more than `max_step_mm` / `max_step_rad`
  apart (the twin's keypoint spacing), so every FE frame is a measured pose and label
  interpolation between frames stays short;
- keypoints relative to the initial pose in the FE contract (docs/fe.md): translation p − p0,
  rotation vector of R·R0⁻¹.

Pure cores: `fit_pose`, `clearance`, `initial_time`, `densify`, `period_scenario`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ...contracts.errors import TensorTouchError

log = logging.getLogger(__name__)


class ResolveError(TensorTouchError):
    """A contact period cannot be turned into an FE scenario (no clear initial pose, unknown indenter)."""


@dataclass(frozen=True)
class ResolveConfig:
    """Stage-2 numbers as named defaults (mm, rad, s)."""

    mesh_top_mm: float = 1.0              # the twin's FE mesh (tools.twin.record.RecordConfig.fe_mesh_top)
    mesh_inside_mm: float = 2.5           # ... and fe_mesh_inside, so results compare node by node
    pose_half_window_s: float = 0.035     # mocap smoothing window (± s) around each FE frame time
    clear_gap_mm: float = 0.05            # initial pose: clear of the rest gel by this (twin approach gap)
    search_back_s: float = 2.0            # how far before the first keypoint to look for a clear pose
    max_step_mm: float = 0.5              # FE frames at most this far apart (translation) ...
    max_step_rad: float = 0.08            # ... and rotation (the twin's keypoint spacing)
    surface_spacing_mm: float = 0.4       # rest-surface samples for the clearance test
    workers: int = 1                      # FE batch worker processes (2 cores shared)
    retry_increment_factor: float = 0.5   # a failed scenario is retried once with smaller increments
    scenario_name: str = "train-resolve"  # part of the scenario hash: keep it constant


@dataclass
class PoseTrack:
    """Measured poses of one indenter: t (N,), position (N, 3) mm, quaternion (N, 4) wxyz."""

    t: np.ndarray
    position: np.ndarray
    quaternion: np.ndarray

    @staticmethod
    def from_table(poses: np.ndarray, indenter: int) -> "PoseTrack":
        p = np.asarray(poses, float)
        p = p[p[:, 1] == indenter]
        if len(p) < 3:
            raise ResolveError(f"poses: indenter {indenter} has {len(p)} samples, expected ≥ 3")
        return PoseTrack(p[:, 0], p[:, 2:5], p[:, 5:9])


@dataclass
class PeriodScenario:
    """An FE scenario of one contact period and what its frames are."""

    scenario: object                      # tools.fe.Scenario
    t_init: float                         # time of the initial (clear) pose
    times: np.ndarray                     # (J,) time of each FE frame (session clock, s)
    is_keypoint: np.ndarray               # (J,) True where the frame is a stage-1 keypoint
    slots: list[int]                      # session indenter id of each scenario indenter
    names: list[str] = field(default_factory=list)


def fit_pose(track: PoseTrack, t: np.ndarray, half_window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed poses at times t: position (T, 3) by a local quadratic fit over ±half_window_s,
    rotation (T, 3 rotvec, local → sensor) by the mean rotation of the same samples."""
    t = np.atleast_1d(np.asarray(t, float))
    pos, rot = np.zeros((len(t), 3)), np.zeros((len(t), 3))
    allrot = Rotation.from_quat(track.quaternion, scalar_first=True)
    for i, ti in enumerate(t):
        sel = np.flatnonzero(np.abs(track.t - ti) <= half_window_s)
        if len(sel) < 4:   # too few samples: nearest ones
            sel = np.sort(np.argsort(np.abs(track.t - ti))[:4])
        dt = track.t[sel] - ti
        A = np.stack([np.ones_like(dt), dt, dt * dt], 1)
        coef, *_ = np.linalg.lstsq(A, track.position[sel], rcond=None)
        pos[i] = coef[0]
        rot[i] = allrot[sel].mean().as_rotvec()
    return pos, rot


def surface_samples(gel_surface, spacing_mm: float) -> np.ndarray:
    """Rest outer-surface sample points (mm) of a tools.twin.geometry.GelSurface."""
    return gel_surface.samples(spacing_mm)


def clearance(shape, position: np.ndarray, rotvec: np.ndarray, surface: np.ndarray) -> float:
    """Smallest signed distance (mm) from the indenter (tools.fe Shape at pose) to the rest surface
    samples: > 0 clear, < 0 penetrating."""
    R = Rotation.from_rotvec(np.asarray(rotvec, float)).as_matrix()
    d, _ = shape.sdf((np.asarray(surface, float) - np.asarray(position, float)) @ R)
    return float(np.min(d))


def initial_time(tracks: list[PoseTrack], shapes: list, surface: np.ndarray, t_first: float,
                 cfg: ResolveConfig = ResolveConfig()) -> float:
    """Latest pose sample time ≤ t_first at which every indenter clears the rest gel by ≥ clear_gap_mm
    (smoothed poses); ResolveError when none within search_back_s."""
    ref = tracks[0].t
    cand = ref[(ref <= t_first) & (ref >= t_first - cfg.search_back_s)][::-1]
    for ti in cand:
        ok = True
        for tr, sh in zip(tracks, shapes):
            p, r = fit_pose(tr, [ti], cfg.pose_half_window_s)
            if clearance(sh, p[0], r[0], surface) < cfg.clear_gap_mm:
                ok = False
                break
        if ok:
            return float(ti)
    raise ResolveError(f"no pose clear of the gel by {cfg.clear_gap_mm} mm within {cfg.search_back_s} s "
                       f"before t = {t_first:.3f} s")


def _step(p0, r0, p1, r1) -> tuple[float, float]:
    """Largest translation (mm) and rotation (rad) change over the indenters between two pose sets."""
    dp = float(np.max(np.linalg.norm(p1 - p0, axis=-1)))
    dr = float(np.max([(Rotation.from_rotvec(b) * Rotation.from_rotvec(a).inv()).magnitude()
                       for a, b in zip(r0, r1)]))
    return dp, dr


def densify(tracks: list[PoseTrack], t_key: np.ndarray, cfg: ResolveConfig = ResolveConfig()
            ) -> tuple[np.ndarray, np.ndarray]:
    """FE frame times: the keypoint times plus measured pose-sample times inserted between two
    keypoints wherever the pose has moved more than max_step since the last frame. Returns
    (times (J,), is_keypoint (J,))."""
    t_key = np.asarray(t_key, float)
    out, key = [float(t_key[0])], [True]
    ref = tracks[0].t

    def poses(ts):
        fits = [fit_pose(tr, ts, cfg.pose_half_window_s) for tr in tracks]
        return np.stack([f[0] for f in fits], 1), np.stack([f[1] for f in fits], 1)   # (T, K, 3)

    for a, b in zip(t_key[:-1], t_key[1:]):
        inner = ref[(ref > a) & (ref < b)]
        if len(inner):
            P, R = poses(np.concatenate([[a], inner]))
            last = 0
            for i in range(1, len(inner) + 1):
                dp, dr = _step(P[last], R[last], P[i], R[i])
                if dp > cfg.max_step_mm or dr > cfg.max_step_rad:
                    # the previous sample is still within the step (or the first one, if one sample jumps)
                    j = max(i - 1, last + 1)
                    out.append(float(np.concatenate([[a], inner])[j]))
                    key.append(False)
                    last = j
        out.append(float(b))
        key.append(True)
    t, k = np.array(out), np.array(key)
    keep = np.concatenate([[True], np.diff(t) > 1e-9])
    return t[keep], k[keep]


def period_scenario(tracks: list[PoseTrack], slots: list[int], names: list[str], t_key: np.ndarray,
                    catalog: dict, gel_geometry, gel_surface, cfg: ResolveConfig = ResolveConfig(),
                    material=None, solver=None) -> PeriodScenario:
    """The FE scenario of one contact period from measured pose tracks (one per indenter in contact).

    catalog: indenter name → {"shape", "params"} (the rig's indenter library); gel_geometry: tools.fe
    GelGeometry; gel_surface: tools.twin.geometry.GelSurface of the same gel (clearance test)."""
    from ..fe import Indenter, Keypoint, MeshSettings, Scenario
    from ..fe.indenters import make_shape

    if not (len(tracks) == len(slots) == len(names)) or not tracks:
        raise ResolveError(f"period_scenario: {len(tracks)} tracks, {len(slots)} slots, {len(names)} names")
    specs = []
    for n in names:
        if n not in catalog:
            raise ResolveError(f"session poses.indenters names {n!r}, not in the indenter catalog {sorted(catalog)}")
        specs.append(catalog[n])
    protos = [Indenter(name=f"{n}_{s}", shape=sp["shape"], params=dict(sp["params"])) for n, s, sp in zip(names, slots, specs)]
    shapes = [make_shape(p) for p in protos]
    surface = surface_samples(gel_surface, cfg.surface_spacing_mm)
    t_key = np.asarray(t_key, float)
    t0 = initial_time(tracks, shapes, surface, float(t_key[0]), cfg)
    times, is_key = densify(tracks, t_key, cfg)
    inds = []
    for proto, tr in zip(protos, tracks):
        p0, r0 = fit_pose(tr, [t0], cfg.pose_half_window_s)
        P, Rv = fit_pose(tr, times, cfg.pose_half_window_s)
        R0inv = Rotation.from_rotvec(r0[0]).inv()
        kps = [Keypoint([float(v) for v in (P[j] - p0[0])],
                        [float(v) for v in (Rotation.from_rotvec(Rv[j]) * R0inv).as_rotvec()])
               for j in range(len(times))]
        proto.position = [float(v) for v in p0[0]]
        proto.rotation = [float(v) for v in r0[0]]
        proto.keypoints = kps
        inds.append(proto)
    kw = {}
    if material is not None:
        kw["material"] = material
    if solver is not None:
        kw["solver"] = solver
    sc = Scenario(gel=gel_geometry, mesh=MeshSettings(size_top=cfg.mesh_top_mm, size_inside=cfg.mesh_inside_mm),
                  indenters=inds, name=cfg.scenario_name, **kw).validate()
    return PeriodScenario(sc, t0, times, is_key, list(slots), list(names))


def frame_sigma(t: np.ndarray, times: np.ndarray, tracks: list[PoseTrack], cfg: ResolveConfig = ResolveConfig(),
                force: tuple | None = None, pose_sd_mm: float = 0.05, force_sd_n: float = 0.05) -> np.ndarray:
    """Continuous FE frame parameter σ = j + s of session times t inside [times[0], times[-1]]:
    segment j between FE frames j and j+1, s ∈ [0, 1] the weighted least-squares position of the
    measurement on the segment, clipped:

    - the measured (smoothed) pose change against the segment's pose change (translation mm +
      rotation·`max_step_mm/max_step_rad`), weight 1/pose_sd_mm²;
    - with `force` = (measured (n, M), FE (J, M)) — the indenters' force vectors at t and at the FE
      frames, same units and frame — the measured force against the segment's force change, weight
      1/force_sd_n². The pose alone misplaces a frame when the motion between two FE frames is not a
      straight line in pose space (a press, then a twist) or when the segment is short against the
      mocap noise; the F/T reading fixes where on the segment the contact is;
    - a segment with neither motion nor force change (a hold) uses the time fraction.
    NaN outside the span."""
    t = np.atleast_1d(np.asarray(t, float))
    times = np.asarray(times, float)
    out = np.full(len(t), np.nan)
    inside = (t >= times[0]) & (t <= times[-1])
    if not inside.any():
        return out
    w = cfg.max_step_mm / cfg.max_step_rad

    def vec(ts):
        parts = []
        for tr in tracks:
            p, r = fit_pose(tr, ts, cfg.pose_half_window_s)
            parts += [p, w * r]
        return np.concatenate(parts, 1)

    V = vec(times)
    ti = t[inside]
    X = vec(ti)
    j = np.clip(np.searchsorted(times, ti, side="right") - 1, 0, len(times) - 2)
    d = V[j + 1] - V[j]
    n2 = np.sum(d * d, 1)
    tf = (ti - times[j]) / np.maximum(times[j + 1] - times[j], 1e-12)
    num = np.sum((X - V[j]) * d, 1) / pose_sd_mm ** 2
    den = n2 / pose_sd_mm ** 2
    moved = n2 > (0.02 * cfg.max_step_mm) ** 2
    if force is not None:
        fm, fe = (np.asarray(a, float) for a in force)
        if fm.shape != (len(t), fe.shape[1]) or fe.shape[0] != len(times):
            raise ValueError(f"frame_sigma: force shapes {fm.shape} / {fe.shape} do not match t ({len(t)},) "
                             f"and times ({len(times)},)")
        df = fe[j + 1] - fe[j]
        f2 = np.sum(df * df, 1)
        num = num + np.sum((fm[inside] - fe[j]) * df, 1) / force_sd_n ** 2
        den = den + f2 / force_sd_n ** 2
        moved |= f2 > force_sd_n ** 2
    s = np.where(moved, num / np.maximum(den, 1e-300), tf)
    out[inside] = j + np.clip(s, 0.0, 1.0)
    return out


def interp_frames(arr: np.ndarray, sigma: float) -> np.ndarray:
    """Linear interpolation of per-frame arrays (J, ...) at σ = j + s."""
    arr = np.asarray(arr)
    J = arr.shape[0]
    sigma = float(np.clip(sigma, 0.0, J - 1))
    j = min(int(np.floor(sigma)), max(J - 2, 0))
    s = sigma - j
    if J == 1:
        return arr[0]
    return (1.0 - s) * arr[j] + s * arr[j + 1]
