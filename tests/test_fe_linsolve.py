"""Sparse solvers (tools/fe/linsolve.py): PARDISO keeps its symbolic analysis, singular matrices, engines
agree."""
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla

fem = pytest.importorskip("felupe")

from tensortouch.tools.fe.errors import FEError  # noqa: E402
from tensortouch.tools.fe.linsolve import PardisoFactor, SuperLUFactor, mkl_rt  # noqa: E402

try:
    mkl_rt()
except FEError:
    pytest.skip("the train extra's mkl is not installed", allow_module_level=True)


def _spd_like(n=400, seed=0, unsym=0.0):
    rng = np.random.default_rng(seed)
    A = sp.random(n, n, density=0.01, random_state=seed, format="csr")
    A = A + A.T + sp.diags(rng.uniform(5, 6, n))
    if unsym:
        A = A + unsym * sp.random(n, n, density=0.005, random_state=seed + 1)
    A = A.tocsr()
    A.sort_indices()
    return A


@pytest.mark.parametrize("symmetric", [True, False])
def test_pardiso_keeps_the_symbolic_analysis_while_the_pattern_stays(symmetric):
    A = _spd_like(unsym=0.0 if symmetric else 0.3)
    b = np.random.default_rng(2).normal(size=A.shape[0])
    fac = PardisoFactor(symmetric)
    fac.factor(A)
    x = fac.solve(b)
    assert np.allclose(x, sla.spsolve(A.tocsc(), b), rtol=1e-10, atol=1e-12)
    A2 = A.copy()
    A2.data = A2.data * np.linspace(0.9, 1.1, A2.nnz) if not symmetric else A2.data * 1.3
    fac.factor(A2)
    x2 = fac.solve(b)
    assert np.allclose(x2, sla.spsolve(A2.tocsc(), b), rtol=1e-10, atol=1e-12)
    assert (fac.analyses, fac.factorizations) == (1, 2)
    fac.factor(_spd_like(seed=5, unsym=0.0 if symmetric else 0.3))  # another pattern: a new analysis
    assert fac.analyses == 2
    # deterministic: the same sequence of matrices gives the same bits (the analysis of the first
    # matrix, with its scaling and matching, is what the later factorisations reuse)
    f2 = PardisoFactor(symmetric)
    f2.factor(A)
    f2.factor(A2)
    assert np.array_equal(f2.solve(b), x2)


@pytest.mark.parametrize("symmetric", [True, False])
def test_mixed_precision_refines_single_factors_to_the_double_solution(symmetric):
    """Engine pardiso-mixed: single-precision factors (raw solve ~1e-6 off), refined in double to
    |b - A x| <= REFINE_TOL |b|; the same bits with one thread or two."""
    from tensortouch.tools.fe.linsolve import REFINE_TOL

    A = _spd_like(n=600, unsym=0.0 if symmetric else 0.3)
    b = np.random.default_rng(2).normal(size=A.shape[0])
    exact = sla.spsolve(A.tocsc(), b)
    out = []
    for threads in (1, 2):
        fac = PardisoFactor(symmetric, mixed=True, threads=threads)
        fac.factor(A)
        out.append(fac.solve(b))
        assert fac.dtype == np.float32 and fac.refinements >= 1 and fac.double_fallbacks == 0
        raw = fac._call(33, fac._A, b.astype(np.float32)).astype(float)
        assert 1e-9 < np.linalg.norm(A @ raw - b) / np.linalg.norm(b) < 1e-4   # the single solve alone
    assert np.linalg.norm(A @ out[0] - b) <= REFINE_TOL * np.linalg.norm(b)
    assert np.allclose(out[0], exact, rtol=1e-8, atol=1e-12)
    assert out[0].tobytes() == out[1].tobytes()


def test_mixed_precision_falls_back_to_double_factors_when_refinement_stalls(monkeypatch):
    """Where refinement does not reach REFINE_TOL within MAX_REFINE corrections (forced here by
    allowing none: the raw single solve is ~1e-6 off), the double factorisation solves the system,
    the same bits as the double engine, and keeps solving for this matrix (chord steps) until the
    next factor()."""
    from tensortouch.tools.fe import linsolve

    monkeypatch.setattr(linsolve, "MAX_REFINE", 0)
    A = _spd_like(n=400, unsym=0.3)
    b = np.random.default_rng(4).normal(size=A.shape[0])
    fac = PardisoFactor(False, mixed=True)
    fac.factor(A)
    x = fac.solve(b)
    dbl = PardisoFactor(False)
    dbl.factor(A)
    assert fac.double_fallbacks == 1 and x.tobytes() == dbl.solve(b).tobytes()
    fac.solve(b)
    assert fac.double_fallbacks == 1      # the double factors stay for this matrix
    monkeypatch.setattr(linsolve, "MAX_REFINE", 4)
    fac.factor(_spd_like(n=400, seed=1, unsym=0.3))   # the next matrix: single factors again
    fac.solve(b)
    assert fac.double_fallbacks == 1 and fac._fallback is None


