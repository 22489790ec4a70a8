"""Indenter shapes and poses (tools/fe/indenters.py): pose interpolation, SDF gradients, mesh shapes."""
import numpy as np
import pytest

pytest.importorskip("felupe")

from tensortouch.tools.fe import (  # noqa: E402
    standard_dome,
)
from tensortouch.tools.fe.indenters import BoxEdge, Cylinder, Flat, MeshShape, Sphere, Torus, pose_at  # noqa: E402

# ---------------------------------------------------------------- scenario contract


def test_pose_interpolation_about_reference_point():
    ind = standard_dome().indenters[0]
    ind.keypoints[0].rotation = [0.0, 0.0, 0.2]
    p_init, r_init = pose_at(ind, -1.0)
    p0, r0 = pose_at(ind, 0.0)
    ph, rh = pose_at(ind, -0.5)
    assert np.allclose(p_init, ind.position) and np.allclose(r_init, 0)
    assert np.allclose(p0, np.add(ind.position, ind.keypoints[0].translation))
    assert np.allclose(rh, [0, 0, 0.1]) and np.allclose(ph, (p_init + p0) / 2)


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
