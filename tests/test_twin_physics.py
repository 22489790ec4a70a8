"""Twin physics: keypoint runs, interpolation between solved keypoints, Hertz fallback, trajectories."""
import numpy as np
from tensortouch.tools.twin.bench import _densify
from tensortouch.tools.twin.geometry import GelSurface
from tensortouch.tools.twin.physics import HertzFallbackPhysics, interpolate, keypoint_poses, motion_runs
from tensortouch.tools.twin.trajectory import TrajectoryConfig, plan_session, poke_pose

GEL = GelSurface()


def _poke(kind, seed=3):
    return plan_session(1, seed, GEL, TrajectoryConfig(kinds=(kind,), p_two=0.0, indenters=("sphere5",)))[0]


def test_motion_runs_split_press_hold_move_release():
    p = _poke("slide")
    runs = motion_runs(p)
    assert runs[0][0] == 0 and runs[-1][1] == len(p.times) - 1
    assert all(a < b for a, b in runs) and all(r[1] == s[0] for r, s in zip(runs, runs[1:]))
    assert len(runs) >= 4  # press, hold, slide, release


def test_interpolation_exact_at_keypoints_and_pchip_beats_linear():
    p = _poke("press")
    phys = HertzFallbackPhysics(GEL)
    sol = phys.solve(p)
    np.testing.assert_allclose(interpolate(sol, p, p.times, "RF"), sol.RF, atol=1e-12)
    dense_p = _densify(p, 4)
    dense = phys.solve(dense_p)
    between = np.arange(len(dense_p.times)) % 4 != 0
    t = dense_p.times[between]
    err = {m: np.abs(interpolate(sol, p, t, "RF", method=m) - dense.RF[between]).max() for m in ("pchip", "linear")}
    assert err["pchip"] < 0.5 * err["linear"], err
    peak = np.abs(dense.RF).max()
    assert err["pchip"] < 0.05 * peak  # 3.5 % measured; the contact onset segment dominates


def test_hertz_fallback_force_grows_with_depth_and_points_into_gel():
    p = _poke("press")
    sol = HertzFallbackPhysics(GEL).solve(p)
    press = [j for j in range(1, len(p.times)) if sol.depth[j, 0] > sol.depth[j - 1, 0]]
    f = np.linalg.norm(sol.RF[press, 0], axis=1)
    assert np.all(np.diff(f) > 0)
    n = GEL.normals(sol.contact[press[-1], 0])
    assert sol.RF[press[-1], 0] @ n < 0  # the indenter pushes into the gel (FE RF convention)


def test_trajectory_keypoints_match_poses_and_start_outside_gel():
    p = _poke("twist")
    pos, rot = keypoint_poses(p)
    tp, tr = poke_pose(p, 0, p.times, hover=6.0)
    np.testing.assert_allclose(tp, pos[:, 0], atol=1e-9)
    np.testing.assert_allclose(tr, rot[:, 0], atol=1e-9)
    # initial tip above the rest surface, pressing along the inward normal
    start = p.position[0]
    assert np.linalg.norm(start) > np.linalg.norm(GEL.point_at(*GEL.theta_phi(start)))
    a, b = plan_session(4, 9, GEL), plan_session(4, 9, GEL)
    assert [x.to_dict() for x in a] == [x.to_dict() for x in b]


