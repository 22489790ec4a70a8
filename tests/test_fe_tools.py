"""tools.fe shells: gmsh meshing of every gel kind, procedural indenters, mesh-indenter solve,
material fitting, batch runner (cache/resume/failures), CLI, .inp export."""
import argparse
import json

import numpy as np
import pytest

pytest.importorskip("felupe")
pytest.importorskip("gmsh")
trimesh = pytest.importorskip("trimesh")

from tensortouch.tools.fe import load_result, save_scenario, solve  # noqa: E402
from tensortouch.tools.fe.mesh import mesh_gel  # noqa: E402
from tensortouch.tools.fe.scenario import GelGeometry, Indenter, Keypoint, MeshSettings, Scenario, standard_dome  # noqa: E402

SMALL_PAD = GelGeometry(kind="flat_pad", size_x=10.0, size_y=10.0, thickness=4.0)
SMALL_MESH = MeshSettings(size_top=1.0, size_inside=1.5, refine_depth=0.5)


def small_scenario(depth=0.5, z0=4.0, shape="sphere", params=None, mesh_path="", mu=2.2):
    ind = Indenter(name="i", shape=shape, params=params or {"radius": 3.0}, mesh_path=mesh_path,
                   position=[0.0, 0.0, z0], keypoints=[Keypoint([0.0, 0.0, -depth])])
    return Scenario(gel=SMALL_PAD, mesh=SMALL_MESH, indenters=[ind], friction=mu, name="small")


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


def test_procedural_set_is_deterministic_and_standardized(tmp_path):
    from tensortouch.tools.fe.procedural import OBJECT_KINDS, TOP_HEIGHT, generate_set

    assert len(OBJECT_KINDS) >= 12
    a = generate_set(tmp_path / "a", seed=3, count=len(OBJECT_KINDS))
    b = generate_set(tmp_path / "b", seed=3, count=2)
    assert a[0].read_bytes() == b[0].read_bytes() and a[1].read_bytes() == b[1].read_bytes()
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())["indenters"]
    assert {m["kind"] for m in manifest} == set(OBJECT_KINDS)
    for p in a:
        m = trimesh.load(p)
        assert m.is_watertight and len(m.split()) == 1
        assert m.bounds[0, 2] == pytest.approx(0, abs=1e-6) and m.bounds[1, 2] == pytest.approx(TOP_HEIGHT, abs=1e-3)
        low = m.vertices[m.vertices[:, 2] < 1e-6]
        assert np.linalg.norm(low, axis=1).min() < 1e-6  # a lowest point (the tip) at the origin


def test_mesh_indenter_solve_matches_analytic_sphere(tmp_path):
    sph = trimesh.creation.icosphere(4, radius=3.0)
    sph.apply_translation([0, 0, 3.0])
    sph.export(tmp_path / "ball.stl")
    sc_mesh = small_scenario(shape="mesh", params={}, mesh_path="ball.stl")
    path = save_scenario(sc_mesh, tmp_path / "s.json")
    from tensortouch.tools.fe import load_scenario

    sc_mesh = load_scenario(path)  # relative mesh path resolves against the scenario folder
    mesh = mesh_gel(SMALL_PAD, SMALL_MESH)
    f_mesh = solve(sc_mesh, mesh=mesh).RF[0, 0, 2]
    f_ana = solve(small_scenario(), mesh=mesh).RF[0, 0, 2]
    assert f_mesh < 0 and f_mesh == pytest.approx(f_ana, rel=0.05)


def test_material_fit_ranks_yeoh_over_neo_hookean(tmp_path):
    from tensortouch.tools.fe.fitting import fit_report, load_test_data, synthetic_test_data

    data = synthetic_test_data(C=(0.03, 0.002, 0.0002), noise=1e-4)
    rep = fit_report(data, plot=tmp_path / "fit.png")
    fits = {f["model"]: f for f in rep["fits"]}
    assert fits["yeoh"]["rmse"] < 0.5 * fits["neo_hookean"]["rmse"]
    assert fits["yeoh"]["params"]["C10"] == pytest.approx(0.03, rel=0.05)
    assert fits["yeoh"]["stable"] and rep["hysteresis_width"] > 0
    assert (tmp_path / "fit.png").stat().st_size > 1000
    csv = "mode,stretch,stress_MPa,branch\n" + "\n".join(
        f"{m},{s},{p},{b}" for m, s, p, b in zip(data.mode, data.stretch, data.stress, data.branch))
    (tmp_path / "d.csv").write_text(csv)
    back = load_test_data(tmp_path / "d.csv")
    assert np.allclose(back.stress, data.stress)


