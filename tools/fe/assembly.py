"""Yeoh gel on linear tets: internal forces and tangent assembled straight onto a fixed sparse pattern.

For P1 tets (one quadrature point, constant shape-function gradients B_a = dN_a/dX per cell) the
element tangent of W(I1b, J) never needs the 4th-order tensor A = d2W/dFdF. With
p_a = F B_a, q_a = F^-T B_a and d_a = dI1b/dF B_a = 2 J^(-2/3) (p_a - tr(C)/3 q_a), the closed-form
Yeoh tangent of tools.fe.materials.YeohUmat contracts to, per cell (volume V):

  K[a i, b k] / V = 2 a f1 (B_a . B_b) delta_ik - 4/3 a f1 (p_ai q_bk + q_ai p_bk)
                    + (4/9 a trC f1 + kappa J (2J - 1)) q_ai q_bk
                    + (2/3 a trC f1 - kappa (J - 1) J) q_bi q_ak + f2 d_ai d_bk

(a = J^(-2/3), f1 = dW/dI1b, f2 = d2W/dI1b^2, kappa the bulk modulus) and the force to
f_ai / V = f1 d_ai + kappa (J - 1) J q_ai: products of 4x3 vectors, never a (3,3,3,3) tensor. One
numba pass over the cells computes the kinematics, the forces and the 12x12 block and adds them
straight into the force vector and into the CSR data of the free-DOF pattern (gel elements + a 3x3
block per surface node for the contact) at precomputed positions, in a fixed order (bit-identical
results run to run). The cells are always assembled as PARTS contiguous parts, each into its own
force vector and CSR data, summed in part order; with two threads (tools.fe.linsolve.thread_count)
the parts run at once (the kernels release the GIL), so the bits are the same with one thread or two. The pattern, and so the factorisation's symbolic analysis (tools.fe.linsolve),
stays the same for a whole solve.
tests/test_fe_assembly.py checks both against felupe's.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numba as nb
import numpy as np
import scipy.sparse as sp

PARTS = 2   # cell parts per assembly (fixed: the summation order, hence the bits, depend on it)
_POOL: ThreadPoolExecutor | None = None


def _run_parts(fn, threads: int) -> list:
    """fn(part) for each part, in threads when threads > 1; results in part order."""
    global _POOL
    if threads <= 1:
        return [fn(k) for k in range(PARTS)]
    if _POOL is None:
        _POOL = ThreadPoolExecutor(PARTS, thread_name_prefix="fe-assembly")
    return list(_POOL.map(fn, range(PARTS)))


class P1Assembly:
    """Fixed free-DOF CSR pattern and the scatter maps of one mesh.

    nodes (N,3), tets (C,4), free (F,) sorted free DOF indices (3 * node + axis), surf_dofs (M*3,)
    the DOFs of the contact nodes; B (C,4,3) shape-function gradients and V (C,) cell volumes
    (felupe's RegionTetra values, so forces match felupe's to rounding)."""

    def __init__(self, tets: np.ndarray, n_nodes: int, free: np.ndarray, surf_dofs: np.ndarray,
                 B: np.ndarray, V: np.ndarray):
        self.tets = np.asarray(tets, np.int64)
        self.B = np.ascontiguousarray(B, float)
        self.V = np.asarray(V, float)
        self.ndof = 3 * n_nodes
        C = len(self.tets)
        self.gram = np.einsum("caJ,cbJ->cab", self.B, self.B)          # (C,4,4) B_a . B_b
        fmap = np.full(self.ndof, -1, np.int64)
        fmap[free] = np.arange(len(free))
        nf = len(free)
        self.nfree = nf
        edofs = (3 * self.tets[:, :, None] + np.arange(3)).reshape(C, 12)  # (C,12) global DOF
        self.edofs = edofs.ravel()
        er = fmap[edofs][:, :, None].repeat(12, axis=2)                   # (C,12,12) row (free)
        ec = fmap[edofs][:, None, :].repeat(12, axis=1)
        sd = np.asarray(surf_dofs, np.int64).reshape(-1, 3)
        cr = fmap[np.repeat(sd, 3, axis=1)].ravel()                        # (M*9,) row-major 3x3 blocks
        cc = fmap[np.tile(sd, (1, 3))].ravel()
        rows = np.concatenate([er.ravel(), cr])
        cols = np.concatenate([ec.ravel(), cc])
        keep = (rows >= 0) & (cols >= 0)
        keys = rows * nf + cols
        k = np.sort(keys[keep])
        ukeys = k[np.concatenate([[True], k[1:] != k[:-1]])]
        pos = np.full(len(keys), len(ukeys), np.int64)                     # dump slot for fixed DOFs
        pos[keep] = np.searchsorted(ukeys, keys[keep])
        self.pos = pos.astype(np.int32) if len(ukeys) < 2**31 - 1 else pos
        self.nnz = len(ukeys)
        self.indices = (ukeys % nf).astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(ukeys // nf, minlength=nf))]).astype(np.int32)
        self.bounds = np.linspace(0, C, PARTS + 1).round().astype(np.int64)   # cell ranges of the parts

    @staticmethod
    def _threads() -> int:
        from .linsolve import thread_count

        return thread_count()

    def forces(self, U: np.ndarray, umat) -> np.ndarray:
        """Internal force vector (ndof,) of the gel at displacement U (N,3)."""
        U = np.ascontiguousarray(U, float)
        b = self.bounds
        parts = _run_parts(lambda k: _forces(U, self.tets, self.B, self.V, umat.C10, umat.C20, umat.C30, umat.bulk,
                                             self.edofs, self.ndof, b[k], b[k + 1]), self._threads())
        f = parts[0]
        for g in parts[1:]:
            f += g
        return f

    def forces_and_tangent(self, U: np.ndarray, umat, contact_K: np.ndarray | None = None):
        """(internal force vector (ndof,), CSR data (nnz,) of the free-DOF tangent incl. contact_K).

        contact_K (M,3,3): d(contact force)/dx per surface node; enters with a minus sign (the
        residual is internal minus contact force)."""
        cw = np.zeros(0) if contact_K is None else np.ascontiguousarray(contact_K, float).ravel()
        U = np.ascontiguousarray(U, float)
        b, none = self.bounds, np.zeros(0)
        parts = _run_parts(lambda k: _forces_and_tangent(U, self.tets, self.B, self.V, self.gram, umat.C10, umat.C20,
                                                         umat.C30, umat.bulk, self.edofs, self.ndof, self.pos,
                                                         self.nnz, cw if k == 0 else none, b[k], b[k + 1]),
                           self._threads())
        f, data = parts[0]
        for g, d in parts[1:]:
            f += g
            data += d
        return f, data

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """The free-DOF tangent as a CSR matrix sharing this pattern's index arrays."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.nfree, self.nfree), copy=False)


