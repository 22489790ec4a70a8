"""Constitutive models for felupe: Yeoh / neo-Hookean (closed form) and Mooney-Rivlin (autodiff).

Yeoh (Abaqus form): W = sum_i Ci0 (I1b - 3)^i + (J - 1)^2 / D1, with I1b = J^(-2/3) tr(C).
Here W_iso = f(I1b), so P = f' dI1b/dF and A = f'' dI1b/dF (x) dI1b/dF + f' d2I1b/dF2, both in
closed form below (fast). Neo-Hookean is Yeoh with C20 = C30 = 0. Mooney-Rivlin uses felupe's
tensortrax autodiff model. The volumetric part K/2 (J-1)^2 (K = 2/D1) is closed form too.
The same Yeoh is also available through felupe+tensortrax (`felupe_reference_umat`), which the tests
use as an independent second formulation of the element forces and tangents.
"""
from __future__ import annotations

import logging

import numpy as np

from .scenario import Material

log = logging.getLogger(__name__)


def _kin(F):
    J = np.linalg.det(F.transpose(2, 3, 0, 1))
    iFT = np.linalg.inv(F.transpose(2, 3, 0, 1)).transpose(3, 2, 0, 1)  # (i,J,q,c) = F^-T
    trC = np.einsum("iJqc,iJqc->qc", F, F)
    return J, iFT, trC


class YeohUmat:
    """felupe user material (gradient/hessian of W w.r.t. F) for Yeoh with bulk modulus `bulk`."""

    def __init__(self, C10: float, C20: float = 0.0, C30: float = 0.0, bulk: float = 0.0):
        self.C10, self.C20, self.C30, self.bulk = float(C10), float(C20), float(C30), float(bulk)
        self.x = [np.eye(3), np.zeros(0)]

    def _f(self, I1b):
        d = I1b - 3.0
        f1 = self.C10 + 2 * self.C20 * d + 3 * self.C30 * d * d
        f2 = 2 * self.C20 + 6 * self.C30 * d
        return f1, f2

    def function(self, x):
        F = x[0]
        J, _, trC = _kin(F)
        d = J ** (-2 / 3) * trC - 3
        return [self.C10 * d + self.C20 * d ** 2 + self.C30 * d ** 3 + self.bulk / 2 * (J - 1) ** 2]

    def gradient(self, x):
        F, statevars = x[0], x[-1]
        J, iFT, trC = _kin(F)
        a = J ** (-2 / 3)
        dI = 2 * a * (F - trC / 3 * iFT)
        f1, _ = self._f(a * trC)
        P = f1 * dI + self.bulk * (J - 1) * J * iFT
        return [P, statevars]

    def hessian(self, x):
        F = x[0]
        J, iFT, trC = _kin(F)
        a = J ** (-2 / 3)
        dI = 2 * a * (F - trC / 3 * iFT)
        f1, f2 = self._f(a * trC)
        eye = np.eye(3)
        A = np.einsum("ik,JL,qc->iJkLqc", eye, eye, 2 * a * f1)
        FiF = np.einsum("iJqc,kLqc->iJkLqc", F, iFT)
        A -= 4 / 3 * a * f1 * (FiF + FiF.transpose(2, 3, 0, 1, 4, 5))
        ii = np.einsum("iJqc,kLqc->iJkLqc", iFT, iFT)
        ix = np.einsum("iLqc,kJqc->iJkLqc", iFT, iFT)
        A += 4 / 9 * a * trC * f1 * ii + 2 / 3 * a * trC * f1 * ix
        A += f2 * np.einsum("iJqc,kLqc->iJkLqc", dI, dI)
        if self.bulk:
            A += self.bulk * J * (2 * J - 1) * ii - self.bulk * (J - 1) * J * ix
        return [A]


def effective_bulk(material: Material, order: int, max_bulk_ratio: float) -> float:
    """Bulk modulus used by the solver: 2/D1, capped at max_bulk_ratio * mu0 for linear tets (the
    locking compensation; against a mesh-converged C3D10 reference, cap 5 reads 1–6 % low and cap 6
    is within ±2.8 % on a 0.5–3 mm dome press: docs/fe.md "Volumetric locking")."""
    bulk = material.bulk_modulus
    cap = max_bulk_ratio * material.shear_modulus
    if order == 1 and max_bulk_ratio > 0 and bulk > cap:
        log.info("material: linear tets use bulk/shear = %.0f instead of %.0f (K = %.4g MPa), the "
                 "locking compensation; see docs/fe.md",
                 max_bulk_ratio, bulk / material.shear_modulus, cap)
        return cap
    return bulk


def make_umat(material: Material, bulk: float):
    """felupe umat for the scenario material with the given bulk modulus (MPa)."""
    if material.model == "yeoh":
        return YeohUmat(material.C10, material.C20, material.C30, bulk)
    if material.model == "neo_hookean":
        return YeohUmat(material.C10, 0.0, 0.0, bulk)
    return felupe_reference_umat(material, bulk)


def felupe_reference_umat(material: Material, bulk: float):
    """The same material through felupe's tensortrax autodiff models (second formulation)."""
    import felupe as fem

    if material.model == "mooney_rivlin":
        iso = fem.Hyperelastic(fem.mooney_rivlin, C10=material.C10, C01=material.C01)
    elif material.model == "neo_hookean":
        iso = fem.Hyperelastic(fem.yeoh, C10=material.C10, C20=0.0, C30=0.0)
    else:
        iso = fem.Hyperelastic(fem.yeoh, C10=material.C10, C20=material.C20, C30=material.C30)
    return iso & fem.Volumetric(bulk=bulk) if bulk else iso


def cauchy_from_P(F: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Cauchy stress sigma = P F^T / J for (3,3,...) arrays."""
    J = np.linalg.det(np.moveaxis(F, (0, 1), (-2, -1)))
    return np.einsum("iJ...,kJ...->ik...", P, F) / J