def test_batch_cache_resume_and_failures(tmp_path):
    from tensortouch.tools.fe.batch import run_batch

    scen = tmp_path / "scen"
    save_scenario(small_scenario(0.4), scen / "a.json")
    save_scenario(small_scenario(0.6), scen / "b.json")
    save_scenario(small_scenario(0.5, z0=3.5), scen / "bad.json")  # starts inside the gel
    rep = run_batch([scen], out_dir=tmp_path / "cache", workers=2)
    assert rep["solved"] == 2 and rep["failed"] == 1 and rep["cached"] == 0
    index = json.loads((tmp_path / "cache" / "index.json").read_text())
    assert "penetrates" in index[str(scen / "bad.json")]["error"]
    h = index[str(scen / "a.json")]["hash"]
    assert load_result(tmp_path / "cache" / f"{h}.npz").converged.all()
    rep2 = run_batch([scen], out_dir=tmp_path / "cache", workers=2)  # resume: nothing to do
    assert rep2["solved"] == 0 and rep2["cached"] == 2 and rep2["failed"] == 1


def test_cli_solve_list_and_inp(tmp_path, capsys):
    from tensortouch.tools.fe.cli import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["fe", "indenters", "list"])
    assert args.func(args) == 0 and "banana" in capsys.readouterr().out
    save_scenario(small_scenario(0.4), tmp_path / "s.json")
    args = parser.parse_args(["fe", "solve", str(tmp_path / "s.json"), "--out", str(tmp_path / "r.npz")])
    assert args.func(args) == 0
    assert load_result(tmp_path / "r.npz").n_frames == 1
    args = parser.parse_args(["fe", "export-inp", str(tmp_path / "s.json"), "--out", str(tmp_path / "d.inp"),
                              "--dialect", "abaqus"])
    assert args.func(args) == 0
    deck = (tmp_path / "d.inp").read_text()
    for key in ("*ELEMENT, TYPE=C3D4H", "*HYPERELASTIC, YEOH", "*FRICTION\n2.2", "*RIGID BODY",
                "KEYPOINT_1", "GEL-1.BASE, ENCASTRE", "CNORMF"):
        assert key in deck
    from tensortouch.runtime.shells.cli import main

    assert main(["fe", "solve", str(tmp_path / "missing.json"), "--out", str(tmp_path / "x.npz")]) == 2
    assert "scenario file not found" in capsys.readouterr().err


def test_standard_dome_contract():
    s = standard_dome()
    assert s.gel.kind == "flattened_dome" and s.gel.radius == 12.0 and s.gel.top_z == 8.0
    assert s.n_keypoints == 5 and s.friction == 2.2 and s.mesh.size_top == 0.7 and s.mesh.size_inside == 2.0


def test_bench_quick_json_last_line(capsys):
    from tensortouch.tools.fe import bench

    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    assert bench.run(parser.parse_args(["--quick", "--json"])) == 0
    out = capsys.readouterr().out.strip().splitlines()
    data = json.loads(out[-1])
    assert data["quick"] and "QUICK" in out[0]
    for key in ("seconds_per_frame", "seconds_per_trajectory", "nodes"):
        assert data[key] > 0
    assert data["equilibrium_error_max"] < 0.01 and data["final_force_N"][2] < 0
    # the reference engine and the default one side by side: both timed, same forces
    assert [r["engine"] for r in data["runs"]] == ["superlu", "pardiso"] and data["engine"] == "pardiso"
    assert data["speedup_cpu"] > 0 and data["final_force_rel_diff"] < 5e-3
    new = data["runs"][1]
    assert new["symbolic_analyses"] == 1 and new["factorizations"] == new["newton_iterations"]
    assert "faster" in "".join(out)


def test_meshing_leaves_sigpipe_ignored():
    """gmsh.initialize resets SIGPIPE to its default; after meshing a broken pipe must still be an OSError,
    not the end of the process."""
    def ignored():
        for line in open("/proc/self/status"):
            if line.startswith("SigIgn"):
                return bool(int(line.split()[1], 16) & (1 << 12))
    mesh_gel(GelGeometry(), MeshSettings(size_top=2.0, size_inside=4.0))
    assert ignored()
