"""Quasi-static Newton-Raphson solver: felupe hyperelastic gel + rigid penalty contact with friction.

Linear tets with the Yeoh / neo-Hookean material (the shipped default) are assembled by
tools.fe.assembly straight onto a fixed free-DOF pattern; quadratic tets (mixed u/p/J, mesh.order = 2)
and Mooney-Rivlin go through felupe's assembly. tools.fe.contact adds the node-to-rigid-indenter
forces and their exact 3x3 tangents. The linear solver (tools.fe.linsolve) is an engine:
"pardiso-krylov" (default: pardiso-mixed's factors kept across tangents, each tangent solved by GCR on
them; below KRYLOV_MIN_DOFS free DOFs the same bits as pardiso-mixed),
"pardiso-mixed" ("pardiso-reuse" with single-precision factors refined in double),
"pardiso-reuse" ("pardiso" plus chord steps on the kept factorisation, CHORD_RATIO),
"pardiso" (MKL PARDISO, symbolic analysis once per solve, symmetric type when the tangent is
symmetric, one factorisation per Newton iteration) or "superlu" (the original path: felupe assembly
and scipy's SuperLU, kept as the reference `tensortouch bench fe` compares against). Each keypoint step is split into increments
(cutback on failure).
"""
from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import time
from dataclasses import asdict

import numpy as np
import scipy.sparse as sp

from . import contact as fc
from .assembly import P1Assembly
from .errors import FEConvergenceError, ScenarioError
from .indenters import make_shape, pose_at, rotmat
from .linsolve import ENGINES, make_factor
from .materials import YeohUmat, effective_bulk, make_umat
from .mesh import GelMesh, mesh_gel
from .result import FEResult
from .scenario import Scenario

log = logging.getLogger(__name__)

INITIAL_PENETRATION_TOL = 1e-6  # mm
# Bumped when a change lets the solver converge where it did not before (2: struggle mode in newton;
# 3: struggle mode's absolute acceptance floor, ACCEPT_ABS), so
# failures recorded by an older solver (tools.twin.fe_physics `*.failed.json`) are tried again.
SOLVER_REVISION = 3
# A node that touches an indenter for the first time sticks where the indenter met it (the surface
# point its converged position crosses between the converged and the current pose), not at the
# closest point, so frictional normal forces do not depend on the increment size (docs/fe.md,
# docs/decisions/2026-11-25-fe-increments-and-locking.md). Module switch, not a scenario field, so
# the scenario hashes (the FE cache keys) stay as they are; solver_info records it.
FIRST_TOUCH_ANCHOR = True
# Linear solver engine when solve() is not told (tools.fe.linsolve); the environment variable
# TENSORTOUCH_FE_ENGINE sets it for a whole pipeline, batch worker processes included (before/after
# timings of a recipe stage). Not a scenario field: the engines solve the same equations (pardiso and
# superlu agree to rounding, pardiso-reuse and pardiso-mixed to the Newton tolerance, `tensortouch
# bench fe`), so the scenario hashes (the FE cache keys) stay as they are; solver_info records the engine.
# pardiso-krylov (GCR on kept single-precision factors; below linsolve.KRYLOV_MIN_DOFS free DOFs the same
# bits as pardiso-mixed): docs/decisions/2026-12-06-fe-krylov-stale-factors.md.
DEFAULT_ENGINE = os.environ.get("TENSORTOUCH_FE_ENGINE", "pardiso-krylov")
# An increment's Newton matrix leaves out the normal penalty's curvature term (tools.fe.contact,
# `normal_curvature`) until a step has moved no node more than this fraction of the top mesh size (the
# convergence test's own step bound); the exact tangent then finishes the increment quadratically.
# The forces and the convergence test do not change, so results move only within the Newton
# tolerance. On the ccx agreement press (1.2 mm mesh) the exact term from the start gave 23 iterations
# and 22 factorisations, this 12 and 9 (docs/decisions/2026-12-02-fe-contact-tangent.md). 0: the exact
# tangent throughout.
CURVATURE_STEP_FRACTION = 0.02


# Where the indenters' motion turns (the increment's direction more than ~25 deg from the last one's,
# e.g. press -> slide, where the whole contact patch goes from stick towards slip) the predictor cannot
# extrapolate and Newton needed 16 iterations for the first slide increment of `tensortouch bench fe`;
# that increment is shortened to this fraction (the rest of the step follows as usual): 7 + 4
# iterations instead of 16, final forces 5e-8 apart (docs/fe.md). Module constant like
# FIRST_TOUCH_ANCHOR (the scenario hashes stay as they are); solver_info records it.
TURN_INCREMENT_FRACTION = 0.5


