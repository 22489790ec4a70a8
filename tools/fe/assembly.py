"""Yeoh gel on linear tets: internal forces and tangent assembled straight onto a fixed sparse pattern.

For P1 tets (one quadrature point, constant shape-function gradients B_a = dN_a/dX per cell) the
element tangent of W(I1b, J) never needs the 4th-order tensor A = d2W/dFdF. With
p_a = F B_a, q_a = F^-T B_a and d_a = dI1b/dF B_a = 2 J^(-2/3) (p_a - tr(C)/3 q_a), the closed-form
Yeoh tangent of tools.fe.materials.YeohUmat contracts to, per cell (volume V):

  K[a i, b k] / V = 2 a f1 (B_a . B_b) delta_ik - 4/3 a f1 (p_ai q_bk + q_ai p_bk)
                    + (4/9 a trC f1 + kappa J (2J - 1)) q_ai q_bk
                    + (2/3 a trC f1 - kappa (J - 1) J) q_bi q_ak + f2 d_ai d_bk

(a = J^(-2/3), f1 = dW/dI1b, f2 = d2W/dI1b^2, kappa the bulk modulus) and the force to
f_ai / V = f1 d_ai + kappa (J - 1) J q_ai: a few outer products of (cell, 12) vectors instead of
einsums over (3,3,3,3,cell) arrays. The entries are summed into the CSR data of the free-DOF
pattern (gel elements + a 3x3 block per surface node for the contact) by one `np.bincount` over
precomputed positions, so the pattern (and the factorisation's symbolic analysis,
tools.fe.linsolve) stays the same for a whole solve, and the sums run in a fixed order
(bit-identical results run to run). tests/test_fe_assembly.py checks both against felupe's.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp


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
        self.n_elem_entries = er.size
        self.pos = pos
        self.nnz = len(ukeys)
        self.indices = (ukeys % nf).astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(ukeys // nf, minlength=nf))]).astype(np.int32)

    # -- kinematics ------------------------------------------------------------------------------
    def kinematics(self, U: np.ndarray, umat) -> tuple:
        """Per-cell quantities at displacement U (N,3) that forces and tangent share; pass them back as
        `cells=` to skip recomputing them (the Newton loop's tangent is at its last residual's U)."""
        ue = U[self.tets]                                                   # (C,4,3)
        F = np.eye(3) + ue.transpose(0, 2, 1) @ self.B                     # (C,3,3) F_iJ
        J, iF = _det_inv3(F)
        trC = np.einsum("ciJ,ciJ->c", F, F)
        a = J ** (-2.0 / 3.0)
        f1, f2 = umat._f(a * trC)
        p = self.B @ F.transpose(0, 2, 1)                                   # (C,4,3) F B_a
        q = self.B @ iF                                                     # (C,4,3) F^-T B_a
        d = (2.0 * a)[:, None, None] * (p - (trC / 3.0)[:, None, None] * q)  # dI1b/dF B_a
        return J, trC, a, f1, f2, p, q, d

    def _element_forces(self, J, f1, q, d, bulk):
        return self.V[:, None, None] * (f1[:, None, None] * d + (bulk * (J - 1.0) * J)[:, None, None] * q)

    def forces(self, U: np.ndarray, umat, cells: tuple | None = None) -> np.ndarray:
        """Internal force vector (ndof,) of the gel at displacement U (N,3)."""
        J, _, _, f1, _, _, q, d = cells if cells is not None else self.kinematics(U, umat)
        return np.bincount(self.edofs, self._element_forces(J, f1, q, d, umat.bulk).ravel(), minlength=self.ndof)

    def forces_and_tangent(self, U: np.ndarray, umat, contact_K: np.ndarray | None = None,
                           cells: tuple | None = None):
        """(internal force vector (ndof,), CSR data (nnz,) of the free-DOF tangent incl. contact_K).

        contact_K (M,3,3): d(contact force)/dx per surface node; enters with a minus sign (the
        residual is internal minus contact force)."""
        J, trC, a, f1, f2, p, q, d = cells if cells is not None else self.kinematics(U, umat)
        V, kap = self.V, umat.bulk
        fe = self._element_forces(J, f1, q, d, kap)
        C = len(V)
        # rank-3 part: [p q d]_a M [p q d]_b^T with M = [[0, beta, 0], [beta, gamma, 0], [0, 0, V f2]]
        M = np.zeros((C, 3, 3))
        M[:, 0, 1] = M[:, 1, 0] = V * (-4.0 / 3.0) * a * f1
        M[:, 1, 1] = V * (4.0 / 9.0 * a * trC * f1 + kap * J * (2.0 * J - 1.0))
        M[:, 2, 2] = V * f2
        L = np.stack([p, q, d], axis=3).reshape(C, 12, 3)
        K = ((L @ M) @ L.transpose(0, 2, 1)).reshape(C, 4, 3, 4, 3)
        # swap part delta q_bi q_ak and the isotropic part 2 a f1 (B_a . B_b) delta_ik
        de = V * (2.0 / 3.0 * a * trC * f1 - kap * (J - 1.0) * J)
        qd = q * de[:, None, None]
        K += (qd.reshape(C, 12, 1) * q.reshape(C, 1, 12)).reshape(C, 4, 3, 4, 3).transpose(0, 1, 4, 3, 2)
        g = self.gram * (V * 2.0 * a * f1)[:, None, None]
        for i in range(3):
            K[:, :, i, :, i] += g
        w = K.ravel()
        if contact_K is not None:
            w = np.concatenate([w, -np.asarray(contact_K).ravel()])
            pos = self.pos
        else:
            pos = self.pos[:self.n_elem_entries]
        data = np.bincount(pos, w, minlength=self.nnz + 1)[:self.nnz]
        return np.bincount(self.edofs, fe.ravel(), minlength=self.ndof), data

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """The free-DOF tangent as a CSR matrix sharing this pattern's index arrays."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.nfree, self.nfree), copy=False)


def _det_inv3(F: np.ndarray):
    """Determinants (C,) and inverses (C,3,3) of (C,3,3) matrices by cofactors."""
    a, b, c = F[:, 0, 0], F[:, 0, 1], F[:, 0, 2]
    d, e, f = F[:, 1, 0], F[:, 1, 1], F[:, 1, 2]
    g, h, i = F[:, 2, 0], F[:, 2, 1], F[:, 2, 2]
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    J = a * c00 + b * c01 + c * c02
    adj = np.stack([c00, c * h - b * i, b * f - c * e,
                    c01, a * i - c * g, c * d - a * f,
                    c02, b * g - a * h, a * e - b * d], axis=1).reshape(-1, 3, 3)
    return J, adj / J[:, None, None]
