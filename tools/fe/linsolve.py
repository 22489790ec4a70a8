"""Sparse direct solves of the FE Newton iterations.

`PardisoFactor` (engine "pardiso"): Intel MKL PARDISO, called through ctypes from the
`mkl` wheel's mkl_rt library (the train extra). The tangent's pattern is fixed for a whole solve (tools.fe.assembly), so the symbolic
analysis (METIS ordering, supernode structure: phase 11) runs once and every later Newton iteration
and keypoint only refactorises the numbers (phase 22) and solves (phase 33). Symmetric tangents
(frictionless contact) use the real symmetric indefinite type on the upper triangle (Bunch-Kaufman
pivoting), general ones the real unsymmetric type (no scaling or matching: an FE tangent has a
strong diagonal, and both cost time). PARDISO runs in its conditional numerical reproducibility
mode (iparm[33]): the factors and solutions are the same bits with one thread or two, so the thread
count (`THREADS`: 1, or environment variable TENSORTOUCH_FE_THREADS) is a speed setting, not part
of a result. Threads come from MKL's GNU
OpenMP layer (the libgomp that torch also uses; MKL's Intel layer crashes next to torch), or the
sequential layer where no libgomp is installed. Engine "pardiso-reuse"
is the same factor with `allow_chord`: the Newton loop (tools.fe.solver.CHORD_RATIO) may solve with
the kept factors instead of refactorising once it converges quadratically. Engine "pardiso-mixed"
is "pardiso-reuse" with `mixed`: PARDISO factorises and solves in single precision
(iparm[27], about 1.7x faster per factorisation here) and `solve` refines the solution in double
precision against the double matrix (residual b - A x in float64, a correction from the single
factors) until the relative residual is <= REFINE_TOL, which one or two corrections reach on the FE
tangents (raw single solve 1e-6, after one correction 1e-11, after two the double solve's 1e-15).
Where refinement does not reach it within MAX_REFINE corrections (a tangent too ill-conditioned for
single factors), the matrix is refactorised in double precision and solved there (counted in
`double_fallbacks`), so the step is never less accurate than REFINE_TOL. `KrylovFactor`
(engine "pardiso-krylov", the default: tools.fe.solver.DEFAULT_ENGINE) keeps those single-precision factors across Newton iterations, increments and
keypoints and solves each new tangent by GCR on them with a local exact solve on the nodes whose
diagonal block moved (the contact set), refactorising only where that fails. `SuperLUFactor`
(engine "superlu") is the reference: scipy's splu, refactorised from scratch each time.
docs/decisions/2026-11-28-fe-linear-solver.md has the measurements behind the choice.
"""
from __future__ import annotations

import ctypes
import glob
import os
import site
import sys
from ctypes.util import find_library

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from .errors import FEError

ENGINES = ("pardiso-mixed", "pardiso-krylov", "pardiso-reuse", "pardiso", "superlu")
# "pardiso-mixed": "pardiso-reuse" with single-precision factors refined in double (`mixed`).
# "pardiso-reuse": PARDISO as "pardiso", and the Newton loop may reuse the last factorisation for
# chord steps (tools.fe.solver.CHORD_RATIO; docs/decisions/2026-12-01-fe-factorisation-reuse.md).
# Mixed precision: a solve is refined until |b - A x| <= REFINE_TOL |b| (double precision); after
# MAX_REFINE corrections without reaching it, the double factorisation takes over for that matrix.
REFINE_TOL = 1e-10
MAX_REFINE = 4
_MKL_THREADING_SEQUENTIAL = 1
_MKL_THREADING_GNU = 3


def thread_count() -> int:
    """PARDISO threads per factorisation: `THREADS` when set, else TENSORTOUCH_FE_THREADS, else 1."""
    if THREADS is not None:
        return THREADS
    env = os.environ.get("TENSORTOUCH_FE_THREADS", "").strip()
    if not env:
        return 1
    try:
        n = int(env)
    except ValueError:
        n = 0
    if n < 1:
        raise FEError(f"TENSORTOUCH_FE_THREADS: expected an integer >= 1, got {env!r}")
    return n