MESH_MEMO_SIZE = 4
_MESH_MEMO: dict[str, GelMesh] = {}


def build_mesh(scenario: Scenario) -> GelMesh:
    """The scenario's gel mesh. gmsh is deterministic for fixed inputs, so meshes of analytic gels are
    kept per process (the last MESH_MEMO_SIZE gel + mesh settings): a twin recording or a batch
    worker meshes its gel once, not once per poke. The arrays are shared: treat them as read-only."""
    if scenario.gel.kind == "stl":
        return mesh_gel(scenario.gel, scenario.mesh, stl_path=str(scenario.resolve(scenario.gel.stl_path)))
    key = json.dumps([asdict(scenario.gel), asdict(scenario.mesh)], sort_keys=True)
    gm = _MESH_MEMO.pop(key, None)
    if gm is None:
        gm = mesh_gel(scenario.gel, scenario.mesh)
    _MESH_MEMO[key] = gm
    while len(_MESH_MEMO) > MESH_MEMO_SIZE:
        _MESH_MEMO.pop(next(iter(_MESH_MEMO)))
    return gm


class GelModel:
    """felupe objects + contact bookkeeping for one scenario and mesh."""

    def __init__(self, scenario: Scenario, gm: GelMesh, engine: str = DEFAULT_ENGINE):
        import felupe as fem

        if engine not in ENGINES:
            raise ScenarioError(f"FE engine {engine!r} (solve(engine=) or TENSORTOUCH_FE_ENGINE): expected one of "
                                f"{', '.join(ENGINES)}")
        self.engine = engine

        self.sc, self.gm = scenario, gm
        self.order = 2 if gm.tets.shape[1] == 10 else 1
        self.bulk = effective_bulk(scenario.material, self.order, scenario.solver.max_bulk_ratio)
        if self.order == 2:  # P2/P0 mixed u/p/J (hybrid-like): no volumetric locking
            mesh = fem.Mesh(gm.nodes, gm.tets, "tetra10")
            self.region = fem.RegionQuadraticTetra(mesh)
        else:
            mesh = fem.Mesh(gm.nodes, gm.tets, "tetra")
            self.region = fem.RegionTetra(mesh)
        self.u = fem.Field(self.region, dim=3)
        self.field = fem.FieldContainer([self.u])
        if self.order == 2:
            self.umat = make_umat(scenario.material, 0.0)
            self.solid = fem.SolidBodyNearlyIncompressible(self.umat, self.field, bulk=self.bulk)
        else:
            self.umat = make_umat(scenario.material, self.bulk)
            self.solid = fem.SolidBody(self.umat, self.field)
        n = len(gm.nodes)
        self.ndof = 3 * n
        fixed = (3 * gm.fixed_nodes[:, None] + np.arange(3)).ravel()
        mask = np.ones(self.ndof, bool)
        mask[fixed] = False
        self.free = np.flatnonzero(mask)
        self.fixed = fixed
        self.surf = gm.surface_nodes
        self.surf_dofs = (3 * self.surf[:, None] + np.arange(3)).ravel()
        self.area = gm.node_area[self.surf]
        self.shapes = [make_shape(i, scenario.resolve) for i in scenario.indenters]
        mu0 = scenario.material.shear_modulus
        self.penalty = scenario.solver.penalty_scale * mu0 / scenario.mesh.size_top  # N/mm^3
        rows = np.repeat(self.surf_dofs.reshape(-1, 3), 3, axis=1).ravel()
        cols = np.tile(self.surf_dofs.reshape(-1, 3), (1, 3)).ravel()
        self._crow, self._ccol = rows, cols
        self.fast = None  # own P1 assembly on a fixed pattern (the pardiso engines, Yeoh on linear tets)
        if engine.startswith("pardiso") and self.order == 1 and isinstance(self.umat, YeohUmat):
            self.fast = getattr(gm, "_p1_assembly", None)  # the pattern depends on the mesh only
            if self.fast is None:
                B = np.asarray(self.region.dhdX)[:, :, 0, :].transpose(2, 0, 1)
                self.fast = P1Assembly(gm.tets, n, self.free, self.surf_dofs, B, np.asarray(self.region.dV)[0])
                gm._p1_assembly = self.fast
        self.symmetric = scenario.friction == 0.0
        self.factor = make_factor(engine, self.symmetric)

    def poses(self, s: float):
        out = []
        for ind in self.sc.indenters:
            p, rv = pose_at(ind, s)
            out.append((p, rotmat(rv)))
        return out

    def set_u(self, U):
        self.u.values[:] = U

    def residual(self, U, poses, state, tangent=True, hold=None, slip_tangent="exact", curvature=True):
        self._U = U
        if self.fast is not None:
            r = self.fast.forces(U, self.umat)
        else:
            r = self.internal_forces(U)
        x = self.gm.nodes[self.surf] + U[self.surf]
        ce = fc.evaluate(x, self.area, self.shapes, poses, state, self.penalty, self.sc.friction, tangent,
                         self.sc.solver.friction_stiffness_ratio, hold, slip_tangent,
                         normal_curvature=curvature)
        r[self.surf_dofs] -= (ce.fn + ce.ft).ravel()
        return r, ce

    def internal_forces(self, U) -> np.ndarray:
        """Internal force vector of the gel (3N,) at displacement U (N,3)."""
        if self.fast is not None:
            return self.fast.forces(U, self.umat)
        self.set_u(U)
        return np.asarray(self.solid.assemble.vector(self.field).todense()).ravel()

    def tangent(self, ce):
        """Free-DOF tangent at the displacement of the last residual() call."""
        if self.fast is not None:
            _, data = self.fast.forces_and_tangent(self._U, self.umat, ce.K)
            return self.fast.matrix(data)
        self.set_u(self._U)
        K = self.solid.assemble.matrix(self.field).tocsr()
        Kc = sp.csr_matrix((-ce.K.ravel(), (self._crow, self._ccol)), shape=K.shape)
        return (K + Kc)[self.free][:, self.free].tocsc()

    def reset_state(self, U):
        """Mixed u/p/J only: re-initialise the cell fields from U (after a cutback)."""
        self.set_u(U)
        if self.order == 2:
            self.solid.restore(self.solid.checkpoint(), restore_state=False)

    def cauchy_nodal(self, U) -> np.ndarray:
        self.set_u(U)
        sig = np.asarray(self.solid.evaluate.cauchy_stress(self.field)).mean(axis=2)  # (3,3,c)
        voigt = np.stack([sig[0, 0], sig[1, 1], sig[2, 2], sig[0, 1], sig[0, 2], sig[1, 2]], axis=1)
        vol = self.region.dV.sum(axis=0)
        tets = self.gm.tets
        n, per = len(self.gm.nodes), tets.shape[1]
        w = np.bincount(tets.ravel(), np.repeat(vol, per), minlength=n)
        out = np.zeros((n, 6))
        for c in range(6):
            out[:, c] = np.bincount(tets.ravel(), np.repeat(vol * voigt[:, c], per), minlength=n)
        return out / np.maximum(w, 1e-300)[:, None]


