"""Stage 2 (resolve): stage-1 keypoints of measured poses → FE scenario (tools/train/resolve.py) and the
frame sigma of the re-solved path. Synthetic pose tracks with known motion."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tensortouch.tools.fe import GelGeometry
from tensortouch.tools.fe.indenters import make_shape
from tensortouch.tools.train.resolve import (
    PoseTrack,
    ResolveConfig,
    ResolveError,
    clearance,
    densify,
    fit_pose,
    frame_sigma,
    interp_frames,
    period_scenario,
    surface_samples,
)
from tensortouch.tools.twin.geometry import GelSurface

GEL = GelGeometry(kind="flattened_dome", radius=12.0, cap_height=6.0, skirt=2.0)
SURF = GelSurface(12.0, 6.0, 2.0)
CATALOG = {"ball": {"shape": "sphere", "params": {"radius": 3.0}}}


def _poke_track(theta=0.3, phi=0.7, depth=1.2, noise=0.0, rate=120.0, seed=0):
    """A press along the inward normal at (θ, φ): hover 3 mm → contact at t = 1 s → depth at t = 1.6 s →
    hold → release by t = 2.6 s. Tip frame local +z along the outward normal (docs/fe.md)."""
    p = SURF.point_at(np.array([theta]), np.array([phi]))[0]
    n = SURF.normals(p[None])[0]
    t = np.arange(0.0, 3.2, 1.0 / rate)
    h = np.interp(t, [0.0, 0.6, 1.0, 1.6, 2.0, 2.6, 3.2], [3.0, 3.0, 0.0, -depth, -depth, 0.5, 3.0])
    pos = p + h[:, None] * n
    axis = np.cross([0, 0, 1.0], n)
    rv = axis / np.linalg.norm(axis) * np.arccos(n[2])
    q = np.tile(Rotation.from_rotvec(rv).as_quat(scalar_first=True), (len(t), 1))
    rng = np.random.default_rng(seed)
    return PoseTrack(t, pos + rng.normal(0, noise, pos.shape), q), p, n, h


def test_fit_pose_smooths_mocap_noise_without_lag():
    tr, p, n, h = _poke_track(noise=0.05)
    clean, *_ = _poke_track(noise=0.0)
    ts = np.array([0.8, 1.3, 1.8, 2.3])
    P, R = fit_pose(tr, ts, ResolveConfig().pose_half_window_s)
    truth = np.stack([np.interp(ts, clean.t, clean.position[:, c]) for c in range(3)], 1)
    err = np.linalg.norm(P - truth, axis=1)
    assert err.max() < 0.06 and err.mean() < 0.045          # raw samples: 0.05 mm per axis (0.087 mm 3-D)
    np.testing.assert_allclose(Rotation.from_rotvec(R).as_quat(scalar_first=True), clean.quaternion[:4], atol=1e-9)


def test_period_scenario_starts_clear_and_moves_by_the_measured_poses():
    tr, p, n, h = _poke_track()
    t_key = np.array([1.2, 1.6, 1.8, 2.1])            # stage-1 keypoints: already in contact at the first
    ps = period_scenario([tr], [3], ["ball"], t_key, CATALOG, GEL, SURF)
    sc = ps.scenario
    ind = sc.indenters[0]
    shape = make_shape(ind)
    surf = surface_samples(SURF, 0.4)
    assert clearance(shape, np.array(ind.position), np.array(ind.rotation), surf) >= ResolveConfig().clear_gap_mm
    # the latest clear sample: the next pose sample already is within the gap
    t_next = tr.t[np.searchsorted(tr.t, ps.t_init) + 1]
    p2, r2 = fit_pose(tr, [t_next], ResolveConfig().pose_half_window_s)
    assert clearance(shape, p2[0], r2[0], surf) < ResolveConfig().clear_gap_mm
    assert 0.9 < ps.t_init < 1.0 and ps.slots == [3]
    # FE frames: every keypoint kept, inserted frames keep steps ≤ 0.5 mm between keypoints
    assert set(np.round(t_key, 6)) <= set(np.round(ps.times, 6)) and ps.is_keypoint.sum() == len(t_key)
    P = np.array(ind.position) + np.array([k.translation for k in ind.keypoints])
    assert np.all(np.linalg.norm(np.diff(P, axis=0), axis=1) <= 0.5 + 1e-6)
    truth = p[None] + np.interp(ps.times, tr.t, h)[:, None] * n
    np.testing.assert_allclose(P, truth, atol=0.02)      # the measured motion (piecewise linear here)
    np.testing.assert_allclose([k.rotation for k in ind.keypoints], 0.0, atol=1e-9)
    assert sc.hash() == period_scenario([tr], [3], ["ball"], t_key, CATALOG, GEL, SURF).scenario.hash()


def test_period_scenario_takes_the_recipes_locking_cap():
    from tensortouch.tools.fe import SolverSettings

    tr, *_ = _poke_track()
    t_key = np.array([1.2, 1.6, 1.8, 2.1])
    plain = period_scenario([tr], [3], ["ball"], t_key, CATALOG, GEL, SURF).scenario
    five = period_scenario([tr], [3], ["ball"], t_key, CATALOG, GEL, SURF, solver=SolverSettings(max_bulk_ratio=5.0)).scenario
    six = period_scenario([tr], [3], ["ball"], t_key, CATALOG, GEL, SURF, solver=SolverSettings(max_bulk_ratio=6.0)).scenario
    assert plain.solver.max_bulk_ratio == 5.0 and five.hash() == plain.hash()     # the default cap: same cache entries
    assert six.solver.max_bulk_ratio == 6.0 and six.hash() != plain.hash()
    from types import SimpleNamespace

    from tensortouch.tools.train.build import BuildConfig
    from tensortouch.tools.train.sources import label_solver

    assert label_solver(SimpleNamespace(cfg=BuildConfig(max_bulk_ratio=6))) == SolverSettings(max_bulk_ratio=6.0)
    assert label_solver(SimpleNamespace(cfg=BuildConfig())) == SolverSettings()      # the recipe default: the shipped labels


def test_period_scenario_refuses_unknown_indenter_or_no_clear_pose():
    tr, *_ = _poke_track()
    with pytest.raises(ResolveError, match="catalog"):
        period_scenario([tr], [0], ["unknown"], np.array([1.2, 1.6]), CATALOG, GEL, SURF)
    stuck = PoseTrack(tr.t, np.tile(SURF.point_at(np.array([0.3]), np.array([0.7]))[0] - 1.0, (len(tr.t), 1)),
                      tr.quaternion)
    with pytest.raises(ResolveError, match="clear"):
        period_scenario([stuck], [0], ["ball"], np.array([1.2, 1.6]), CATALOG, GEL, SURF)


def test_densify_inserts_measured_frames_only_where_keypoints_are_far_apart():
    tr, *_ = _poke_track(depth=2.0)
    t, key = densify([tr], np.array([1.0, 1.6, 1.61]))
    assert key.sum() == 3 and len(t) >= 5 and np.all(np.diff(t) > 0)
    assert np.all(np.isin(t[~key], tr.t))                  # inserted frames are pose-sample times
    t2, key2 = densify([tr], np.array([1.0, 1.05]))
    assert len(t2) == 2 and key2.all()


def test_frame_sigma_follows_the_measured_motion_and_interp_frames():
    tr, *_ = _poke_track()
    times = np.array([1.0, 1.3, 1.6, 2.0])
    s = frame_sigma(np.array([0.5, 1.0, 1.15, 1.45, 1.8, 2.0, 2.5]), times, [tr])
    assert np.isnan(s[0]) and np.isnan(s[-1])
    np.testing.assert_allclose(s[1:6], [0.0, 0.5, 1.5, 2.5, 3.0], atol=0.03)   # hold segment: time fraction
    arr = np.arange(4.0)[:, None] * np.ones((4, 2))
    np.testing.assert_allclose(interp_frames(arr, 1.25), [1.25, 1.25])
    np.testing.assert_allclose(interp_frames(arr, 7.0), [3.0, 3.0])


def _press_then_twist():
    """Press 0.2 mm (t 0–0.2 s), hold, twist 0.06 rad about z (t 0.7–0.9 s), hold to 1.5 s: one FE segment
    from t = −0.1 to 1.0 s whose straight line in pose space the motion does not follow."""
    t = np.arange(-0.5, 1.5, 1 / 120)
    z = -0.2 * np.clip(t / 0.2, 0, 1)
    twist = 0.06 * np.clip((t - 0.7) / 0.2, 0, 1)
    q = Rotation.from_rotvec(np.column_stack([0 * t, 0 * t, twist])).as_quat(scalar_first=True)
    return PoseTrack(t, np.column_stack([0 * t, 0 * t, z]), q)


def test_frame_sigma_with_the_ft_force_places_a_hold_before_a_twist():
    tr = _press_then_twist()
    times, t = np.array([-0.1, 1.0]), np.array([0.5])
    # pose alone: (X − V0)·d / |d|² with d = (0, 0, −0.2 mm, 0, 0, 0.06 rad · 6.25 mm/rad)
    s_pose = 0.04 / (0.04 + 0.375 ** 2)
    np.testing.assert_allclose(frame_sigma(t, times, [tr]), [s_pose], atol=2e-3)
    # the FE force grows 0 → 0.6 N over the segment and the F/T already reads 0.6 N during the hold
    fe, fm = np.array([[0, 0, 0.0], [0, 0, 0.6]]), np.array([[0, 0, 0.6]])
    s = frame_sigma(t, times, [tr], force=(fm, fe), pose_sd_mm=0.05, force_sd_n=0.05)
    want = (0.04 / 0.05 ** 2 + 0.36 / 0.05 ** 2) / ((0.04 + 0.375 ** 2) / 0.05 ** 2 + 0.36 / 0.05 ** 2)
    np.testing.assert_allclose(s, [want], atol=2e-3)                  # 0.740
    s_ft = frame_sigma(t, times, [tr], force=(fm, fe), pose_sd_mm=0.05, force_sd_n=1e-3)
    np.testing.assert_allclose(s_ft, [1.0], atol=2e-3)                # a precise F/T decides
    with pytest.raises(ValueError, match="force shapes"):
        frame_sigma(t, times, [tr], force=(fm, fe[:1]))


