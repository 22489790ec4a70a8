"""tools.fe: contracts, materials, element forces/tangents, contact, shapes (fast, no full solves)."""
import json

import numpy as np
import pytest

pytest.importorskip("felupe")

from tensortouch.tools.fe import (  # noqa: E402
    FEResultError,
    ScenarioError,
    load_result,
    load_scenario,
    save_result,
    save_scenario,
    standard_dome,
)
from tensortouch.tools.fe import contact as fc  # noqa: E402
from tensortouch.tools.fe.indenters import BoxEdge, Cylinder, Flat, MeshShape, Sphere, Torus, pose_at, rotmat  # noqa: E402
from tensortouch.tools.fe.materials import YeohUmat, felupe_reference_umat  # noqa: E402
from tensortouch.tools.fe.mesh import box_mesh  # noqa: E402
from tensortouch.tools.fe.scenario import Material, scenario_from_dict  # noqa: E402


# ---------------------------------------------------------------- scenario contract
def test_scenario_json_toml_roundtrip(tmp_path):
    s = standard_dome()
    path = save_scenario(s, tmp_path / "s.json")
    s2 = load_scenario(path)
    assert s2.hash() == s.hash()
    toml = """schema = "tensortouch.fe_scenario"
schema_version = 1
friction = 0.5
[gel]
kind = "flat_pad"
thickness = 10.0
[material]
model = "mooney_rivlin"
C10 = 0.02
C01 = 0.005
[[indenters]]
name = "a"
shape = "torus"
params = { major_radius = 4.0, minor_radius = 1.0 }
position = [0.0, 0.0, 10.5]
[[indenters.keypoints]]
translation = [0.0, 0.0, -1.0]
"""
    (tmp_path / "t.toml").write_text(toml)
    t = load_scenario(tmp_path / "t.toml")
    assert t.material.model == "mooney_rivlin" and t.indenters[0].keypoints[0].rotation == [0, 0, 0]
    assert t.hash() != s.hash()


@pytest.mark.parametrize("patch, field", [
    ({"material": {"C10": -0.1}}, "material.C10"),
    ({"material": {"D1": 0.0}}, "material.D1"),
    ({"material": {"C10": 0.03, "C30": -1.0}}, "material.C30"),
    ({"material": {"model": "ogden"}}, "material.model"),
    ({"gel": {"kind": "cube"}}, "gel.kind"),
    ({"gel": {"radius": 5.0, "cap_height": 9.0}}, "gel.cap_height"),
    ({"mesh": {"size_top": 3.0, "size_inside": 2.0}}, "mesh.size_top"),
    ({"friction": -1.0}, "friction"),
    ({"gel": {"colour": "red"}}, "unknown field"),
])
def test_bad_scenarios_name_the_field(patch, field):
    data = json.loads(standard_dome().to_json())
    for key, value in patch.items():
        if isinstance(value, dict):
            data[key].update(value)
        else:
            data[key] = value
    with pytest.raises(ScenarioError, match=field.replace(".", r"\.")):
        scenario_from_dict(data)


def test_bad_indenters_rejected():
    data = json.loads(standard_dome().to_json())
    data["indenters"][0]["params"] = {}
    with pytest.raises(ScenarioError, match="missing 'radius'"):
        scenario_from_dict(data)
    data = json.loads(standard_dome().to_json())
    second = dict(data["indenters"][0], name="b", keypoints=data["indenters"][0]["keypoints"][:2])
    data["indenters"].append(second)
    with pytest.raises(ScenarioError, match="same number"):
        scenario_from_dict(data)
    data = json.loads(standard_dome().to_json())
    data["indenters"][0].update(shape="mesh", mesh_path="nope.stl")
    with pytest.raises(ScenarioError, match="file not found"):
        scenario_from_dict(data)


def test_pose_interpolation_about_reference_point():
    ind = standard_dome().indenters[0]
    ind.keypoints[0].rotation = [0.0, 0.0, 0.2]
    p_init, r_init = pose_at(ind, -1.0)
    p0, r0 = pose_at(ind, 0.0)
    ph, rh = pose_at(ind, -0.5)
    assert np.allclose(p_init, ind.position) and np.allclose(r_init, 0)
    assert np.allclose(p0, np.add(ind.position, ind.keypoints[0].translation))
    assert np.allclose(rh, [0, 0, 0.1]) and np.allclose(ph, (p_init + p0) / 2)


# ---------------------------------------------------------------- result contract
def _fake_result(F=2, N=5, K=1, converged=True):
    from tensortouch.tools.fe.result import FEResult

    z = np.zeros
    return FEResult(nodes=np.random.default_rng(0).normal(size=(N, 3)), tets=np.array([[0, 1, 2, 3]]),
                    surface_nodes=np.arange(4), surface_tris=np.array([[0, 1, 2]]), fixed_nodes=np.array([4]),
                    U=z((F, N, 3)), S=z((F, N, 6)), CNORMF=z((F, N, 3)), CSHEAR=z((F, N, 3)),
                    contact_owner=np.full((F, N), -1), CAREA=z((F, K)), RF=np.ones((F, K, 3)), RM=z((F, K, 3)),
                    pose_position=z((F, K, 3)), pose_rotation=z((F, K, 3)),
                    converged=np.full(F, converged), base_reaction=z((F, 3)), seconds=z(F),
                    indenter_names=np.array(["a"] * K), scenario_json=standard_dome().to_json())