def test_singular_matrix_is_a_floating_point_error():
    A = _spd_like(n=50)
    A = A.tolil()
    A[:, 3] = 0.0
    A[3, :] = 0.0
    A[3, 3] = 0.0
    A = A.tocsr()
    A.sort_indices()
    for fac in (SuperLUFactor(), ):
        with pytest.raises(FloatingPointError):
            fac.factor(A)


def _pad_press_slide(mu: float):
    """A small pad pressed 0.6 mm by a R 4 mm sphere, then slid 0.6 mm: (scenario, mesh)."""
    from tensortouch.tools.fe.mesh import mesh_gel
    from tensortouch.tools.fe.scenario import GelGeometry, Indenter, Keypoint, MeshSettings, Scenario

    pad = GelGeometry(kind="flat_pad", size_x=12.0, size_y=12.0, thickness=5.0)
    ms = MeshSettings(size_top=1.2, size_inside=1.5)
    ind = Indenter(name="s", shape="sphere", params={"radius": 4.0}, position=[0.0, 0.0, 5.0],
                   keypoints=[Keypoint(list(t), [0.0, 0.0, 0.0]) for t in [(0, 0, -0.6), (0.6, 0, -0.6)]])
    return Scenario(gel=pad, mesh=ms, indenters=[ind], friction=mu), mesh_gel(pad, ms)


@pytest.mark.parametrize("mu", [0.0, 0.4])
def test_engines_give_the_same_solve_and_pardiso_repeats_bit_for_bit(mu):
    """A press-and-slide on a small pad: the reference engine (felupe + SuperLU) and the default one
    (own assembly + PARDISO, symmetric type when mu = 0) reach the same iterates; two runs of the
    default engine give identical bits (the FE cache and the recipe's data hash rely on it)."""
    import json

    from tensortouch.tools.fe import solve

    sc, gm = _pad_press_slide(mu)
    ref = solve(sc, mesh=gm, engine="superlu")
    new = solve(sc, mesh=gm, engine="pardiso")
    again = solve(sc, mesh=gm, engine="pardiso")
    info = json.loads(new.solver_info)
    assert info["engine"] == "pardiso" and info["symmetric_tangent"] == (mu == 0.0)
    assert info["symbolic_analyses"] == 1 and info["factorizations"] == info["iterations"]
    assert json.loads(ref.solver_info)["iterations"] == info["iterations"]
    assert np.allclose(new.RF, ref.RF, rtol=1e-9, atol=1e-12) and np.allclose(new.U, ref.U, atol=1e-10)
    assert np.array_equal(again.RF, new.RF) and np.array_equal(again.U, new.U)
    if mu == 0.0:  # no friction: only the plowing slope of the pressed surface pushes back in x
        assert abs(new.RF[-1, 0, 0]) < 0.03 * abs(new.RF[-1, 0, 2])


@pytest.mark.parametrize("mu", [0.0, 0.4])
def test_chord_steps_reuse_the_factorisation_converge_alike_and_repeat_bit_for_bit(mu):
    """Engine pardiso-reuse: where a Newton step has cut the residual tenfold, the next
    correction reuses the kept factorisation (a chord step). It refactorises less than once per
    iteration, reaches the exact-Newton engine's forces within the Newton tolerance, and two runs give
    the same bits."""
    import json

    from tensortouch.tools.fe import solve

    sc, gm = _pad_press_slide(mu)
    exact = solve(sc, mesh=gm, engine="pardiso")
    chord = solve(sc, mesh=gm, engine="pardiso-reuse")
    again = solve(sc, mesh=gm, engine="pardiso-reuse")
    info = json.loads(chord.solver_info)
    assert info["engine"] == "pardiso-reuse" and info["chord_steps"] > 0
    assert info["factorizations"] + info["chord_steps"] == info["iterations"]
    assert json.loads(exact.solver_info)["chord_steps"] == 0
    scale = np.abs(exact.RF).max()
    assert np.abs(chord.RF - exact.RF).max() <= 1e-4 * scale   # the Newton tolerance, not rounding
    assert np.array_equal(again.RF, chord.RF) and np.array_equal(again.U, chord.U)