# Chord steps (engines "pardiso-reuse" and "pardiso-mixed", tools.fe.linsolve `allow_chord`): once a Newton step
# has cut the residual to CHORD_RATIO of the last iterate's (the quadratic range; not the first step,
# whose starting residual is the predictor's), the next correction
# reuses the kept factorisation with no new tangent (assembly) and no refactorisation, as long as
# each such step keeps cutting the residual by CHORD_RATIO; otherwise the next step is a full Newton
# step again. The convergence test is the same, so the result is converged to the same tolerance.
CHORD_RATIO = 0.1
HOLD_AFTER = 8      # Newton iterations of plain Newton before an increment switches to struggle mode
ACCEPT_REL = 5e-3   # struggle mode: best iterate accepted if |r|max <= ACCEPT_REL * total normal force
ACCEPT_ABS = 2.5e-3  # ... or <= this many N whatever the normal force (ACCEPT_REL's bound at 0.5 N)


def accept_best(res: float, normal_force: float, tol_force: float) -> bool:
    """Whether struggle mode may accept its best iterate: largest free-node residual `res` (N) against
    the total normal force `normal_force` (N). The relative bound alone refuses every iterate when the
    indenter is leaving the gel (normal force -> 0) although the residual is then a few mN on a node,
    far below the labels' own error; the absolute floor accepts those."""
    return bool(res <= max(tol_force, ACCEPT_ABS, ACCEPT_REL * normal_force))