def test_result_roundtrip_no_pickle(tmp_path):
    r = _fake_result()
    path = save_result(r, tmp_path / "r.npz")
    assert not list(tmp_path.glob("*.tmp"))
    back = load_result(path)
    assert np.array_equal(back.nodes, r.nodes) and back.scenario().hash() == standard_dome().hash()
    with np.load(path, allow_pickle=False) as data:
        assert "U" in data.files


def test_result_refuses_unconverged_and_corrupt(tmp_path):
    with pytest.raises(FEResultError, match="unconverged"):
        save_result(_fake_result(converged=False), tmp_path / "r.npz")
    assert not (tmp_path / "r.npz").exists()
    bad = _fake_result()
    bad.S = np.zeros((2, 5, 3))
    with pytest.raises(FEResultError, match="S has shape"):
        save_result(bad, tmp_path / "r.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FEResultError, match="not a readable"):
        load_result(tmp_path / "junk.npz")


# ---------------------------------------------------------------- material: two formulations
def _random_F(seed=1, scale=0.25, shape=(4, 6)):
    rng = np.random.default_rng(seed)
    return np.eye(3)[:, :, None, None] + scale * rng.normal(size=(3, 3, *shape))


@pytest.mark.parametrize("model", ["yeoh", "neo_hookean"])
def test_closed_form_material_matches_felupe_autodiff(model):
    m = Material(model=model)
    F = _random_F()
    sv = np.zeros((0, *F.shape[2:]))
    ours = YeohUmat(m.C10, m.C20 if model == "yeoh" else 0, m.C30 if model == "yeoh" else 0, 3.0)
    ref = felupe_reference_umat(m, 3.0)
    P, Pr = ours.gradient([F, sv])[0], ref.gradient([F, sv])[0]
    A, Ar = ours.hessian([F, sv])[0], ref.hessian([F, sv])[0]
    assert np.abs(P - Pr).max() < 1e-10 * np.abs(Pr).max()
    assert np.abs(A - Ar).max() < 1e-10 * np.abs(Ar).max()
    h = 1e-6  # and the tangent is the derivative of the stress
    i, j = 1, 2
    Fp, Fm = F.copy(), F.copy()
    Fp[i, j] += h
    Fm[i, j] -= h
    dP = (ours.gradient([Fp, sv])[0] - ours.gradient([Fm, sv])[0]) / (2 * h)
    assert np.abs(dP - A[:, :, i, j]).max() < 1e-6 * np.abs(A).max()


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


# ---------------------------------------------------------------- shapes
@pytest.mark.parametrize("shape", [Sphere(3.0), Cylinder(2.0, 8.0), BoxEdge(8.0, 3.0), Flat(3.0, 0.5),
                                   Torus(4.0, 1.0)], ids=lambda s: type(s).__name__)
def test_shape_sdf_gradient_and_tip(shape):
    rng = np.random.default_rng(2)
    pts = rng.uniform(-5, 5, size=(300, 3)) + [0, 0, 3]
    d, g = shape.sdf(pts)
    h = 1e-6
    fd = np.stack([(shape.sdf(pts + h * e)[0] - shape.sdf(pts - h * e)[0]) / (2 * h) for e in np.eye(3)], 1)
    ok = np.abs(d) > 0.05  # away from the creases of non-smooth SDFs
    assert np.percentile(np.linalg.norm(fd - g, axis=1)[ok], 95) < 1e-4
    # the lowest point of every shape is at the origin (tip), nothing below z = 0
    below = np.column_stack([rng.uniform(-3, 3, 200), rng.uniform(-3, 3, 200), rng.uniform(-2, -1e-3, 200)])
    assert (shape.sdf(below)[0] > 0).all()
    assert shape.sdf(np.array([[0.0, 0.0, 0.05]]))[0][0] < 0 or isinstance(shape, Torus)


def test_mesh_shape_matches_analytic_sphere():
    import trimesh

    sph = trimesh.creation.icosphere(subdivisions=4, radius=3.0)
    sph.apply_translation([0, 0, 3.0])
    ms = MeshShape(sph.vertices, sph.faces)
    rng = np.random.default_rng(4)
    pts = rng.uniform(-4, 4, size=(200, 3)) + [0, 0, 3]
    d_mesh, g_mesh = ms.sdf(pts)
    d_ref, g_ref = Sphere(3.0).sdf(pts)
    assert np.abs(d_mesh - d_ref).max() < 0.02  # faceting error of a level-4 icosphere
    assert np.median(np.einsum("ij,ij->i", g_mesh, g_ref)) > 0.999


def test_docs_toml_example_is_a_valid_scenario():
    import re
    import tomllib
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "fe.md").read_text()
    block = re.search(r"```toml\n(.*?)```", text, re.S).group(1)
    s = scenario_from_dict(tomllib.loads(block))
    assert s.n_keypoints == 2 and s.indenters[0].keypoints[1].rotation == [0.0, 0.0, 0.1]


def test_mesh_shape_sign_at_edges_and_corners_of_a_box(tmp_path):
    import trimesh
    from tensortouch.tools.fe.indenters import _box_sdf, load_mesh_shape

    box = trimesh.creation.box([6.0, 4.0, 2.0])  # 12 large triangles: edges and corners dominate
    box.apply_translation([0, 0, 1.0])
    box.export(tmp_path / "box.stl")
    shape = load_mesh_shape(tmp_path / "box.stl")
    pts = np.random.default_rng(7).uniform([-6, -5, -3], [6, 5, 5], size=(2000, 3))
    d, _ = shape.sdf(pts)
    d_ref, _ = _box_sdf(pts - [0, 0, 1.0], np.array([3.0, 2.0, 1.0]))
    assert np.abs(d - d_ref).max() < 1e-6