# PARDISO threads per factorisation when set here (`bench fe --threads`); a speed setting, see above.
# One unless asked: two threads halve a factorisation on an idle machine, but with the other core busy
# every OpenMP barrier waits for a time slice and a solve took 5x longer than with one thread.
THREADS: int | None = None


class SingularTangent(FloatingPointError):
    """The factorisation met a zero pivot or another numerical failure."""


_LIB = None


def mkl_rt() -> ctypes.CDLL:
    """The mkl_rt library (loaded once per process, sequential threading layer)."""
    global _LIB
    if _LIB is None:
        names = [find_library("mkl_rt")]
        for root in (sys.prefix, site.USER_BASE):
            for sub in ("lib", "Library/bin"):
                names += sorted(glob.glob(os.path.join(root, sub, "*mkl_rt*")), key=len)
        for name in filter(None, names):
            try:
                lib = ctypes.CDLL(name)
                break
            except OSError:
                continue
        else:
            raise FEError("MKL's mkl_rt library not found: the FE's sparse solver needs the `mkl` package "
                          "(pip install -e '.[train]')")
        lib.MKL_Set_Threading_Layer.argtypes = [ctypes.c_int]
        lib.MKL_Set_Threading_Layer(_MKL_THREADING_GNU if find_library("gomp") else _MKL_THREADING_SEQUENTIAL)
        lib.MKL_Set_Num_Threads_Local.argtypes = [ctypes.c_int]
        lib.MKL_Set_Num_Threads_Local.restype = ctypes.c_int
        p_i32 = ctypes.POINTER(ctypes.c_int32)
        lib.pardiso.argtypes = [ctypes.POINTER(ctypes.c_int64)] + [p_i32] * 5 + [ctypes.c_void_p, p_i32, p_i32, p_i32,
                                                                                  p_i32, p_i32, p_i32,
                                                                                  ctypes.c_void_p, ctypes.c_void_p, p_i32]
        lib.pardiso.restype = None
        _LIB = lib
    return _LIB


class _Csr:
    """The three CSR arrays PARDISO reads (no scipy checks or copies)."""

    def __init__(self, data, indptr, indices, n):
        self.data, self.indptr, self.indices, self.shape = data, indptr, indices, (n, n)


