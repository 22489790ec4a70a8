"""tools.fe core: element forces/tangents against an independent energy, and contact (fast, no full
solves)."""
import numpy as np
import pytest

pytest.importorskip("felupe")

from tensortouch.tools.fe import contact as fc  # noqa: E402
from tensortouch.tools.fe.indenters import Sphere, rotmat  # noqa: E402
from tensortouch.tools.fe.materials import YeohUmat  # noqa: E402
from tensortouch.tools.fe.mesh import box_mesh  # noqa: E402
from tensortouch.tools.fe.scenario import Material  # noqa: E402

# ---------------------------------------------------------------- element forces


def _p1_energy(nodes, tets, U, m: Material, bulk):
    """Independent numpy P1 strain energy (no felupe): sum_e W(F_e) V_e."""
    X = nodes[tets]
    x = X + U[tets]
    DX = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)
    Dx = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)
    F = Dx @ np.linalg.inv(DX)
    V = np.abs(np.linalg.det(DX)) / 6
    J = np.linalg.det(F)
    d = J ** (-2 / 3) * np.einsum("eij,eij->e", F, F) - 3
    W = m.C10 * d + m.C20 * d ** 2 + m.C30 * d ** 3 + bulk / 2 * (J - 1) ** 2
    return float((W * V).sum())


def test_element_forces_and_tangent_against_independent_energy():
    import felupe as fem

    gm = box_mesh((4.0, 3.0, 2.0), (3, 2, 2))
    m = Material()
    region = fem.RegionTetra(fem.Mesh(gm.nodes, gm.tets, "tetra"))
    u = fem.Field(region, dim=3)
    field = fem.FieldContainer([u])
    solid = fem.SolidBody(YeohUmat(m.C10, m.C20, m.C30, 3.0), field)
    rng = np.random.default_rng(3)
    U = 0.15 * rng.normal(size=gm.nodes.shape)
    u.values[:] = U
    f = np.asarray(solid.assemble.vector(field).todense()).ravel()
    K = solid.assemble.matrix(field).toarray()
    h = 1e-6
    for dof in rng.choice(U.size, 8, replace=False):  # force = dEnergy/du (central differences)
        Up, Um = U.copy(), U.copy()
        Up.reshape(-1)[dof] += h
        Um.reshape(-1)[dof] -= h
        g = (_p1_energy(gm.nodes, gm.tets, Up, m, 3.0) - _p1_energy(gm.nodes, gm.tets, Um, m, 3.0)) / (2 * h)
        assert g == pytest.approx(f[dof], rel=1e-5, abs=1e-9)
    v = rng.normal(size=U.size)  # tangent = dForce/du along a random direction
    u.values[:] = U + 1e-6 * v.reshape(-1, 3)
    fp = np.asarray(solid.assemble.vector(field).todense()).ravel()
    u.values[:] = U - 1e-6 * v.reshape(-1, 3)
    fm = np.asarray(solid.assemble.vector(field).todense()).ravel()
    assert np.abs((fp - fm) / 2e-6 - K @ v).max() < 1e-6 * np.abs(K @ v).max()


# ---------------------------------------------------------------- contact
def _contact_fd(mu, anchors_shift, ratio=0.1):
    rng = np.random.default_rng(5)
    shape = Sphere(4.0)
    R = rotmat([0.1, -0.2, 0.3])
    p = np.array([0.2, -0.1, 0.0])
    xi = rng.uniform(-1.5, 1.5, size=(30, 3))
    xi[:, 2] = 4.0 - np.sqrt(16 - xi[:, 0] ** 2 - xi[:, 1] ** 2) + rng.uniform(0.01, 0.1, 30)  # inside
    x = xi @ R.T + p
    area = rng.uniform(0.2, 0.5, 30)
    st = fc.ContactState.empty(1, x)
    ce = fc.evaluate(x, area, [shape], [(p, R)], st, 5.0, mu, tangential_ratio=ratio)
    st = fc.ContactState(ce.new_anchors + anchors_shift, x - 0.01)
    ce = fc.evaluate(x, area, [shape], [(p, R)], st, 5.0, mu, tangential_ratio=ratio)
    h = 1e-7
    err = 0.0
    for a in range(len(x)):
        for j in range(3):
            xp, xm = x.copy(), x.copy()
            xp[a, j] += h
            xm[a, j] -= h
            fp = fc.evaluate(xp, area, [shape], [(p, R)], st, 5.0, mu, tangential_ratio=ratio)
            fm = fc.evaluate(xm, area, [shape], [(p, R)], st, 5.0, mu, tangential_ratio=ratio)
            col = ((fp.fn + fp.ft) - (fm.fn + fm.ft))[a] / (2 * h)
            err = max(err, np.abs(col - ce.K[a][:, j]).max() / np.abs(ce.K[a]).max())
    return ce, err


