"""tools.fe shells: mesh-indenter solve, batch runner (cache/resume/failures), CLI, .inp export, bench."""
import argparse
import json

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
    assert [r["engine"] for r in data["runs"]] == ["superlu", "pardiso-krylov"] and data["engine"] == "pardiso-krylov"
    assert data["speedup_cpu"] > 0 and data["final_force_rel_diff"] < 5e-3
    new = data["runs"][1]
    assert new["symbolic_analyses"] == 1
    assert new["factorizations"] + new["chord_steps"] == new["newton_iterations"]
    assert new["refinements"] >= new["newton_iterations"] - new["chord_steps"] and new["double_fallbacks"] == 0
    assert "faster" in "".join(out)


def test_bench_engines_list_compares_each_with_the_first(capsys):
    from tensortouch.tools.fe import bench

    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    assert bench.run(parser.parse_args(["--quick", "--json", "--keypoints", "2",
                                        "--engines", "pardiso,pardiso-reuse"])) == 0
    data = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert data["reference_engine"] == "pardiso" and list(data["versus_reference"]) == ["pardiso-reuse"]
    assert data["versus_reference"]["pardiso-reuse"]["final_force_rel_diff"] < 1e-3
    assert bench.run(parser.parse_args(["--engines", "pardiso,nope"])) == 2
    assert "--engines" in capsys.readouterr().out




def test_bench_counts_the_krylov_engines_solves(capsys, monkeypatch):
    """`bench fe --engines pardiso-mixed,pardiso-krylov`: the Krylov engine's solves on kept factors and
    their iterations are counted in the runs and printed; forces as the mixed engine's."""
    from tensortouch.tools.fe import bench, linsolve

    monkeypatch.setattr(linsolve, "KRYLOV_MIN_DOFS", 0)    # the quick mesh is small: Krylov solves anyway
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    assert bench.run(parser.parse_args(["--quick", "--json", "--keypoints", "2",
                                        "--engines", "pardiso-mixed,pardiso-krylov"])) == 0
    out = capsys.readouterr().out.strip().splitlines()
    data = json.loads(out[-1])
    mixed, kry = data["runs"]
    assert kry["engine"] == "pardiso-krylov" and mixed["krylov_solves"] == 0
    assert kry["krylov_solves"] > 0 and kry["krylov_iterations"] >= kry["krylov_solves"]
    assert kry["factorizations"] < mixed["factorizations"] and kry["newton_iterations"] == mixed["newton_iterations"]
    assert data["final_force_rel_diff"] < 1e-6
    assert "Krylov solves on kept factors" in "".join(out)