class PardisoFactor:
    """Factorise-and-solve with the symbolic analysis kept while indptr/indices stay the same.

    `factor(A)` with A a CSR matrix with sorted indices (the full matrix also when symmetric: the
    upper triangle is taken here); `solve(b)`. Counters: `analyses`, `factorizations`; `allow_chord`
    lets the Newton loop solve with the kept factors without refactorising (it counts `chord_steps`).
    `mixed`: single-precision factors, solutions refined in double (module docstring; counters
    `refinements`, `double_fallbacks`)."""

    def __init__(self, symmetric: bool, allow_chord: bool = False, threads: int | None = None,
                 mixed: bool = False):
        self._lib = mkl_rt()
        self.mixed = bool(mixed)
        self.dtype = np.float32 if self.mixed else np.float64
        self.refinements = self.double_fallbacks = 0
        self._A64 = self._fallback = None
        self.threads = thread_count() if threads is None else int(threads)
        self.symmetric = symmetric
        self.mtype = -2 if symmetric else 11
        self.pt = np.zeros(64, np.int64)      # PARDISO's internal handle
        self.iparm = it = np.zeros(64, np.int32)
        it[0] = 1            # iparm given here, no defaults
        it[1] = 2            # METIS nested dissection ordering
        it[7] = 0            # iterative refinement: only after perturbed pivots (set in factor())
        it[9] = 8 if symmetric else 13   # pivot perturbation 1e-8 / 1e-13
        it[10] = 0           # no scaling
        it[12] = 0           # no weighted matching
        it[33] = 1           # conditional numerical reproducibility: the same bits whatever the threads
        it[17] = -1          # report nnz(L+U) in iparm[17]
        it[20] = 1           # Bunch-Kaufman pivoting (symmetric indefinite)
        it[34] = 1           # zero-based indexing
        it[27] = 1 if self.mixed else 0   # single-precision factors and solves (a, b, x in float32)
        self._pattern = None
        self._upper = None
        self._A = self._take = None
        self.analyses = self.factorizations = 0
        self.allow_chord, self.chord_steps = allow_chord, 0

    def _call(self, phase: int, A, b: np.ndarray) -> np.ndarray:
        x = np.zeros_like(b)
        err = ctypes.c_int32(0)
        i32 = ctypes.POINTER(ctypes.c_int32)

        def ref(v):
            return ctypes.byref(ctypes.c_int32(v))

        prev = self._lib.MKL_Set_Num_Threads_Local(self.threads)
        try:
            self._lib.pardiso(self.pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), ref(1), ref(1), ref(self.mtype),
                              ref(phase), ref(A.shape[0]), A.data.ctypes.data, A.indptr.ctypes.data_as(i32),
                              A.indices.ctypes.data_as(i32), None, ref(1), self.iparm.ctypes.data_as(i32), ref(0),
                              b.ctypes.data, x.ctypes.data, ctypes.byref(err))
        finally:
            self._lib.MKL_Set_Num_Threads_Local(prev)
        if err.value != 0:
            raise SingularTangent(f"PARDISO phase {phase} failed with error {err.value}")
        return x

    def factor(self, A: sp.csr_matrix) -> None:
        A = A.tocsr()
        if not A.has_sorted_indices:
            A.sort_indices()
        p = self._pattern
        same = p is not None and ((A.indptr is p[0] and A.indices is p[1]) or
                                  (np.array_equal(A.indptr, p[0]) and np.array_equal(A.indices, p[1])))
        if not same:
            if self.symmetric:  # PARDISO's symmetric types read the upper triangle only
                rows = np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))
                self._take = np.flatnonzero(A.indices >= rows)
                indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[self._take], minlength=A.shape[0]))])
                indices = A.indices[self._take]
            else:
                self._take, indptr, indices = None, A.indptr, A.indices
            self._struct = (np.ascontiguousarray(indptr, np.int32), np.ascontiguousarray(indices, np.int32))
        data = A.data if self._take is None else A.data[self._take]
        M = _Csr(np.ascontiguousarray(data, dtype=self.dtype), *self._struct, A.shape[0])
        b = np.zeros(A.shape[0], self.dtype)
        if not same:
            if self._A is not None:
                self._call(-1, self._A, b)  # release the old factors
            self._call(11, M, b)
            self.analyses += 1
            self._pattern = (A.indptr, A.indices)
        self._call(22, M, b)
        self.factorizations += 1
        # two refinement steps where pivots were perturbed (iparm[13] counts them); none otherwise,
        # where they only repeat the solve (the residual is at rounding level after one)
        # (mixed: never, the double-precision refinement in solve() does it)
        self.iparm[7] = 2 if self.iparm[13] > 0 and not self.mixed else 0
        self._A = M
        if self.mixed:
            self._A64 = A     # the assembly allocates each tangent anew: a reference, not a copy
            if self._fallback is not None:
                self._fallback.free()
                self._fallback = None

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.ascontiguousarray(b, dtype=float)
        if not self.mixed:
            return self._call(33, self._A, b)
        if self._fallback is not None:
            return self._fallback.solve(b)
        x = self._call(33, self._A, b.astype(np.float32)).astype(float)
        bound = REFINE_TOL * np.linalg.norm(b)
        for _ in range(MAX_REFINE):
            r = b - self._A64 @ x
            if np.linalg.norm(r) <= bound:
                return x
            x += self._call(33, self._A, r.astype(np.float32))
            self.refinements += 1
        if np.linalg.norm(b - self._A64 @ x) <= bound:
            return x
        # single factors too coarse for this matrix: its double factorisation solves it (and the
        # kept-factor solves of chord steps) until the next factor()
        self.double_fallbacks += 1
        self._fallback = PardisoFactor(self.symmetric, threads=self.threads)
        self._fallback.factor(self._A64)
        return self._fallback.solve(b)

    def free(self) -> None:
        if self._fallback is not None:
            self._fallback.free()
            self._fallback = None
        if self._A is not None:
            self._call(-1, self._A, np.zeros(self._A.shape[0], self.dtype))
            self._A = self._pattern = self._A64 = None

    def __del__(self):
        try:
            self.free()
        except Exception:
            pass