def newton(model: GelModel, U0, poses, state, sv):
    """Solve equilibrium at fixed indenter poses; returns (U, ContactEval, iterations, residual).

    An increment still unconverged after HOLD_AFTER iterations goes into struggle mode: nodes that
    slipped are held slipping (contact.evaluate `hold`) and slip uses the secant tangent, which breaks
    the stick/slip flip cycles of deep slides; if it still misses tol_force after max_iterations, its
    best iterate is accepted when that residual is <= ACCEPT_REL of the total normal force (at most
    25 mN on one node under a 5 N contact) or <= ACCEPT_ABS (unloading, normal force near 0; logged).
    Until a step is small (CURVATURE_STEP_FRACTION) the Newton matrix leaves out the normal penalty's
    curvature term; otherwise an increment that converges within HOLD_AFTER iterations is solved by
    plain Newton. docs/fe.md "Struggle mode for deep slides" has the measurements."""
    U = U0.copy()
    hold, mode = None, "exact"
    curv = not CURVATURE_STEP_FRACTION > 0
    r, ce = model.residual(U, poses, state, curvature=curv)
    best = None
    chord_ok = model.factor.allow_chord
    chord = False
    res_prev = np.abs(r[model.free]).max()
    for it in range(1, sv.max_iterations + 1):
        if it > HOLD_AFTER:
            hold = ce.slip.copy() if hold is None else hold | ce.slip
            if mode == "exact":
                mode = "secant"
                r, ce = model.residual(U, poses, state, hold=hold, slip_tangent=mode, curvature=curv)
                chord = False   # the kept factors are of the exact tangent: struggle mode refactorises
        rf = r[model.free]
        fscale = max(np.abs(ce.fn).sum(), 1e-12)
        if chord:
            model.factor.chord_steps += 1
        else:
            model.factor.factor(model.tangent(ce))  # SingularTangent is a FloatingPointError
        du = -model.factor.solve(rf)
        if not np.all(np.isfinite(du)):
            raise FloatingPointError("non-finite Newton update")
        norm0 = np.linalg.norm(rf)
        step = 1.0
        for _ in range(6):  # backtracking line search on the residual norm
            Ut = U.copy()
            Ut.reshape(-1)[model.free] += step * du
            with np.errstate(invalid="ignore", divide="ignore"):
                rt, cet = model.residual(Ut, poses, state, hold=hold, slip_tangent=mode, curvature=curv)
            nt = np.linalg.norm(rt[model.free])
            if np.isfinite(nt) and (nt < norm0 or step < 0.1):
                break
            step *= 0.5
        U, r, ce = Ut, rt, cet
        res = np.abs(r[model.free]).max()
        if not np.isfinite(res):
            if best is not None:
                break
            raise FloatingPointError("inverted elements (non-finite residual)")
        dmax = np.abs(step * du).max()
        log.debug("  it %d: |r|max %.3e N, |du|max %.3e mm, step %.2f", it, res, dmax, step)
        if res <= max(sv.tol_force, sv.tol_rel * fscale) and dmax < 0.02 * model.sc.mesh.size_top:
            return U, ce, it, res
        if not curv and dmax < CURVATURE_STEP_FRACTION * model.sc.mesh.size_top:
            curv = True   # the rest of the increment on the exact tangent (the forces are the same)
            r, ce = model.residual(U, poses, state, hold=hold, slip_tangent=mode, curvature=curv)
        chord = chord_ok and mode == "exact" and it >= 2 and res <= CHORD_RATIO * res_prev
        res_prev = res
        if mode != "exact" and (best is None or res < best[3]):
            best = (U, ce, it, res, max(np.abs(ce.fn).sum(), 1e-12))
    if best is not None and accept_best(best[3], best[4], sv.tol_force):
        log.info("increment accepted at |r|max %.2e N (%.1e of the normal force %.2f N) after %d iterations",
                 best[3], best[3] / best[4], best[4], sv.max_iterations)
        return best[:4]
    if not np.isfinite(res):
        raise FloatingPointError("inverted elements (non-finite residual)")
    raise FloatingPointError(f"no convergence in {sv.max_iterations} iterations (|r|max {res:.3e} N)")