# -- per-cell kernels (numba, compiled once and cached next to this file) ------------------------------
# Cells are visited in order and their entries added in the order of `edofs` / `pos`, so a result is the
# same bits on every run (the FE cache keys depend on them). No fastmath: IEEE semantics as in numpy.

@nb.njit(cache=True, nogil=True)
def _cell(U, tets, B, c, C10, C20, C30, w):
    """Kinematics of cell c: fills w[0] = p_a = F B_a, w[1] = q_a = F^-T B_a, w[2] = d_a = dI1b/dF B_a
    (each (4,3)); returns (J, tr C, J^(-2/3), f1, f2)."""
    F = np.empty((3, 3))
    for i in range(3):
        for J in range(3):
            s = 1.0 if i == J else 0.0
            for a in range(4):
                s += U[tets[c, a], i] * B[c, a, J]
            F[i, J] = s
    c00 = F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]
    c01 = F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]
    c02 = F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]
    det = F[0, 0] * c00 + F[0, 1] * c01 + F[0, 2] * c02
    iF = np.empty((3, 3))   # F^-1 by cofactors
    iF[0, 0] = c00
    iF[0, 1] = F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]
    iF[0, 2] = F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]
    iF[1, 0] = c01
    iF[1, 1] = F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]
    iF[1, 2] = F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]
    iF[2, 0] = c02
    iF[2, 1] = F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]
    iF[2, 2] = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    trC = 0.0
    for i in range(3):
        for J in range(3):
            iF[i, J] /= det
            trC += F[i, J] * F[i, J]
    a = det ** (-2.0 / 3.0)
    x = a * trC - 3.0
    f1 = C10 + 2.0 * C20 * x + 3.0 * C30 * x * x      # YeohUmat._f
    f2 = 2.0 * C20 + 6.0 * C30 * x
    for k in range(4):
        for i in range(3):
            p = 0.0
            q = 0.0
            for J in range(3):
                p += B[c, k, J] * F[i, J]
                q += B[c, k, J] * iF[J, i]
            w[0, k, i] = p
            w[1, k, i] = q
            w[2, k, i] = 2.0 * a * (p - trC / 3.0 * q)
    return det, trC, a, f1, f2


