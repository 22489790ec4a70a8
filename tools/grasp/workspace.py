"""Thumb–index contact workspace of one hand variant (seed §III.N).

For joint configurations sampled uniformly within the joint limits: forward kinematics and the
fingertip Jacobians (Pinocchio), the thumb's manipulability, and — for configurations passing the
filters (fingertip distance ≤ 60 mm, alignment z_thumb·z_index ≤ 0) — coal's distance between the
fingertip spheres shrunk by 15 % (the gel gives). A contact is a distance ≤ 1 mm; its point is the
midpoint of coal's two nearest points and its normal points from the index to the thumb:

    p_c = (p_thumb + p_index) / 2,   n = (p_thumb − p_index) / ‖p_thumb − p_index‖.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .hand_model import HandSpec, limits, q_indices
from .manipulability import manipulability


@dataclass(frozen=True)
class WorkspaceConfig:
    """The seed's numbers (§III.N) as named defaults."""

    samples: int = 10_000
    shrink: float = 0.15                 # fingertip sphere radius × (1 − shrink)
    contact_distance_m: float = 0.001    # coal distance ≤ this is a contact
    max_penetration_m: float = 0.003     # deeper overlap of the shrunk spheres is not a pinch (ours)
    max_tip_distance_m: float = 0.06     # fingertip centres farther apart are not a pinch
    max_alignment: float = 0.0           # z_thumb · z_index ≤ this
    min_manipulability: float = 1e-23    # the seed's threshold (meaningful only for 6×n, see manipulability.py)
    seed: int = 0


@dataclass
class Workspace:
    """Samples of one variant. q: (S, n_thumb + n_index) joint angles (thumb first)."""

    q: np.ndarray
    w_thumb: np.ndarray          # (S,) thumb manipulability (positional Jacobian)
    w_index: np.ndarray          # (S,)
    tip_distance: np.ndarray     # (S,) m, fingertip centres
    alignment: np.ndarray        # (S,) z_thumb · z_index
    candidate: np.ndarray        # (S,) bool, passed the distance, alignment and w filters
    contact: np.ndarray          # (S,) bool, candidate with coal distance within the contact band
    distance: np.ndarray         # (S,) m, coal distance (nan where not queried)
    point: np.ndarray            # (S,3) contact point p_c (nan where no contact)
    normal: np.ndarray           # (S,3) contact normal n (index → thumb)
    p_thumb: np.ndarray          # (S,3) coal nearest point on the thumb sphere
    p_index: np.ndarray          # (S,3)
    tip_thumb: np.ndarray        # (S,4,4) fingertip frame poses
    tip_index: np.ndarray        # (S,4,4)

    @property
    def contact_points(self) -> np.ndarray:
        return self.point[self.contact]


def sample_q(model, spec: HandSpec, n: int, rng: np.random.Generator) -> np.ndarray:
    lo_t, hi_t = limits(model, spec.thumb)
    lo_i, hi_i = limits(model, spec.index)
    lo, hi = np.concatenate([lo_t, lo_i]), np.concatenate([hi_t, hi_i])
    return lo + rng.random((n, len(lo))) * (hi - lo)


def full_q(model, spec: HandSpec, q_pair: np.ndarray) -> np.ndarray:
    """Pair configurations (S, n_t+n_i) → full model configurations (S, nq), other joints at 0."""
    q = np.zeros((len(q_pair), model.nq))
    it, ii = q_indices(model, spec.thumb), q_indices(model, spec.index)
    q[:, it] = q_pair[:, :len(it)]
    q[:, ii] = q_pair[:, len(it):]
    return q


