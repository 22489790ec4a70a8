"""tools.fe.assembly (P1 Yeoh forces and tangent on a fixed pattern) against felupe's assembly of the
same closed-form material, and tools.fe.linsolve (PARDISO with the symbolic analysis kept) against
scipy on small matrices built here."""
import numpy as np
import pytest
import scipy.sparse as sp

fem = pytest.importorskip("felupe")

from tensortouch.tools.fe.assembly import P1Assembly  # noqa: E402
from tensortouch.tools.fe.errors import FEError  # noqa: E402
from tensortouch.tools.fe.linsolve import mkl_rt  # noqa: E402
from tensortouch.tools.fe.materials import YeohUmat  # noqa: E402

try:
    mkl_rt()
except FEError:
    pytest.skip("the train extra's mkl is not installed", allow_module_level=True)


def _tet_mesh(n=4, seed=0):
    """Jittered grid of a unit-ish block, Delaunay tets oriented to positive volume."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(*[np.linspace(0, 3, n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    g[:, :2] += rng.normal(0, 0.08, (len(g), 2)) * ((g[:, :2] > 0) & (g[:, :2] < 3))
    tets = Delaunay(g).simplices.copy()
    x = g[tets]
    vol = np.einsum("ci,ci->c", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])
    tets = tets[np.abs(vol) > 0.05]  # no slivers
    flip = np.einsum("ci,ci->c", np.cross(g[tets[:, 1]] - g[tets[:, 0]], g[tets[:, 2]] - g[tets[:, 0]]),
                     g[tets[:, 3]] - g[tets[:, 0]]) < 0
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]
    return g, tets


def _felupe_and_fast(nodes, tets, umat):
    mesh = fem.Mesh(nodes, tets, "tetra")
    region = fem.RegionTetra(mesh)
    u = fem.Field(region, dim=3)
    field = fem.FieldContainer([u])
    solid = fem.SolidBody(umat, field)
    fixed_nodes = np.flatnonzero(nodes[:, 2] < 1e-9)
    fixed = (3 * fixed_nodes[:, None] + np.arange(3)).ravel()
    free = np.setdiff1d(np.arange(3 * len(nodes)), fixed)
    top = np.flatnonzero(nodes[:, 2] > 3 - 1e-9)
    surf_dofs = (3 * top[:, None] + np.arange(3)).ravel()
    B = np.asarray(region.dhdX)[:, :, 0, :].transpose(2, 0, 1)
    fast = P1Assembly(tets, len(nodes), free, surf_dofs, B, np.asarray(region.dV)[0])
    return u, field, solid, free, top, surf_dofs, fast


@pytest.mark.parametrize("bulk", [0.0, 0.5])
def test_p1_forces_and_tangent_match_felupe(bulk):
    nodes, tets = _tet_mesh()
    umat = YeohUmat(0.03, 0.002, 0.0002, bulk)
    u, field, solid, free, top, surf_dofs, fast = _felupe_and_fast(nodes, tets, umat)
    rng = np.random.default_rng(1)
    x, y, z = nodes.T / 3
    U = np.stack([0.3 * z * np.sin(2 * x), 0.2 * z * y, -0.4 * z ** 2], 1)  # tens of % strain, base fixed
    U += rng.normal(0, 0.01, nodes.shape) * z[:, None]
    u.values[:] = U
    f_ref = np.asarray(solid.assemble.vector(field).todense()).ravel()
    K_ref = solid.assemble.matrix(field).tocsr()
    Kc = rng.normal(0, 0.01, (len(top), 3, 3))
    rows = np.repeat(surf_dofs.reshape(-1, 3), 3, axis=1).ravel()
    cols = np.tile(surf_dofs.reshape(-1, 3), (1, 3)).ravel()
    K_ref = (K_ref - sp.csr_matrix((Kc.ravel(), (rows, cols)), shape=K_ref.shape))[free][:, free].toarray()
    f, data = fast.forces_and_tangent(U, umat, Kc)
    K = fast.matrix(data).toarray()
    assert np.abs(f - f_ref).max() <= 1e-12 * np.abs(f_ref).max() * 10
    assert np.abs(fast.forces(U, umat) - f).max() == 0.0
    assert np.abs(K - K_ref).max() <= 1e-11 * np.abs(K_ref).max()
    # the fixed pattern holds every element and contact entry, and a second call gives the same bits
    assert fast.matrix(data).nnz == fast.nnz
    assert np.array_equal(fast.forces_and_tangent(U, umat, Kc)[1], data)


def test_two_assembly_threads_give_the_same_bits(monkeypatch):
    """The cells are assembled in PARTS fixed parts summed in order, so two threads (the parts at once)
    give the bits of one, and the contact blocks are added once."""
    from tensortouch.tools.fe import assembly, linsolve

    nodes, tets = _tet_mesh()
    umat = YeohUmat(0.03, 0.002, 0.0002, 0.5)
    *_, top, surf_dofs, fast = _felupe_and_fast(nodes, tets, umat)
    assert assembly.PARTS >= 2 and fast.bounds[0] == 0 and fast.bounds[-1] == len(tets)
    rng = np.random.default_rng(2)
    x, y, z = nodes.T / 3
    U = np.stack([0.3 * z * np.sin(2 * x), 0.2 * z * y, -0.4 * z ** 2], 1)
    Kc = rng.normal(0, 0.01, (len(top), 3, 3))
    out = {}
    for threads in (1, 2):
        monkeypatch.setattr(linsolve, "THREADS", threads)
        out[threads] = (fast.forces(U, umat), *fast.forces_and_tangent(U, umat, Kc))
    assert all(a.tobytes() == b.tobytes() for a, b in zip(out[1], out[2]))
    _, no_contact = fast.forces_and_tangent(U, umat, np.zeros_like(Kc))
    # the contact blocks enter once, with a minus sign: their sum is the difference of the traces
    assert np.isclose(no_contact.sum() - out[1][2].sum(), Kc.sum(), rtol=1e-9, atol=1e-12)


def test_a_turn_of_the_motion_starts_with_a_shorter_increment(monkeypatch):
    """Press then slide on a small pad: where the motion turns the first increment is shortened to
    TURN_INCREMENT_FRACTION (one increment more than plain stepping, recorded in solver_info), and
    the forces are those of plain stepping (a shorter step, not another model)."""
    import json

    from tensortouch.tools.fe import solver
    from tensortouch.tools.fe.mesh import mesh_gel
    from tensortouch.tools.fe.scenario import GelGeometry, Indenter, Keypoint, MeshSettings, Scenario

    pad = GelGeometry(kind="flat_pad", size_x=12.0, size_y=12.0, thickness=5.0)
    ms = MeshSettings(size_top=1.2, size_inside=1.5)
    ind = Indenter(name="s", shape="sphere", params={"radius": 4.0}, position=[0.0, 0.0, 5.0],
                   keypoints=[Keypoint(list(t), [0.0, 0.0, 0.0]) for t in [(0, 0, -0.6), (0.45, 0, -0.6)]])
    sc = Scenario(gel=pad, mesh=ms, indenters=[ind], friction=0.6)
    gm = mesh_gel(pad, ms)
    monkeypatch.setattr(solver, "TURN_INCREMENT_FRACTION", 1.0)
    plain = solver.solve(sc, mesh=gm)
    monkeypatch.setattr(solver, "TURN_INCREMENT_FRACTION", 0.5)
    turned = solver.solve(sc, mesh=gm)
    a, b = json.loads(plain.solver_info), json.loads(turned.solver_info)
    assert b["turn_increment_fraction"] == 0.5 and b["increments"] == a["increments"] + 1
    assert np.array_equal(turned.RF[0], plain.RF[0])                      # the press is stepped as before
    assert np.linalg.norm(turned.RF[-1] - plain.RF[-1]) < 2e-3 * np.linalg.norm(plain.RF[-1])
