"""Twin signal chain (pure numpy): indenter pose tracks, true contact wrench with effects, the F/T
reading in the F/T frame, mocap noise, temperature, gel hysteresis.

F/T convention (docs/session.md): the F/T sensor sits on the indentation module; its frame is
fixed to the indenter: p_indenter = R_fi p_ft + t_fi. The indenter frame is the FE's (docs/fe.md):
origin at the tip, body along local +z. The sensor reads the load the gel puts on the indenter,
F = -RF (RF: force the indenter applies to the gel, FE convention), with the moment taken about
the F/T origin, both expressed in the F/T frame, plus noise.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .trajectory import Poke, minjerk, poke_pose

log = logging.getLogger(__name__)


@dataclass
class RigConfig:
    """The seed's rig (§III.A): mocap 120 Hz, ATI Mini45 at 200 Hz, camera; noise levels."""

    pose_rate: float = 120.0
    wrench_rate: float = 200.0
    camera_fps: float = 30.0
    temperature_rate: float = 2.0
    pose_noise_mm: float = 0.05           # seed appendix: mocap errors 0.03-0.08 mm
    pose_noise_rad: float = 0.002
    ft_noise_n: float = 0.02              # ATI Mini45 resolution 0.0625 N
    ft_noise_nmm: float = 0.4
    ft_offset_mm: tuple = (0.0, 0.0, 44.0)  # F/T origin in the indenter frame (indenter top at 44 mm)
    ft_yaw_rad: float = 0.5236            # F/T axes turned about the indenter axis
    temperature_c: float = 24.0
    temperature_drift_c_per_s: float = 0.01
    temperature_noise_c: float = 0.02
    hysteresis_fraction: float = 0.15     # share of the surface displacement that recovers slowly
    hysteresis_tau_s: float = 1.5         # recovery time constant
    park: tuple = ((-20.0, 0.0, 30.0), (20.0, 0.0, 30.0))
    hover_mm: float = 6.0

    def ft_to_indenter(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_fi (3,3), t_fi (3,)) with p_indenter = R_fi p_ft + t_fi."""
        return Rotation.from_rotvec([0.0, 0.0, self.ft_yaw_rad]).as_matrix(), np.asarray(self.ft_offset_mm, float)

    def ft_to_indenter_dict(self) -> dict:
        R, t = self.ft_to_indenter()
        q = Rotation.from_matrix(R).as_quat()  # x, y, z, w
        return {"rotation_wxyz": [float(q[3]), float(q[0]), float(q[1]), float(q[2])],
                "translation_mm": [float(v) for v in t],
                "meaning": "p_indenter = R p_ft + t; indenter frame: origin at the tip, body along +z"}


def slot_track(pokes: list[Poke], slot: int, t: np.ndarray, rig: RigConfig) -> tuple[np.ndarray, np.ndarray]:
    """Tip position (T,3) and rotation vector (T,3) of indentation module `slot` at times t."""
    park = np.asarray(rig.park[slot % len(rig.park)], float)
    anchors = []  # (t0, t1, poke, k)
    for p in pokes:
        if slot in p.slots:
            anchors.append((p.t_approach, p.t_retreat_end, p, p.slots.index(slot)))
    pos = np.tile(park, (len(t), 1))
    rot = np.zeros((len(t), 3))
    prev_t, prev_p, prev_r = -np.inf, park, np.zeros(3)
    for t0, t1, p, k in anchors:
        sp, sr = poke_pose(p, k, np.array([t0]), rig.hover_mm)
        _transfer(t, pos, rot, prev_t, t0, prev_p, sp[0], prev_r, sr[0])
        inside = (t >= t0) & (t <= t1)
        if inside.any():
            pos[inside], rot[inside] = poke_pose(p, k, t[inside], rig.hover_mm)
        ep, er = poke_pose(p, k, np.array([t1]), rig.hover_mm)
        prev_t, prev_p, prev_r = t1, ep[0], er[0]
    _transfer(t, pos, rot, prev_t, np.inf, prev_p, park, prev_r, np.zeros(3))
    return pos, rot


def _transfer(t, pos, rot, t0, t1, p0, p1, r0, r1, move_s: float = 0.5) -> None:
    """Between two anchors: hold p0, move (min-jerk, move_s long, ending at t1) to p1."""
    sel = (t > t0) & (t < t1)
    if not sel.any():
        return
    if not np.isfinite(t0):
        pos[sel], rot[sel] = p1, r1
        return
    dur = min(move_s, t1 - t0) if np.isfinite(t1) else move_s
    start = t1 - dur if np.isfinite(t1) else t0
    s = minjerk((t[sel] - start) / max(dur, 1e-9))[:, None]
    pos[sel] = p0 + s * (p1 - p0)
    delta = (Rotation.from_rotvec(r1) * Rotation.from_rotvec(r0).inv()).as_rotvec()
    rot[sel] = (Rotation.from_rotvec(s * delta) * Rotation.from_rotvec(r0)).as_rotvec()


def quat_wxyz(rotvec: np.ndarray) -> np.ndarray:
    q = Rotation.from_rotvec(rotvec).as_quat()
    q = q[:, [3, 0, 1, 2]]
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def mocap_noise(pos, rotvec, rig: RigConfig, rng: np.random.Generator, ar1: float = 0.0):
    """Noisy pose measurement: Gaussian position and small-rotation noise, white or (ar1 > 0) AR(1)
    coloured with the same stationary σ (tools.twin.world.ar1_filter)."""
    dp = rng.normal(0.0, rig.pose_noise_mm, pos.shape)
    dr = rng.normal(0.0, rig.pose_noise_rad, rotvec.shape)
    if ar1:
        from .world import ar1_filter

        dp, dr = ar1_filter(dp, ar1), ar1_filter(dr, ar1)
    return pos + dp, (Rotation.from_rotvec(dr) * Rotation.from_rotvec(rotvec)).as_rotvec()


def ft_reading(rf: np.ndarray, rm: np.ndarray, tip: np.ndarray, rotvec: np.ndarray, rig: RigConfig) -> np.ndarray:
    """Noise-free F/T reading (T,6) = [F N, T N*mm] in the F/T frame from the FE-convention
    reaction RF (T,3) and moment RM (T,3) about the tip (sensor frame) and the indenter pose."""
    R_fi, t_fi = rig.ft_to_indenter()
    R_ind = Rotation.from_rotvec(rotvec).as_matrix()           # indenter -> sensor
    R_ft = R_ind @ R_fi                                          # F/T -> sensor
    o_ft = tip + np.einsum("tij,j->ti", R_ind, t_fi)
    F = -rf
    M = -rm + np.cross(tip - o_ft, F)                            # moment about the F/T origin
    return np.concatenate([np.einsum("tji,tj->ti", R_ft, F), np.einsum("tji,tj->ti", R_ft, M)], axis=1)


def temperature(t: np.ndarray, rig: RigConfig, rng: np.random.Generator) -> np.ndarray:
    """True gel temperature: slow drift plus a smooth wander."""
    wander = np.convolve(rng.normal(0, rig.temperature_noise_c, len(t) + 8), np.ones(9) / 3, "valid")[:len(t)]
    return rig.temperature_c + rig.temperature_drift_c_per_s * t + wander


class Hysteresis:
    """Slow recovery of the gel skin: u_vis = (1-h) u + h m,  dm/dt = (u - m)/tau."""

    def __init__(self, fraction: float, tau: float, shape):
        self.h, self.tau = float(fraction), float(tau)
        self.m = np.zeros(shape)
        self.t = None

    def step(self, t: float, u: np.ndarray) -> np.ndarray:
        if self.t is not None and self.tau > 0:
            a = 1.0 - np.exp(-(t - self.t) / self.tau)
            self.m += a * (u - self.m)
        elif self.tau <= 0:
            self.m = u.copy()
        self.t = t
        return (1.0 - self.h) * u + self.h * self.m
