"""gmsh meshing of the gel (tools/fe/mesh.py): every gel kind, refinement, STL gels, SIGPIPE left alone."""
import numpy as np
import pytest

pytest.importorskip("felupe")
pytest.importorskip("gmsh")
trimesh = pytest.importorskip("trimesh")

from tensortouch.tools.fe.mesh import mesh_gel  # noqa: E402
from tensortouch.tools.fe.scenario import GelGeometry, MeshSettings  # noqa: E402


@pytest.mark.parametrize("kind", ["dome", "flattened_dome", "flat_pad"])
def test_gmsh_gel_kinds_are_valid_meshes(kind):
    g = GelGeometry(kind=kind, radius=6.0, cap_height=3.0, skirt=1.0, size_x=8, size_y=8, thickness=3)
    m = mesh_gel(g, MeshSettings(size_top=0.8, size_inside=1.6))
    x = m.nodes[m.tets]
    vol = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]) / 6
    assert (vol > 0).all()
    assert m.nodes[:, 2].min() == pytest.approx(0, abs=1e-9)
    assert m.nodes[:, 2].max() == pytest.approx(g.top_z, abs=0.02)
    assert len(m.fixed_nodes) > 10 and np.isin(m.surface_nodes, m.fixed_nodes).sum() == 0
    expected_volume = {"dome": 2 / 3 * np.pi * 6 ** 3 + np.pi * 36 * 1,
                       "flattened_dome": np.pi * 3 / 6 * (3 * 36 + 9) + np.pi * 36 * 1, "flat_pad": 8 * 8 * 3}[kind]
    assert vol.sum() == pytest.approx(expected_volume, rel=0.02)


def test_refinement_is_finer_at_the_top():
    m = mesh_gel(GelGeometry(), MeshSettings(size_top=1.0, size_inside=2.5))
    edges = m.nodes[m.tets[:, 1]] - m.nodes[m.tets[:, 0]]
    length = np.linalg.norm(edges, axis=1)
    zc = m.nodes[m.tets].mean(axis=1)
    r = np.linalg.norm(zc, axis=1)
    outer = r > 0.85 * r.max()
    assert length[outer].mean() < 0.8 * length[~outer].mean()


def test_stl_gel(tmp_path):
    box = trimesh.creation.box([8.0, 8.0, 3.0])
    box.apply_translation([0, 0, 1.5])
    box.export(tmp_path / "gel.stl")
    m = mesh_gel(GelGeometry(kind="stl", stl_path=str(tmp_path / "gel.stl")), MeshSettings(1.0, 1.5))
    x = m.nodes[m.tets]
    vol = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]) / 6
    assert vol.sum() == pytest.approx(192.0, rel=1e-3) and len(m.fixed_nodes) > 0


def test_meshing_leaves_sigpipe_ignored():
    """gmsh.initialize resets SIGPIPE to its default; after meshing a broken pipe must still be an OSError,
    not the end of the process."""
    def ignored():
        for line in open("/proc/self/status"):
            if line.startswith("SigIgn"):
                return bool(int(line.split()[1], 16) & (1 << 12))
    mesh_gel(GelGeometry(), MeshSettings(size_top=2.0, size_inside=4.0))
    assert ignored()
