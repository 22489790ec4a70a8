"""Node-to-rigid-surface penalty contact with Coulomb friction (pure numpy core).

For a surface node at x and an indenter with pose (R, p) and signed distance d(xi), xi = R^T (x-p):
  normal force    fN = -eps d n              (d < 0 only; eps = penalty * nodal area, N/mm)
  tangential      trial  fT = -eps_t (I - n n)(x - a), eps_t = tangential_ratio * eps,  a = R a_loc + p the stick anchor
                  stick  |fT| <= mu |fN|,  else slip fT = -mu |fN| s/|s|   (return mapping from the
                  last converged state, elastic slip <= mu |d| / tangential_ratio)
The node force tangents dF/dx (3x3 per node) are exact (normal part incl. curvature n (x) n + d H;
friction incl. the turning of the normal, dn/dx = H); the tests check them by finite differences. Anchors live in the indenter's local frame
so a rotating/translating indenter drags sticking nodes along.

For increments whose Newton iterations cycle (tools.fe.solver), two options that leave the
converged law almost or exactly as is:
- `hold` (K,M bool, nodes that slipped in an earlier iteration of this increment): a held node keeps
  slipping while its trial force is within HOLD_BAND of the Coulomb limit, so its force differs from
  the plain law by < HOLD_BAND*mu|fN|; this breaks stick/slip flips at the kink.
- `slip_tangent="secant"`: the slip tangent leaves out its unsymmetric normal-coupling term
  mu*eps*s(x)n; a quasi-Newton direction (forces unchanged), steadier when the exact one cycles.
`normal_curvature=False` leaves the curvature term -eps d H out of the normal part's tangent (forces
unchanged, a quasi-Newton matrix). On a convex indenter that term is a negative tangential stiffness
eps |d| / R per node; at the penetration of an increment's first iterate (0.2-0.4 mm under a 4 mm
sphere) it outweighs the soft gel's own, and the Newton step throws the contact patch sideways.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HOLD_BAND = 0.05   # fraction of the Coulomb limit below which a held node may stick again
SLIP_TANGENTS = ("exact", "secant")


@dataclass
class ContactState:
    """Converged history: stick anchors in the local frame of each indenter (K, M, 3), NaN = free,
    the converged node positions x_prev (M,3) and the converged indenter poses [(p, R), ...].
    A node touching for the first time sticks where the indenter met it: the surface point crossed
    by its converged position on the way from the converged pose to the current one (fixed during
    the iterations: consistent tangent). Without poses (or when that position is still outside at
    the current pose) it sticks to the closest surface point of its converged position; that
    anchor lies too far out along the surface by an amount that grows with the increment, so with
    it friction lowers the normal force of a press at coarse increments (docs/fe.md)."""

    anchors: np.ndarray
    x_prev: np.ndarray
    poses: list | None = None

    @classmethod
    def empty(cls, n_indenters: int, x: np.ndarray, poses: list | None = None) -> ContactState:
        return cls(np.full((n_indenters, len(x), 3), np.nan), np.array(x, float), poses)


CROSSING_BISECTIONS = 30


def first_touch(shape, xi_old: np.ndarray, xi_new: np.ndarray) -> np.ndarray:
    """Local surface point where the segment xi_old (outside, sdf >= 0) -> xi_new (inside) crosses
    the indenter surface (bisection on the signed distance), projected onto the surface."""
    lo, hi = np.zeros(len(xi_old)), np.ones(len(xi_old))
    for _ in range(CROSSING_BISECTIONS):
        mid = 0.5 * (lo + hi)
        d, _ = shape.sdf(xi_old + mid[:, None] * (xi_new - xi_old))
        out = d >= 0
        lo, hi = np.where(out, mid, lo), np.where(out, hi, mid)
    xc = xi_old + lo[:, None] * (xi_new - xi_old)
    d, g = shape.sdf(xc)
    return xc - d[:, None] * g


@dataclass
class ContactEval:
    fn: np.ndarray       # (M,3) normal force on each node (N)
    ft: np.ndarray       # (M,3) friction force on each node (N)
    K: np.ndarray        # (M,3,3) d(fn+ft)/dx
    owner: np.ndarray    # (M,) indenter index, -1 free
    gap: np.ndarray      # (K,M) signed distance (mm)
    slip: np.ndarray     # (K,M) bool
    new_anchors: np.ndarray  # (K,M,3) anchors to commit if this state converges
    force_k: np.ndarray  # (K,M,3) total force from indenter k on each node


def evaluate(x, area, shapes, poses, state: ContactState, penalty: float, mu: float,
             tangent: bool = True, tangential_ratio: float = 1.0, hold: np.ndarray | None = None,
             slip_tangent: str = "exact", normal_curvature: bool = True) -> ContactEval:
    """Contact forces on surface nodes at current positions x (M,3); poses = [(p, R), ...];
    hold, slip_tangent, normal_curvature: see the module docstring."""
    if slip_tangent not in SLIP_TANGENTS:
        raise ValueError(f"slip_tangent {slip_tangent!r}: expected one of {SLIP_TANGENTS}")
    M, K = len(x), len(shapes)
    fn, ft = np.zeros((M, 3)), np.zeros((M, 3))
    Kt = np.zeros((M, 3, 3))
    owner = np.full(M, -1)
    gap = np.full((K, M), np.inf)
    slip = np.zeros((K, M), bool)
    new_anchors = np.full((K, M, 3), np.nan)
    force_k = np.zeros((K, M, 3))
    eye = np.eye(3)
    for k, (shape, (p, R)) in enumerate(zip(shapes, poses)):
        xi = (x - p) @ R
        bound = getattr(shape, "radius_bound", np.inf)
        cand = np.flatnonzero(np.linalg.norm(xi, axis=1) < bound) if np.isfinite(bound) else np.arange(M)
        if cand.size == 0:
            continue
        d, g = shape.sdf(xi[cand])
        gap[k, cand] = d
        act = d < 0
        if not np.any(act):
            continue
        idx = cand[act]
        d, n = d[act], g[act] @ R.T
        eps = penalty * area[idx]
        fN = (-eps * d)[:, None] * n
        nn = np.einsum("ai,aj->aij", n, n)
        Kn = np.zeros((len(idx), 3, 3))
        H = np.zeros((len(idx), 3, 3))
        if tangent:
            H = R @ shape.hessian(xi[idx]) @ R.T
            Kn = -eps[:, None, None] * ((nn + d[:, None, None] * H) if normal_curvature else nn)
        # friction
        a_loc = state.anchors[k, idx]
        fresh = np.isnan(a_loc[:, 0])
        surf_pt = x[idx] - d[:, None] * n
        a_w = a_loc @ R.T + p
        if np.any(fresh):
            xp = state.x_prev[idx[fresh]]
            xi_new = (xp - p) @ R
            dp, gp = shape.sdf(xi_new)
            a_w[fresh] = xp - dp[:, None] * (gp @ R.T)
            if state.poses is not None:
                p_old, R_old = state.poses[k]
                xi_old = (xp - p_old) @ R_old
                d_old, _ = shape.sdf(xi_old)
                cross = (dp < 0) & (d_old >= 0)
                if np.any(cross):
                    fi = np.flatnonzero(fresh)[cross]
                    a_w[fi] = first_touch(shape, xi_old[cross], xi_new[cross]) @ R.T + p
        P = eye - nn
        s = np.einsum("aij,aj->ai", P, x[idx] - a_w)
        epst = tangential_ratio * eps
        fT = -epst[:, None] * s
        lim = mu * eps * (-d)
        mag = np.linalg.norm(fT, axis=1)
        slipping = mag > lim
        if hold is not None:
            slipping |= hold[k, idx] & (mag > (1.0 - HOLD_BAND) * lim)
        shat = s / np.maximum(np.linalg.norm(s, axis=1), 1e-300)[:, None]
        fT[slipping] = -lim[slipping, None] * shat[slipping]
        # ds/dx = P - (n.r) H - n (x) (H r), r = x - a (includes the turning of the normal)
        r = x[idx] - a_w
        Hr = np.einsum("aij,aj->ai", H, r)
        dsdx = P - np.einsum("a,aij->aij", np.einsum("ai,ai->a", n, r), H) - np.einsum("ai,aj->aij", n, Hr)
        Kf = -epst[:, None, None] * dsdx
        if tangent and np.any(slipping):
            sl = slipping
            snorm = np.maximum(np.linalg.norm(s[sl], axis=1), 1e-300)
            ss = np.einsum("ai,aj->aij", shat[sl], shat[sl])
            Kf[sl] = -(lim[sl] / snorm)[:, None, None] * np.einsum("aij,ajk->aik", eye - ss, dsdx[sl])
            if slip_tangent == "exact":
                Kf[sl] += mu * eps[sl, None, None] * np.einsum("ai,aj->aij", shat[sl], n[sl])
        # anchors to commit: stick keeps the anchor (or the first touch point); slip drags it
        a_new = a_w.copy()
        if np.any(slipping):
            elastic = (lim[slipping] / epst[slipping])[:, None] * shat[slipping]
            a_new[slipping] = surf_pt[slipping] - elastic
        new_anchors[k, idx] = (a_new - p) @ R
        slip[k, idx] = slipping
        fn[idx] += fN
        ft[idx] += fT
        force_k[k, idx] = fN + fT
        Kt[idx] += Kn + (Kf if mu > 0 else 0.0)
        owner[idx] = np.where(owner[idx] < 0, k, owner[idx])
    return ContactEval(fn, ft, Kt, owner, gap, slip, new_anchors, force_k)