@pytest.mark.parametrize("mu", [0.0, 0.4])
def test_mixed_precision_engine_takes_the_same_newton_path_and_repeats_bit_for_bit(mu, monkeypatch):
    """Engine pardiso-mixed: the same iterations, factorisations and chord steps as
    pardiso-reuse, forces to rounding of the refined solves (not the Newton tolerance), and the same
    bits on a rerun and with two threads (PARDISO's reproducible mode and the fixed assembly parts)."""
    import json

    from tensortouch.tools.fe import linsolve, solve

    sc, gm = _pad_press_slide(mu)
    dbl = solve(sc, mesh=gm, engine="pardiso-reuse")
    mixed = solve(sc, mesh=gm, engine="pardiso-mixed")
    monkeypatch.setattr(linsolve, "THREADS", 2)
    two = solve(sc, mesh=gm, engine="pardiso-mixed")
    a, b = json.loads(dbl.solver_info), json.loads(mixed.solver_info)
    assert b["engine"] == "pardiso-mixed" and b["refinements"] > 0 and b["double_fallbacks"] == 0
    for key in ("iterations", "factorizations", "chord_steps", "increments"):
        assert a[key] == b[key], key
    scale = np.abs(dbl.RF).max()
    assert np.abs(mixed.RF - dbl.RF).max() <= 1e-7 * scale
    assert np.array_equal(two.RF, mixed.RF) and np.array_equal(two.U, mixed.U)


def test_one_thread_and_two_give_the_same_bits():
    """PARDISO's reproducible mode (iparm[33]): the thread count is a speed setting only, so FE results
    (and the cache keys that hash them) do not depend on TENSORTOUCH_FE_THREADS. A 3D grid Laplacian
    with an unsymmetric part, large enough for the factorisation to split across threads."""
    n = 22
    lap1 = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n))
    eye = sp.identity(n)
    A = (sp.kron(sp.kron(lap1, eye), eye) + sp.kron(sp.kron(eye, lap1), eye) + sp.kron(sp.kron(eye, eye), lap1))
    A = (A + 0.05 * sp.diags(np.linspace(-1, 1, n ** 3 - 1), 1) + 0.1 * sp.identity(n ** 3)).tocsr()
    A.sort_indices()
    b = np.random.default_rng(3).normal(size=A.shape[0])
    out = []
    for threads in (1, 2, 1):
        fac = PardisoFactor(False, threads=threads)
        fac.factor(A)
        out.append(fac.solve(b))
        fac.free()
    assert np.abs(A @ out[0] - b).max() < 1e-9
    assert out[0].tobytes() == out[1].tobytes() == out[2].tobytes()


def test_the_thread_count_comes_from_the_environment_and_bad_values_name_it(monkeypatch):
    from tensortouch.tools.fe import linsolve

    monkeypatch.setattr(linsolve, "THREADS", None)
    monkeypatch.delenv("TENSORTOUCH_FE_THREADS", raising=False)
    assert linsolve.thread_count() == 1
    monkeypatch.setenv("TENSORTOUCH_FE_THREADS", "2")
    assert linsolve.thread_count() == 2 and PardisoFactor(False).threads == 2
    for bad in ("0", "two"):
        monkeypatch.setenv("TENSORTOUCH_FE_THREADS", bad)
        with pytest.raises(FEError, match="TENSORTOUCH_FE_THREADS"):
            linsolve.thread_count()


# -- engine pardiso-krylov: GCR on kept (stale) single-precision factors, local Schwarz correction --------

def _node_matrix(side=12, seed=0, unsym=0.0):
    """A 3-DOF-per-node matrix on a side x side grid of nodes (every node's 3x3 diagonal block in the
    pattern, as the FE tangent): grid Laplacian (x) an SPD 3x3 block, plus a small unsymmetric part."""
    rng = np.random.default_rng(seed)
    lap1 = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(side, side))
    eye = sp.identity(side)
    lap = sp.kron(lap1, eye) + sp.kron(eye, lap1) + 0.05 * sp.identity(side * side)
    B0 = np.array([[2.0, 0.3, 0.1], [0.3, 1.5, 0.2], [0.1, 0.2, 1.0]])
    A = sp.kron(lap, B0).tocsr()
    if unsym:
        A = A + unsym * sp.kron(sp.diags([1.0, -1.0], [1, -1], shape=(side * side, side * side)),
                                rng.normal(size=(3, 3)))
    A = A.tocsr()
    A.sum_duplicates()
    A.sort_indices()
    return A