def _n_increments(model: GelModel, s0: float, s1: float) -> int:
    sv = model.sc.solver
    n = sv.min_increments
    for ind in model.sc.indenters:
        (p0, r0), (p1, r1) = pose_at(ind, s0), pose_at(ind, s1)
        n = max(n, math.ceil(np.linalg.norm(p1 - p0) / sv.max_increment_mm - 1e-9),
                math.ceil(np.linalg.norm(r1 - r0) / sv.max_increment_rad - 1e-9))
    return n


def _motion(model: GelModel, s0: float, s1: float) -> np.ndarray:
    """Concatenated pose change (translation mm, rotation vector rad) of all indenters."""
    parts = []
    for ind in model.sc.indenters:
        (p0, r0), (p1, r1) = pose_at(ind, s0), pose_at(ind, s1)
        parts += [p1 - p0, r1 - r0]
    return np.concatenate(parts)


def check_initial(model: GelModel) -> None:
    poses = model.poses(-1.0)
    x = model.gm.nodes[model.surf]
    for k, (shape, (p, R)) in enumerate(zip(model.shapes, poses)):
        d, _ = shape.sdf((x - p) @ R)
        if d.min() < -INITIAL_PENETRATION_TOL:
            ind = model.sc.indenters[k]
            raise ScenarioError(f"indenters[{k}] ({ind.name}).position: the initial pose penetrates "
                                f"the gel by {-d.min():.3f} mm; start the indenter above the surface")