def test_contact_tangent_exact_frictionless_and_slip():
    ce, err = _contact_fd(0.0, 0.0)
    assert (ce.gap < 0).all() and np.allclose(ce.ft, 0) and err < 1e-5
    ce, err = _contact_fd(0.3, 0.5)  # large anchor offset -> every node slips
    assert ce.slip.all() and err < 1e-5
    mags = np.linalg.norm(ce.ft, axis=1)
    assert np.allclose(mags, 0.3 * np.linalg.norm(ce.fn, axis=1))


def test_contact_tangent_exact_stick():
    ce, err = _contact_fd(2.2, 0.002)
    assert not ce.slip.any() and err < 1e-5


def test_contact_tangent_without_normal_curvature():
    """`normal_curvature=False` (the Newton matrix of an increment's first iterates, tools.fe.solver):
    the same forces, and the frictionless tangent is -eps n n — by hand at a sphere's tip, where the
    exact one adds the curvature term -eps d (I - n n) / R, a negative tangential stiffness."""
    shape, R, p = Sphere(4.0), np.eye(3), np.zeros(3)
    x = np.array([[0.0, 0.0, 0.2]])                 # 0.2 mm inside the tip of the 4 mm sphere
    area, pen = np.array([0.5]), 5.0
    st = fc.ContactState.empty(1, x)
    exact = fc.evaluate(x, area, [shape], [(p, R)], st, pen, 0.0)
    plain = fc.evaluate(x, area, [shape], [(p, R)], st, pen, 0.0, normal_curvature=False)
    np.testing.assert_array_equal(plain.fn, exact.fn)
    eps, d = pen * 0.5, -0.2
    n = np.array([0.0, 0.0, -1.0])                  # outward normal of the sphere at its tip (towards the gel)
    assert np.allclose(plain.fn[0], -eps * d * n)
    assert np.allclose(plain.K[0], -eps * np.outer(n, n))
    assert np.allclose(exact.K[0], -eps * (np.outer(n, n) + d * (np.eye(3) - np.outer(n, n)) / (4.0 + d)))
    ce_f = fc.evaluate(x, area, [shape], [(p, R)], st, pen, 0.4, normal_curvature=False)
    ce_e = fc.evaluate(x, area, [shape], [(p, R)], st, pen, 0.4)
    np.testing.assert_array_equal(ce_f.fn + ce_f.ft, ce_e.fn + ce_e.ft)


def test_contact_slip_hold_keeps_near_limit_nodes_slipping_only():
    """A held node slips while its trial force is within HOLD_BAND of the Coulomb limit; outside the
    band, or without a hold, the law is the plain return mapping."""
    shape, R, p = Sphere(4.0), np.eye(3), np.zeros(3)
    x = np.array([[0.0, 0.0, 0.05], [0.3, 0.0, 0.05], [0.6, 0.0, 0.05]])   # 0.05 mm inside the sphere's tip
    area, pen, mu, ratio = np.full(3, 0.3), 5.0, 0.5, 0.1
    d, _ = shape.sdf(x)
    lim_over_k = mu * (-d) / ratio                 # tangential offset at which the trial reaches the limit
    frac = np.array([0.97, 0.90, 1.02])            # in the band, below it, beyond the limit
    anchors = x.copy()
    anchors[:, 1] -= frac * lim_over_k             # offsets along y (tangent at the tip)
    st = fc.ContactState(anchors[None], x)
    plain = fc.evaluate(x, area, [shape], [(p, R)], st, pen, mu, tangential_ratio=ratio)
    assert plain.slip[0].tolist() == [False, False, True]
    held = fc.evaluate(x, area, [shape], [(p, R)], st, pen, mu, tangential_ratio=ratio,
                       hold=np.ones((1, 3), bool))
    assert held.slip[0].tolist() == [True, False, True]
    lim = mu * np.linalg.norm(plain.fn, axis=1)
    assert np.isclose(np.linalg.norm(held.ft[0]), lim[0])           # at the limit, ...
    assert np.linalg.norm(held.ft[0] - plain.ft[0]) <= fc.HOLD_BAND * lim[0]   # ... within the band of the plain law
    np.testing.assert_array_equal(held.ft[1:], plain.ft[1:])
    none = fc.evaluate(x, area, [shape], [(p, R)], st, pen, mu, tangential_ratio=ratio,
                       hold=np.zeros((1, 3), bool))
    np.testing.assert_array_equal(none.ft, plain.ft)