def _with_block_jump(A, nodes, scale):
    """A with `scale` times a contact-like 3x3 block added on the diagonal of each node in `nodes`
    (a node entering contact: its penalty is far stiffer than the gel around it)."""
    A = A.tolil()
    for k in nodes:
        for i in range(3):
            A[3 * k + i, 3 * k + i] += scale * (1.0 + 0.1 * i)
        A[3 * k, 3 * k + 2] += 0.3 * scale     # unsymmetric, as a slipping node's friction block
    A = A.tocsr()
    A.sort_indices()
    return A


def test_gcr_reaches_the_tolerance_with_a_stale_preconditioner_and_repeats_bit_for_bit():
    from tensortouch.tools.fe.linsolve import gcr

    A = _node_matrix(unsym=0.2)
    stale = PardisoFactor(False, mixed=True)
    stale.factor((A * 1.0 + 0.3 * sp.identity(A.shape[0])).tocsr())   # an earlier tangent, 10-20 % off

    def pre(v):
        return stale._call(33, stale._A, v.astype(np.float32)).astype(float)

    b = np.random.default_rng(1).normal(size=A.shape[0])
    x, its, ok = gcr(A.dot, pre, b, 1e-10, 40)
    assert ok and 1 < its < 40
    assert np.linalg.norm(b - A @ x) <= 1e-10 * np.linalg.norm(b)
    x2, its2, _ = gcr(A.dot, pre, b, 1e-10, 40)
    assert its2 == its and x2.tobytes() == x.tobytes()
    # the exact preconditioner: one iteration to the single factors' accuracy
    fresh = PardisoFactor(False)
    fresh.factor(A)
    _, its1, ok1 = gcr(A.dot, fresh.solve, b, 1e-10, 5)
    assert ok1 and its1 == 1
    # too few iterations allowed: not converged, and says so (the caller refactorises)
    _, its3, ok3 = gcr(A.dot, pre, b, 1e-14, 2)
    assert not ok3 and its3 == 2
    assert gcr(A.dot, pre, np.zeros_like(b), 1e-10, 5)[1:] == (0, True)


@pytest.mark.parametrize("symmetric", [True, False])
def test_krylov_factor_keeps_its_factors_while_the_local_correction_absorbs_a_contact_change(symmetric, monkeypatch):
    """A later tangent with a few nodes' diagonal blocks jumped 50x (contact) and the rest a little
    changed: solved by GCR on the kept factors with no refactorisation; the moved nodes and their
    neighbours are the local (Schwarz) set; the answer within KRYLOV_TOL; the same bits again."""
    from tensortouch.tools.fe import linsolve
    from tensortouch.tools.fe.linsolve import KrylovFactor

    monkeypatch.setattr(linsolve, "KRYLOV_MIN_DOFS", 0)
    A = _node_matrix(unsym=0.0 if symmetric else 0.2)
    A2 = _with_block_jump((A * 1.02).tocsr(), [40, 41, 77], 50.0)
    if symmetric:
        A2 = ((A2 + A2.T) * 0.5).tocsr()
        A2.sort_indices()
    b = np.random.default_rng(2).normal(size=A.shape[0])
    out = []
    for _ in range(2):
        fac = KrylovFactor(symmetric)
        fac.factor(A)
        fac.solve(b)
        fac.factor(A2)
        x = fac.solve(b)
        assert fac.factorizations == 1 and fac.krylov_solves == 1 and fac.krylov_failures == 0
        kind, its, nloc = fac.trace[-1]
        assert kind == "krylov" and its <= linsolve.KRYLOV_MAX and 3 <= nloc < A.shape[0] // 3
        assert np.linalg.norm(b - A2 @ x) <= linsolve.KRYLOV_TOL * np.linalg.norm(b)
        x_chord = fac.solve(2.0 * b)     # a chord step: the same tangent, no factor() in between
        assert np.linalg.norm(2.0 * b - A2 @ x_chord) <= linsolve.KRYLOV_TOL * 2.0 * np.linalg.norm(b)
        out.append(x)
    assert out[0].tobytes() == out[1].tobytes()


