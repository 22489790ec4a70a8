"""Fingertip pose selection (tools/grasp): hand-worked cases and the Allegro run end to end."""
import argparse
import json

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio")
coal = pytest.importorskip("coal")

from tensortouch.tools.grasp import axis, hand_model, manipulability, mount, workspace

PLANAR_2LINK = """<?xml version="1.0"?>
<robot name="planar2">
  <link name="base"/>
  <link name="l1"/>
  <link name="l2"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="{l1} 0 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <link name="tip"/>
  <joint name="tipj" type="fixed"><parent link="l2"/><child link="tip"/><origin xyz="{l2} 0 0"/></joint>
</robot>
"""


def test_manipulability_planar_two_link_matches_l1_l2_sin_q2(tmp_path):
    """For a planar 2-link arm, w = √det(J Jᵀ) of the planar (x,y) Jacobian is l1·l2·|sin q2|."""
    l1, l2 = 0.3, 0.2
    urdf = tmp_path / "p.urdf"
    urdf.write_text(PLANAR_2LINK.format(l1=l1, l2=l2))
    model = pin.buildModelFromUrdf(str(urdf))
    data = model.createData()
    fid = model.getFrameId("tip")
    for q in ([0.3, 0.0], [0.1, 0.5], [-1.0, 1.2], [0.7, np.pi / 2]):
        q = np.array(q)
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacements(model, data)
        J = pin.getFrameJacobian(model, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:2]
        assert manipulability.manipulability(J) == pytest.approx(l1 * l2 * abs(np.sin(q[1])), abs=1e-12)
        # the full 6×2 Jacobian makes J Jᵀ singular: w collapses to ~0 (the seed's 1e-23 threshold)
        J6 = pin.getFrameJacobian(model, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        assert manipulability.manipulability(J6) < 1e-10
    # hand-worked J at q = (0, π/2): tip at (l1, l2); J = [[-l2, -l2], [l1, 0]], det = l1·l2
    J = np.array([[-l2, -l2], [l1, 0.0]])
    assert manipulability.manipulability(J) == pytest.approx(l1 * l2)


@pytest.mark.parametrize("c2,r1,r2", [((0.05, 0, 0), 0.01, 0.012), ((0.01, 0.02, -0.005), 0.0102, 0.0102),
                                     ((0.0201, 0, 0), 0.01, 0.01)])
def test_coal_sphere_distance_equals_centre_distance_minus_radii(c2, r1, r2):
    c1 = np.array([0.001, -0.002, 0.003])
    c2 = c1 + np.array(c2)
    d, p1, p2 = workspace.sphere_distance(c1, r1, c2, r2)
    expected = np.linalg.norm(c2 - c1) - r1 - r2
    assert d == pytest.approx(expected, abs=1e-9)
    if expected > 0:  # witness points lie on the spheres along the centre line
        u = (c2 - c1) / np.linalg.norm(c2 - c1)
        np.testing.assert_allclose(p1, c1 + r1 * u, atol=1e-9)
        np.testing.assert_allclose(p2, c2 - r2 * u, atol=1e-9)


def test_ransac_finds_a_known_line_among_outliers():
    rng = np.random.default_rng(3)
    d = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    p0 = np.array([0.02, -0.01, 0.05])
    on = p0 + np.outer(rng.uniform(-0.05, 0.05, 60), d) + rng.normal(0, 0.002, (60, 3))
    off = rng.uniform(-0.08, 0.08, (40, 3)) + p0
    off = off[axis.line_distance(off, p0, d) > 0.02]
    pts = np.concatenate([on, off])
    best = axis.best_inlier_axis(pts, radius=0.01, trials=300, rng=0)
    assert abs(best.direction @ d) > 0.995
    assert axis.line_distance(best.point[None], p0, d)[0] < 0.003
    assert best.inliers[:60].all() and not best.inliers[60:].any()
    # PCA is pulled by the outliers; the inlier axis is not
    pca = axis.pca_axis(pts)
    assert abs(pca.direction @ d) < abs(best.direction @ d)


def test_allegro_workspace_filters_and_contact_geometry():
    spec = hand_model.HandSpec()
    model = hand_model.load(None, spec)
    ws = workspace.sample(model, spec, workspace.WorkspaceConfig(samples=3000, seed=1))
    assert ws.contact.sum() > 5
    c = ws.contact
    assert np.all(ws.tip_distance[c] <= 0.06) and np.all(ws.alignment[c] <= 0)
    assert np.all(ws.distance[c] <= 0.001)
    # the contact point is the midpoint of coal's nearest points; the normal points index → thumb
    np.testing.assert_allclose(ws.point[c], 0.5 * (ws.p_thumb[c] + ws.p_index[c]))
    pt, pi = ws.tip_thumb[c][:, :3, 3], ws.tip_index[c][:, :3, 3]
    assert np.all(np.einsum("sk,sk->s", ws.normal[c], pt - pi) > 0)
    # shrunk spheres: r = 12 mm × 0.85; coal distance = centre distance − 2r
    np.testing.assert_allclose(ws.distance[c], np.linalg.norm(pt - pi, axis=1) - 2 * 0.0102, atol=1e-9)


def test_variant_edits_the_distal_joint_placement_and_urdf(tmp_path):
    spec = hand_model.HandSpec()
    model = hand_model.load(None, spec)
    nominal = hand_model.nominal_placement(model, spec)
    jid = model.getJointId(spec.distal_joint)
    hand_model.apply_variant(model, spec, nominal, 0.043, np.radians(10))
    M = model.jointPlacements[jid]
    assert M.translation[2] == pytest.approx(0.043)
    assert np.degrees(pin.rpy.matrixToRpy(M.rotation))[1] == pytest.approx(10)
    out = hand_model.write_urdf(hand_model.default_urdf(), tmp_path / "h.urdf", spec, 0.043, np.radians(10))
    m2 = hand_model.load(out, spec)
    np.testing.assert_allclose(m2.jointPlacements[jid].homogeneous, M.homogeneous, atol=1e-6)


def test_mount_cli_writes_figures_variant_and_urdf(tmp_path):
    from tensortouch.tools.grasp.cli import register

    parser = argparse.ArgumentParser(prog="tensortouch")
    register(parser.add_subparsers())
    args = parser.parse_args(["mount", "--out", str(tmp_path), "--samples", "1500", "--z-cm", "4.3,5.1",
                              "--pitch-deg", "0,10", "--graph-nodes", "60", "--refine-nodes", "20"])
    assert args.func(args) == 0
    summary = json.loads((tmp_path / "mount.json").read_text())
    assert summary["chosen"]["z_cm"] in (4.3, 5.1) and summary["chosen"]["pitch_deg"] in (0, 10)
    assert np.array(summary["grid"]["inliers"]).shape == (2, 2)
    for name in ("mount_heatmaps.png", "mount_contacts_3d.png", "hand_mounted.urdf", "contact_graph.npz"):
        assert (tmp_path / name).stat().st_size > 500
    assert summary["graph"]["nodes"] == 80


def test_mount_cli_bad_urdf_exits_2(tmp_path, capsys):
    from tensortouch.tools.grasp.cli import register

    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'/></robot>")
    parser = argparse.ArgumentParser(prog="tensortouch")
    register(parser.add_subparsers())
    args = parser.parse_args(["mount", "--urdf", str(bad), "--out", str(tmp_path), "--samples", "100"])
    assert args.func(args) == 2
    assert "joint_12.0" in capsys.readouterr().err


def test_select_scores_every_variant_and_picks_the_best_score():
    cfg = mount.MountConfig(z_cm=(4.3, 5.1), pitch_deg=(0.0, 20.0),
                            workspace=workspace.WorkspaceConfig(samples=2000))
    res = mount.select(cfg=cfg)
    s = mount.score(res.variants, cfg)
    assert res.chosen is res.variants[int(np.argmax(s))]
    assert res.grid("n_contacts").shape == (2, 2)