def fingertip_kinematics(model, spec: HandSpec, q_pair: np.ndarray, data=None):
    """Fingertip poses (S,4,4) ×2 and positional world Jacobians (S,3,n) ×2 (thumb, index)."""
    import pinocchio as pin

    data = data or model.createData()
    ft, fi = model.getFrameId(spec.thumb.tip_frame), model.getFrameId(spec.index.tip_frame)
    vt = [model.joints[model.getJointId(j)].idx_v for j in spec.thumb.joints]
    vi = [model.joints[model.getJointId(j)].idx_v for j in spec.index.joints]
    Q = full_q(model, spec, q_pair)
    S = len(Q)
    Tt, Ti = np.empty((S, 4, 4)), np.empty((S, 4, 4))
    Jt, Ji = np.empty((S, 3, len(vt))), np.empty((S, 3, len(vi)))
    rf = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    for s in range(S):
        pin.computeJointJacobians(model, data, Q[s])   # also runs forward kinematics
        pin.updateFramePlacements(model, data)
        Tt[s] = data.oMf[ft].homogeneous
        Ti[s] = data.oMf[fi].homogeneous
        Jt[s] = pin.getFrameJacobian(model, data, ft, rf)[:3, vt]
        Ji[s] = pin.getFrameJacobian(model, data, fi, rf)[:3, vi]
    return Tt, Ti, Jt, Ji


def sphere_distance(c1: np.ndarray, r1: float, c2: np.ndarray, r2: float):
    """coal distance between two spheres: (signed distance, nearest point on 1, on 2)."""
    import coal

    s1, s2 = coal.Sphere(r1), coal.Sphere(r2)
    req, res = coal.DistanceRequest(), coal.DistanceResult()
    req.enable_signed_distance = True
    d = coal.distance(s1, coal.Transform3s(np.eye(3), np.asarray(c1, float)),
                      s2, coal.Transform3s(np.eye(3), np.asarray(c2, float)), req, res)
    return float(d), np.array(res.getNearestPoint1()), np.array(res.getNearestPoint2())


def evaluate(model, spec: HandSpec, q_pair: np.ndarray, cfg: WorkspaceConfig | None = None) -> Workspace:
    """The contact workspace of configurations q_pair on `model` (as currently edited)."""
    cfg = cfg or WorkspaceConfig()
    Tt, Ti, Jt, Ji = fingertip_kinematics(model, spec, q_pair)
    S = len(q_pair)
    w_t, w_i = manipulability(Jt), manipulability(Ji)
    pt, pi = Tt[:, :3, 3], Ti[:, :3, 3]
    tip_d = np.linalg.norm(pt - pi, axis=1)
    align = np.einsum("sk,sk->s", Tt[:, :3, 2], Ti[:, :3, 2])
    cand = (tip_d <= cfg.max_tip_distance_m) & (align <= cfg.max_alignment) & (w_t > cfg.min_manipulability)
    rt = spec.thumb.tip_radius_m * (1 - cfg.shrink)
    ri = spec.index.tip_radius_m * (1 - cfg.shrink)
    dist = np.full(S, np.nan)
    nt, ni = np.full((S, 3), np.nan), np.full((S, 3), np.nan)
    for s in np.flatnonzero(cand):
        dist[s], nt[s], ni[s] = sphere_distance(pt[s], rt, pi[s], ri)
    contact = cand & (dist <= cfg.contact_distance_m) & (dist >= -cfg.max_penetration_m)
    point = np.where(contact[:, None], 0.5 * (nt + ni), np.nan)
    # p_thumb − p_index of the nearest points flips sign when the spheres overlap; the centre
    # difference has the same direction as the separated witness difference and never flips.
    diff = pt - pi
    normal = np.where(contact[:, None], diff / np.maximum(np.linalg.norm(diff, axis=1, keepdims=True), 1e-12),
                      np.nan)
    return Workspace(q_pair, w_t, w_i, tip_d, align, cand, contact, dist, point, normal, nt, ni, Tt, Ti)


def sample(model, spec: HandSpec, cfg: WorkspaceConfig | None = None, rng=None) -> Workspace:
    cfg = cfg or WorkspaceConfig()
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(cfg.seed)
    return evaluate(model, spec, sample_q(model, spec, cfg.samples, rng), cfg)