def test_krylov_factor_refactorises_when_gcr_fails_or_too_many_nodes_moved(monkeypatch):
    from tensortouch.tools.fe import linsolve
    from tensortouch.tools.fe.linsolve import KrylovFactor

    monkeypatch.setattr(linsolve, "KRYLOV_MIN_DOFS", 0)
    A = _node_matrix(unsym=0.2)
    wobble = sp.diags(0.04 * A.diagonal() * np.random.default_rng(5).uniform(size=A.shape[0]))  # < SCHWARZ_REL
    A2 = _with_block_jump((A + wobble).tocsr(), [10, 60], 20.0)
    b = np.random.default_rng(3).normal(size=A.shape[0])
    # GCR allowed one iteration only: it fails, the tangent is refactorised and solved (refined)
    monkeypatch.setattr(linsolve, "KRYLOV_MAX", 1)
    fac = KrylovFactor(False)
    fac.factor(A)
    fac.factor(A2)
    x = fac.solve(b)
    assert fac.krylov_failures == 1 and fac.factorizations == 2 and fac.trace[-1][0] == "failed"
    assert np.linalg.norm(b - A2 @ x) <= linsolve.REFINE_TOL * np.linalg.norm(b)
    # the refactorised tangent is now the kept one: its chord step is a plain refined solve
    fac.solve(b)
    assert fac.trace[-1][0] == "factor" and fac.factorizations == 2
    # more moved nodes than SCHWARZ_MAX_NODES: refactorised at factor(), not counted as a failure
    monkeypatch.setattr(linsolve, "KRYLOV_MAX", 12)
    monkeypatch.setattr(linsolve, "SCHWARZ_MAX_NODES", 1)
    fac2 = KrylovFactor(False)
    fac2.factor(A)
    fac2.factor(A2)
    fac2.solve(b)
    assert fac2.factorizations == 2 and fac2.krylov_failures == 0 and fac2.krylov_solves == 0


@pytest.mark.parametrize("mu", [0.0, 0.4])
def test_krylov_engine_takes_the_mixed_engines_newton_path_and_repeats_bit_for_bit(mu, monkeypatch):
    """Engine pardiso-krylov (the default) on the pad press-and-slide: the same increments, Newton iterations and
    chord steps as pardiso-mixed, fewer factorisations (Krylov solves on kept factors instead), forces
    within 1e-6 of pardiso-mixed's (the linear solves are converged to KRYLOV_TOL, not the Newton
    tolerance), and the same bits on a rerun and with two threads."""
    import json

    from tensortouch.tools.fe import linsolve, solve
    from tensortouch.tools.fe.solver import DEFAULT_ENGINE

    assert DEFAULT_ENGINE == "pardiso-krylov" or "TENSORTOUCH_FE_ENGINE" in __import__("os").environ
    sc, gm = _pad_press_slide(mu)
    monkeypatch.setattr(linsolve, "KRYLOV_MIN_DOFS", 0)     # the pad is small: Krylov solves anyway
    mixed = solve(sc, mesh=gm, engine="pardiso-mixed")
    kry = solve(sc, mesh=gm, engine="pardiso-krylov")
    again = solve(sc, mesh=gm, engine="pardiso-krylov")
    monkeypatch.setattr(linsolve, "THREADS", 2)
    two = solve(sc, mesh=gm, engine="pardiso-krylov")
    a, b = json.loads(mixed.solver_info), json.loads(kry.solver_info)
    assert b["engine"] == "pardiso-krylov" and b["krylov_solves"] > 0 and b["krylov_iterations"] >= b["krylov_solves"]
    for key in ("iterations", "chord_steps", "increments", "cutbacks"):
        assert a[key] == b[key], key
    assert b["factorizations"] < a["factorizations"]
    scale = np.abs(mixed.RF).max()
    assert np.abs(kry.RF - mixed.RF).max() <= 1e-6 * scale
    assert np.array_equal(again.RF, kry.RF) and np.array_equal(again.U, kry.U)
    assert np.array_equal(two.RF, kry.RF) and np.array_equal(two.U, kry.U)


def test_krylov_engine_refactorises_small_systems_like_the_mixed_engine():
    """Below KRYLOV_MIN_DOFS a factorisation costs few solves: pardiso-krylov refactorises each tangent,
    the same bits as pardiso-mixed."""
    import json

    from tensortouch.tools.fe import linsolve, solve

    sc, gm = _pad_press_slide(0.4)
    assert 3 * len(gm.nodes) < linsolve.KRYLOV_MIN_DOFS
    mixed = solve(sc, mesh=gm, engine="pardiso-mixed")
    kry = solve(sc, mesh=gm, engine="pardiso-krylov")
    a, b = json.loads(mixed.solver_info), json.loads(kry.solver_info)
    assert b["krylov_solves"] == 0 and b["factorizations"] == a["factorizations"]
    assert np.array_equal(kry.RF, mixed.RF) and np.array_equal(kry.U, mixed.U)