@nb.njit(cache=True, nogil=True)
def _forces(U, tets, B, V, C10, C20, C30, bulk, edofs, ndof, c0, c1):
    f = np.zeros(ndof)
    w = np.empty((3, 4, 3))
    for c in range(c0, c1):
        det, trC, a, f1, f2 = _cell(U, tets, B, c, C10, C20, C30, w)
        vol = bulk * (det - 1.0) * det
        for k in range(4):
            for i in range(3):
                f[edofs[c * 12 + 3 * k + i]] += V[c] * (f1 * w[2, k, i] + vol * w[1, k, i])
    return f


@nb.njit(cache=True, nogil=True)
def _forces_and_tangent(U, tets, B, V, gram, C10, C20, C30, bulk, edofs, ndof, pos, nnz, contact_w, c0, c1):
    """Cells c0..c1-1 (and the contact blocks contact_w, empty for all parts but one)."""
    f = np.zeros(ndof)
    data = np.zeros(nnz + 1)          # the last slot takes the entries of fixed DOFs
    w = np.empty((3, 4, 3))
    C = tets.shape[0]
    for c in range(c0, c1):
        det, trC, a, f1, f2 = _cell(U, tets, B, c, C10, C20, C30, w)
        Vc = V[c]
        vol = bulk * (det - 1.0) * det
        for k in range(4):
            for i in range(3):
                f[edofs[c * 12 + 3 * k + i]] += Vc * (f1 * w[2, k, i] + vol * w[1, k, i])
        beta = Vc * (-4.0 / 3.0) * a * f1
        gam = Vc * (4.0 / 9.0 * a * trC * f1 + bulk * det * (2.0 * det - 1.0))
        vf2 = Vc * f2
        de = Vc * (2.0 / 3.0 * a * trC * f1 - bulk * (det - 1.0) * det)
        g0 = Vc * 2.0 * a * f1
        base = c * 144
        # the gel block is symmetric: each entry is computed once and added at (a i, b k) and (b k, a i)
        for r in range(12):
            ka, i = r // 3, r % 3
            pa, qa, da = w[0, ka, i], w[1, ka, i], w[2, ka, i]
            for col in range(r, 12):
                kb, k = col // 3, col % 3
                v = (beta * (pa * w[1, kb, k] + qa * w[0, kb, k]) + gam * qa * w[1, kb, k]
                     + vf2 * da * w[2, kb, k] + de * w[1, kb, i] * w[1, ka, k])
                if i == k:
                    v += g0 * gram[c, ka, kb]
                data[pos[base + r * 12 + col]] += v
                if col != r:
                    data[pos[base + col * 12 + r]] += v
    for j in range(contact_w.shape[0]):
        data[pos[C * 144 + j]] -= contact_w[j]
    return f, data[:nnz]


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the kernels on a one-cell mesh, so a timed solve does not
    pay for it."""
    nodes = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    B = np.array([[[-1.0, -1, -1], [1, 0, 0], [0, 1, 0], [0, 0, 1]]])
    asm = P1Assembly(np.arange(4)[None], 4, np.arange(3, 12), np.arange(3, 6), B, np.array([1 / 6]))
    from .materials import YeohUmat

    umat = YeohUmat(0.03, 0.002, 0.0002, 0.1)
    asm.forces(np.zeros_like(nodes), umat)
    asm.forces_and_tangent(np.zeros_like(nodes), umat, np.zeros((1, 3, 3)))
