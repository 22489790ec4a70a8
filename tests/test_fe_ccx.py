"""CalculiX 2.20 cross-check: the deck `tensortouch fe export-inp` writes runs in ccx as written and
gives the press force tools.fe computes on the same mesh, element and bulk modulus (issue 26 item 4)."""
import numpy as np
import pytest

pytest.importorskip("felupe")
pytest.importorskip("gmsh")
pytest.importorskip("trimesh")

from tensortouch.tools.fe.ccx import crosscheck, find_ccx, read_reactions
from tensortouch.tools.fe.inp import export_inp_ccx, rigid_tets, step_increments
from tensortouch.tools.fe.scenario import standard_dome

needs_ccx = pytest.mark.skipif(find_ccx() is None, reason="CalculiX (ccx) is not installed: "
                               "apt-get install -y calculix-ccx (.ci/system-deps installs it)")


def coarse_press(depth=2.0, mu=0.0):
    sc = standard_dome(depth=depth, slide=(0.0, 0.0), n_keypoints=1, size_top=1.0, size_inside=2.5)
    sc.friction = mu
    return sc


def test_ccx_deck_keywords(tmp_path):
    sc = coarse_press(mu=2.2)
    sc.indenters[0].keypoints[0].rotation = [0.0, 0.0, 0.05]
    deck = export_inp_ccx(sc, tmp_path / "d.inp").read_text()
    for bad in ("ENCASTRE", "C3D4H", "R3D3", "*PART", "*INSTANCE", "GEL-1.", "ELSET=IND1_EL\n*RIGID", "H,"):
        assert bad not in deck
    for key in ("*ELEMENT, TYPE=C3D4, ELSET=GEL", "BASE, 1, 3", "TYPE=NODE TO SURFACE",
                "*RIGID BODY, NSET=IND1_NODES, REF NODE=", "ROT NODE=", "PRESSURE-OVERCLOSURE=LINEAR\n6\n",
                "*FRICTION\n2.2, 0.6\n", "IND1_ROT, 3, 3, 0.05", "*NODE PRINT, NSET=IND1_REF"):
        assert key in deck, key
    assert "*FRICTION" not in export_inp_ccx(coarse_press(mu=0.0), tmp_path / "f.inp").read_text()
    # the true D1 on request (P1 otherwise gets the solver's capped bulk modulus 5 * mu0 = 0.3 MPa)
    assert "0.0002, 0.66" in export_inp_ccx(sc, tmp_path / "m.inp", bulk="material").read_text()
    assert step_increments(coarse_press(depth=2.0)) == [5]  # 2.05 mm at <= 0.5 mm


def test_rigid_tets_are_positive_and_face1_is_the_surface():
    import trimesh

    m = trimesh.creation.icosphere(2, radius=3.0)
    nodes, tets = rigid_tets(m)
    x = nodes[tets]
    vol = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])
    assert (vol > 0).all()
    assert np.allclose(np.linalg.norm(x[:, :3], axis=2), 3.0)  # face 1 lies on the surface


def test_read_reactions_takes_the_end_of_each_step(tmp_path):
    (tmp_path / "a.dat").write_text(
        "\n forces (fx,fy,fz) for set IND1_REF and time  0.5000000E+00\n\n  77 1.0 2.0 -3.0\n"
        "\n forces (fx,fy,fz) for set IND1_REF and time  0.1000000E+01\n\n  77 1.5 2.5 -3.5\n"
        "\n forces (fx,fy,fz) for set IND1_REF and time  0.2000000E+01\n\n  77 0.1 0.2 -0.3\n")
    r = read_reactions(tmp_path / "a.dat", 2)["IND1_REF"]
    assert np.allclose(r, [[1.5, 2.5, -3.5], [0.1, 0.2, -0.3]])


@needs_ccx
def test_press_agrees_with_calculix(tmp_path):
    """A 2 mm frictionless press of the coarse dome (top 1.0 mm): ccx runs our deck as written."""
    out = crosscheck(coarse_press(), tmp_path)
    ours, ccx = out["ours"][-1, 0], out["ccx"][-1, 0]
    assert ccx[2] < -1.0  # pressing: the indenter pushes the gel down
    assert ours[2] / ccx[2] == pytest.approx(1.0, abs=0.05)
    assert abs(ccx[0]) < 0.05 and abs(ccx[1]) < 0.05


def test_deck_increment_cap_for_c3d10(tmp_path):
    from tensortouch.tools.fe.inp import C3D10_MAX_INCREMENT_MM

    sc = coarse_press(depth=2.0)
    assert step_increments(sc, max_increment_mm=C3D10_MAX_INCREMENT_MM) == [9]  # 2.05 mm at <= 0.25 mm
    deck = export_inp_ccx(sc, tmp_path / "d.inp", max_increment_mm=0.25).read_text()
    assert "*STATIC\n0.11111111, 1., 1.11e-06, 0.11111111\n" in deck
    assert "*STATIC\n0.2, 1., 2e-06, 0.2\n" in export_inp_ccx(sc, tmp_path / "e.inp").read_text()
    with pytest.raises(ValueError, match="max_increment_mm"):
        export_inp_ccx(sc, tmp_path / "f.inp", max_increment_mm=0.0)


def test_cli_export_inp_max_increment(tmp_path, capsys):
    import argparse

    from tensortouch.tools.fe.cli import register
    from tensortouch.tools.fe.scenario import save_scenario

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    save_scenario(coarse_press(depth=1.0), tmp_path / "s.json")
    args = parser.parse_args(["fe", "export-inp", str(tmp_path / "s.json"), "--out", str(tmp_path / "d.inp"),
                              "--max-increment-mm", "0.25"])
    assert args.func(args) == 0
    assert "*STATIC\n0.2, 1., 2e-06, 0.2\n" in (tmp_path / "d.inp").read_text()  # 1.05 mm in 5 increments
    with pytest.raises(SystemExit) as exc:
        parser.parse_args(["fe", "export-inp", "standard", "--out", "x.inp", "--max-increment-mm", "0"])
    assert exc.value.code == 2 and "expected a length in mm > 0" in capsys.readouterr().err