def _blas_one_thread():
    """numpy's OpenBLAS held to one thread during a solve: its BLAS calls here are tiny products, and
    a second thread only spins (≈ 10 % more CPU for the same bits). PARDISO's threads are set per call
    (tools.fe.linsolve.THREADS). threadpoolctl comes with the train extra (scikit-learn); without it,
    no limit."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def solve(scenario: Scenario, progress=None, mesh: GelMesh | None = None, engine: str | None = None) -> FEResult:
    """Solve all keypoint frames of `scenario`; see docs/fe.md for the contract. `engine`: the
    linear solver path (tools.fe.linsolve.ENGINES; None = DEFAULT_ENGINE)."""
    with _blas_one_thread():
        return _solve(scenario, progress, mesh, engine)


def _solve(scenario: Scenario, progress, mesh: GelMesh | None, engine: str | None) -> FEResult:
    scenario.validate()
    t_start = time.time()
    gm = mesh if mesh is not None else build_mesh(scenario)
    model = GelModel(scenario, gm, engine or DEFAULT_ENGINE)
    check_initial(model)
    sv = scenario.solver
    N, K, F = len(gm.nodes), len(scenario.indenters), scenario.n_keypoints
    out = _alloc(N, K, F)
    U = np.zeros((N, 3))
    state = fc.ContactState.empty(K, gm.nodes[model.surf], model.poses(-1.0) if FIRST_TOUCH_ANCHOR else None)
    s_done = -1.0
    stats = {"increments": 0, "iterations": 0, "cutbacks": 0}
    dU_last, m_last = None, None
    for j in range(F):
        t0 = time.time()
        n_inc = _n_increments(model, s_done, float(j))
        ds = (j - s_done) / n_inc
        cut = 0
        while s_done < j - 1e-12:
            s_try = min(s_done + ds, float(j))
            m_new = _motion(model, s_done, s_try)
            if m_last is not None and float(m_new @ m_last) < 0.9 * np.linalg.norm(m_new) * np.linalg.norm(m_last):
                s_try = s_done + TURN_INCREMENT_FRACTION * (s_try - s_done)  # the motion turns: shorter first step
                m_new = _motion(model, s_done, s_try)
            U0 = U  # predictor: extrapolate the last increment when the motion continues
            if dU_last is not None:
                c = float(m_new @ m_last) / max(float(m_last @ m_last), 1e-30)
                cos = float(m_new @ m_last) / max(np.linalg.norm(m_new) * np.linalg.norm(m_last), 1e-30)
                if cos > 0.9:
                    U0 = U + c * dU_last
            try:
                U_new, ce, its, _ = newton(model, U0, model.poses(s_try), state, sv)
            except FloatingPointError as exc:
                cut += 1
                stats["cutbacks"] += 1
                if cut > sv.max_cutbacks:
                    msg = (f"keypoint step {j} did not converge at keypoint {s_try:.4f} after "
                           f"{sv.max_cutbacks} cutbacks: {exc}")
                    partial = _finish(out, model, scenario, stats, t_start, F)
                    raise FEConvergenceError(msg, partial=partial) from exc
                ds *= 0.5
                dU_last = None
                model.reset_state(U)
                log.info("step %d: cutback %d (%s), increment %.4f", j, cut, exc, ds)
                continue
            dU_last, m_last = U_new - U, m_new
            U, s_done = U_new, s_try
            state = fc.ContactState(np.where(ce.gap[:, :, None] >= 0, np.nan, ce.new_anchors),
                                    gm.nodes[model.surf] + U[model.surf],
                                    model.poses(s_try) if FIRST_TOUCH_ANCHOR else None)
            stats["increments"] += 1
            stats["iterations"] += its
        _record(out, j, model, U, ce, time.time() - t0)
        if progress:
            progress(j, F, f"frame {j + 1}/{F}: |RF| " +
                     ", ".join(f"{np.linalg.norm(out['RF'][j, k]):.3f}" for k in range(K)) + " N")
    return _finish(out, model, scenario, stats, t_start, F)


def _alloc(N, K, F):
    z = np.zeros
    return {"U": z((F, N, 3)), "S": z((F, N, 6)), "CNORMF": z((F, N, 3)), "CSHEAR": z((F, N, 3)),
            "contact_owner": np.full((F, N), -1, np.int16), "CAREA": z((F, K)), "RF": z((F, K, 3)),
            "RM": z((F, K, 3)), "pose_position": z((F, K, 3)), "pose_rotation": z((F, K, 3)),
            "converged": np.zeros(F, bool), "base_reaction": z((F, 3)), "seconds": z(F)}


def _record(out, j, model: GelModel, U, ce, seconds):
    surf = model.surf
    out["U"][j] = U
    out["S"][j] = model.cauchy_nodal(U)
    out["CNORMF"][j, surf] = ce.fn
    out["CSHEAR"][j, surf] = ce.ft
    out["contact_owner"][j, surf] = ce.owner
    x = model.gm.nodes[surf] + U[surf]
    for k, ind in enumerate(model.sc.indenters):
        p, rv = pose_at(ind, float(j))
        out["pose_position"][j, k], out["pose_rotation"][j, k] = p, rv
        out["CAREA"][j, k] = model.area[ce.gap[k] < 0].sum()
        out["RF"][j, k] = ce.force_k[k].sum(axis=0)
        out["RM"][j, k] = np.cross(x - p, ce.force_k[k]).sum(axis=0)
    r = model.internal_forces(U)
    out["base_reaction"][j] = r[model.fixed].reshape(-1, 3).sum(axis=0)
    out["converged"][j] = True
    out["seconds"][j] = seconds


def _finish(out, model: GelModel, scenario: Scenario, stats, t_start, F) -> FEResult:
    import felupe

    elem = "P1 tets" if model.order == 1 else "P2/P0 u-p-J tets"
    info = {"solver": f"tools.fe (felupe {felupe.__version__}, {elem}, penalty contact)", "order": model.order,
            "bulk_modulus_used": model.bulk, "penalty_N_per_mm3": model.penalty,
            "first_touch_anchor": FIRST_TOUCH_ANCHOR, "turn_increment_fraction": TURN_INCREMENT_FRACTION,
            "engine": model.engine,
            "assembly": "tools.fe.assembly (P1 Yeoh)" if model.fast is not None else "felupe",
            "symmetric_tangent": model.symmetric, "curvature_step_fraction": CURVATURE_STEP_FRACTION,
            "factorizations": model.factor.factorizations,
            "symbolic_analyses": model.factor.analyses,
            "chord_steps": model.factor.chord_steps, "chord_ratio": CHORD_RATIO,
            "refinements": model.factor.refinements,
            "double_fallbacks": model.factor.double_fallbacks,
            **{k: getattr(model.factor, k) for k in ("krylov_solves", "krylov_iterations", "krylov_failures",
                                                     "schwarz_nodes") if hasattr(model.factor, k)},
            "seconds_total": time.time() - t_start, **stats}
    gm = model.gm
    return FEResult(nodes=gm.nodes, tets=gm.tets, surface_nodes=gm.surface_nodes,
                    surface_tris=gm.surface_tris, fixed_nodes=gm.fixed_nodes,
                    indenter_names=np.array([i.name for i in scenario.indenters]),
                    scenario_json=scenario.to_json(), scenario_hash=scenario.hash(),
                    solver_info=json.dumps(info), **out)