# Engine "pardiso-krylov": Newton systems solved by GCR preconditioned by kept (stale) single-precision
# factors of an earlier tangent, with an exact local solve on the nodes whose diagonal 3x3 block moved
# (the contact set) and one ring of their neighbours (multiplicative Schwarz); refactorised only when
# that does not reach KRYLOV_TOL within KRYLOV_MAX iterations, or when more than SCHWARZ_MAX_NODES nodes
# changed. docs/decisions/2026-12-06-fe-krylov-stale-factors.md has the measurements.
KRYLOV_TOL = 1e-6           # relative residual |b - A x| <= KRYLOV_TOL |b|, in double precision
KRYLOV_MAX = 12             # GCR iterations before the kept factors are given up (refactorisation)
SCHWARZ_REL = 0.05          # a node's diagonal block "moved" when |dB| > SCHWARZ_REL * max(|B_kept|, |B_now|)
SCHWARZ_RING = 1            # rings of neighbours added to the moved nodes for the local solve
SCHWARZ_MAX_NODES = 500     # more local nodes than this: refactorise instead
# Smaller systems are refactorised every time, as pardiso-mixed: a factorisation costs fewer solves
# there (the 1.2 mm cross-check mesh, 3.5k DOFs: GCR on kept factors 20-30 % slower; the standard gel,
# 11.5k DOFs: faster). A size rule, not a timing, so the path (and the bits) never depend on the machine.
KRYLOV_MIN_DOFS = 8000


def gcr(matvec, precond, b: np.ndarray, tol: float, kmax: int):
    """Preconditioned generalised conjugate residuals: flexible (the preconditioner may be any
    operator), minimal residual, zero initial guess. Each iteration adds a direction z = precond(r)
    with q = A z, both orthogonalised (classical Gram-Schmidt, twice) against the earlier q's, so the
    q's stay orthonormal and A z = q. Returns (x, iterations, converged): iterations = preconditioner
    applications, converged = the true residual |b - A x| <= tol |b| (one product in double precision
    at the end). Deterministic: a fixed order of operations, no random start."""
    n = b.shape[0]
    Zs, Qs = np.zeros((kmax, n)), np.zeros((kmax, n))
    bn = float(np.linalg.norm(b))
    if bn == 0.0:
        return np.zeros(n), 0, True
    x, r = np.zeros(n), b.copy()
    k = 0
    while k < kmax and np.linalg.norm(r) > 0.5 * tol * bn:
        z = precond(r)
        q = matvec(z)
        for _ in range(2):
            h = Qs[:k] @ q
            q -= h @ Qs[:k]
            z -= h @ Zs[:k]
        nq = float(np.linalg.norm(q))
        if not nq > 0.0:
            break
        Qs[k], Zs[k] = q / nq, z / nq
        a = Qs[k] @ r
        x += a * Zs[k]
        r -= a * Qs[k]
        k += 1
    ok = bool(np.all(np.isfinite(x)) and np.linalg.norm(b - matvec(x)) <= tol * bn)
    return x, k, ok


class KrylovFactor(PardisoFactor):
    """Engine "pardiso-krylov": `factor(A)` only records the new tangent; `solve(b)` solves it by
    GCR (`gcr`) preconditioned by the kept single-precision PARDISO factors of an earlier
    tangent, corrected by an exact sparse LU (scipy splu) of the current tangent restricted to the
    nodes whose diagonal 3x3 block moved against the kept one, plus SCHWARZ_RING rings of neighbours
    (the contact set; multiplicative Schwarz: local, global, local). Refactorises (the mixed engine's
    factor + refined solve) where GCR does not reach KRYLOV_TOL within KRYLOV_MAX iterations, or
    where more than SCHWARZ_MAX_NODES nodes are local. Counters beside the parent's:
    `krylov_solves`, `krylov_iterations`, `krylov_failures` (refactorisations after a failed
    GCR), `schwarz_nodes` (sum over Krylov solves). DOFs come in node triplets (3 per node)."""

    def __init__(self, symmetric: bool, threads: int | None = None):
        super().__init__(symmetric, allow_chord=True, threads=threads, mixed=True)
        self.krylov_solves = self.krylov_iterations = self.krylov_failures = self.schwarz_nodes = 0
        self._cur = None          # the latest tangent (double, full CSR)
        self._cur_factored = False
        self._local = None        # (dofs, splu, A[:, L], A[L, :]) of the current tangent
        self._graph = None        # node graph of the pattern (CSR indptr, indices) and diagonal-block positions
        self._kept_blocks = None
        self.trace: list[tuple[str, int, int]] = []   # per solve: ("krylov"|"failed"|"factor", iterations, local nodes)

    def _node_structure(self, A):
        g = self._graph
        if g is not None and ((g[0] is A.indptr and g[1] is A.indices) or
                              (np.array_equal(g[0], A.indptr) and np.array_equal(g[1], A.indices))):
            return g
        n = A.shape[0]
        if n % 3:
            raise FEError("pardiso-krylov: the free DOFs must come in node triplets")
        m = n // 3
        rows = np.repeat(np.arange(n), np.diff(A.indptr))
        nr, nc = rows // 3, A.indices // 3
        key = np.unique(nr.astype(np.int64) * m + nc)
        gptr = np.concatenate([[0], np.cumsum(np.bincount(key // m, minlength=m))])
        gidx = (key % m).astype(np.int64)
        diag = (rows // 3 == A.indices // 3)
        pos = np.flatnonzero(diag)
        if len(pos) != 9 * m:
            raise FEError("pardiso-krylov: every node's diagonal 3x3 block must be in the pattern")
        self._graph = (A.indptr, A.indices, gptr, gidx, pos.reshape(m, 9))
        return self._graph

    def factor(self, A: sp.csr_matrix) -> None:
        A = A.tocsr()
        if not A.has_sorted_indices:
            A.sort_indices()
        self._cur, self._local = A, None
        g = self._node_structure(A)
        p = self._pattern
        if self._A is None or p is None or not ((p[0] is A.indptr and p[1] is A.indices) or (
                np.array_equal(p[0], A.indptr) and np.array_equal(p[1], A.indices))):
            self._refactor()
            return
        if A.shape[0] < KRYLOV_MIN_DOFS:
            self._refactor()
            return
        self._cur_factored = False
        moved = self._moved_nodes(g)
        if moved is None:
            self._refactor()

    def _refactor(self) -> None:
        super().factor(self._cur)
        self._kept_blocks = self._cur.data[self._graph[4]].reshape(-1, 3, 3)
        self._cur_factored, self._local = True, None

    def _moved_nodes(self, g):
        """Local DOFs of the current tangent against the kept factors (None: too many, refactorise)."""
        B = self._cur.data[g[4]].reshape(-1, 3, 3)
        d = np.linalg.norm(B - self._kept_blocks, axis=(1, 2))
        scale = np.maximum(np.linalg.norm(B, axis=(1, 2)), np.linalg.norm(self._kept_blocks, axis=(1, 2)))
        sel = d > SCHWARZ_REL * scale
        gptr, gidx = g[2], g[3]
        for _ in range(SCHWARZ_RING):
            nodes = np.flatnonzero(sel)
            if not len(nodes):
                break
            starts, ends = gptr[nodes], gptr[nodes + 1]
            nb_ = np.concatenate([gidx[s:e] for s, e in zip(starts, ends)])
            sel[nb_] = True
        nodes = np.flatnonzero(sel)
        if len(nodes) > SCHWARZ_MAX_NODES:
            return None
        dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        self._local = dofs
        return dofs

    def _precond(self):
        A = self._cur
        dofs = self._local if self._local is not None else np.zeros(0, np.int64)
        if isinstance(dofs, tuple):
            dofs, lu, acol, arow = dofs
        elif len(dofs):
            sub = A[dofs]
            arow = sub.tocsr()
            lu = sla.splu(sub[:, dofs].tocsc(), permc_spec="MMD_AT_PLUS_A")
            acol = A[:, dofs].tocsr()
            self._local = (dofs, lu, acol, arow)
        kept = self._A

        def glob(v):
            return self._call(33, kept, v.astype(np.float32)).astype(float)

        if not len(dofs):
            return glob

        def schwarz(v):
            xl = lu.solve(v[dofs])
            x = glob(v - acol @ xl)
            x[dofs] += xl
            x[dofs] += lu.solve(v[dofs] - arow @ x)
            return x

        return schwarz

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.ascontiguousarray(b, dtype=float)
        if not self._cur_factored:
            A = self._cur
            try:
                pre = self._precond()
            except RuntimeError:       # a singular local block: the full factorisation decides
                pre = None
            if pre is not None:
                x, its, ok = gcr(A.dot, pre, b, KRYLOV_TOL, KRYLOV_MAX)
                self.krylov_iterations += its
                nloc = len(self._local[0]) // 3 if isinstance(self._local, tuple) else 0
                self.trace.append(("krylov" if ok else "failed", its, nloc))
                if ok:
                    self.krylov_solves += 1
                    self.schwarz_nodes += nloc
                    return x
            self.krylov_failures += 1
            self._refactor()
        else:
            self.trace.append(("factor", 0, 0))
        return super().solve(b)

    def free(self) -> None:
        self._local = None
        super().free()


class SuperLUFactor:
    """scipy SuperLU, symmetric-mode ordering first and partial pivoting as the fallback (the solver's
    original path; every factorisation starts from scratch)."""

    symmetric = False
    allow_chord = False
    chord_steps = refinements = double_fallbacks = 0

    def __init__(self, symmetric: bool = False):
        self._lu = None
        self.analyses = self.factorizations = 0

    def factor(self, A) -> None:
        K = A.tocsc()
        try:
            self._lu = sla.splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                options=dict(SymmetricMode=True))
        except RuntimeError:
            try:
                self._lu = sla.splu(K, permc_spec="COLAMD")
            except RuntimeError as exc:
                raise SingularTangent(f"singular tangent ({exc})") from exc
        self.analyses += 1
        self.factorizations += 1

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._lu.solve(b)

    def free(self) -> None:
        self._lu = None


def make_factor(engine: str, symmetric: bool):
    if engine == "pardiso-mixed":
        return PardisoFactor(symmetric, allow_chord=True, mixed=True)
    if engine == "pardiso-krylov":
        return KrylovFactor(symmetric)
    if engine == "pardiso-reuse":
        return PardisoFactor(symmetric, allow_chord=True)
    if engine == "pardiso":
        return PardisoFactor(symmetric)
    if engine == "superlu":
        return SuperLUFactor(symmetric)
    raise ValueError(f"FE linear solver engine {engine!r}: expected one of {ENGINES}")
