"""Stage 1 (seed §III.C): contact detection and keypoints on synthetic trajectories with known events."""
import numpy as np
import pytest
from tensortouch.tools.train.keypoints import (
    KeypointConfig,
    detect_contacts,
    extract_keypoints,
    find_keypoints,
    merge_intervals,
    relative_pose,
    smooth,
)

CFG = KeypointConfig()


def test_dual_threshold_hysteresis_and_pre_contact():
    t = np.arange(0, 5, 0.005)
    f = np.zeros_like(t)
    f[(t >= 1.0) & (t < 3.0)] = 1.3          # above exit but below entry: no contact on its own
    f[(t >= 1.5) & (t < 1.6)] = 1.6          # crosses entry at t = 1.5
    f[(t >= 2.5) & (t < 3.0)] = 1.15          # dips but stays above 1.1: still in contact
    # falls to 0 at t = 3.0 -> contact ends there
    ivs = detect_contacts(t, f, CFG)
    assert len(ivs) == 1
    start, end, on = ivs[0]
    assert on == pytest.approx(1.5, abs=0.006)
    assert start == pytest.approx(1.5 - CFG.pre_contact_s, abs=0.006)
    assert end == pytest.approx(3.0, abs=0.006)


def test_pre_contact_clipped_and_open_end():
    t = np.linspace(0, 1, 201)
    f = np.where(t > 0.1, 2.0, 0.0)
    (start, end, on), = detect_contacts(t, f, CFG)
    assert start == t[0] and end == t[-1] and on == pytest.approx(0.1, abs=0.006)


def test_merge_intervals_multi_indenter():
    per = {0: [(0.0, 1.0, 0.3), (5.0, 6.0, 5.3)], 1: [(0.8, 2.0, 1.1)], 2: [(3.0, 4.0, 3.3)]}
    periods = merge_intervals(per)
    assert [(p.t_start, p.t_end, p.indenters) for p in periods] == [
        (0.0, 2.0, (0, 1)), (3.0, 4.0, (2,)), (5.0, 6.0, (0,))]
    assert periods[0].t_contact == 0.3


def test_relative_pose_rotation_about_z():
    ang = np.linspace(0, 0.4, 5)
    q = np.stack([np.cos(ang / 2), 0 * ang, 0 * ang, np.sin(ang / 2)], 1)
    # start from a tilted pose: the relative rotation is still about the body z axis
    tilt = np.array([np.cos(0.3), np.sin(0.3), 0, 0])
    def mul(a, b):
        w1, x1, y1, z1 = a; w2, x2, y2, z2 = b.T
        return np.stack([w1*w2-x1*x2-y1*y2-z1*z2, w1*x2+x1*w2+y1*z2-z1*y2,
                         w1*y2-x1*z2+y1*w2+z1*x2, w1*z2+x1*y2-y1*x2+z1*w2], 1)
    pos = np.stack([ang, 2 * ang, 0 * ang], 1) + 7.0
    rel = relative_pose(pos, mul(tilt, q), CFG)
    np.testing.assert_allclose(rel[:, :3], np.stack([ang, 2 * ang, 0 * ang], 1), atol=1e-12)
    np.testing.assert_allclose(rel[:, 5], ang, atol=1e-9)
    np.testing.assert_allclose(rel[:, 3:5], 0, atol=1e-9)


def test_smooth_is_order_one_at_fs_over_3():
    fs = 120.0
    t = np.arange(0, 4, 1 / fs)
    slow = np.sin(2 * np.pi * 1.0 * t)
    fast = 0.5 * np.sin(2 * np.pi * 55.0 * t)     # above fc = 40 Hz
    y = smooth((slow + fast)[:, None], fs, CFG)[:, 0]
    inner = slice(60, -60)
    assert np.abs(y - slow)[inner].max() < 0.3     # fast part attenuated (order 1: gently)
    assert np.abs(y - slow)[inner].max() < np.abs(fast).max() * 0.6
    assert np.abs(smooth(slow[:, None], fs, CFG)[:, 0] - slow)[inner].max() < 0.01  # no lag, no loss


def _press_slide(t0=0.0, fs=120.0, depth=3.0, slide=1.5, noise=0.0, seed=0):
    """Indenter: approach, press to `depth` (peak at t0+2), slide +x to `slide` (peak at t0+3.5), back
    (trough at t0+5), release. Returns poses/wrench tables and the known event times."""
    rng = np.random.default_rng(seed)
    t = np.arange(t0, t0 + 8.0, 1 / fs)
    s = t - t0
    z = -depth * np.clip(np.minimum(s - 0.5, 7.0 - s) / 1.5, 0, 1)        # plateau from 2.0 to 5.5
    x = slide * np.interp(s, [0, 2.5, 3.5, 5.0, 6.0, 8.0], [0, 0, 1, -0.5, 0, 0])
    pos = np.stack([x, 0 * x, 10.0 + z], 1) + noise * rng.standard_normal((t.size, 3))
    quat = np.tile([1.0, 0, 0, 0], (t.size, 1))
    tw = np.arange(t0, t0 + 8.0, 1 / 200.0)
    depth_w = np.interp(tw, t, -z)
    fz = 1.6 * depth_w                                               # 1.5 N at ~0.94 mm
    wrench = np.zeros((tw.size, 8)); wrench[:, 0] = tw; wrench[:, 4] = fz
    poses = np.zeros((t.size, 9)); poses[:, 0] = t; poses[:, 2:5] = pos; poses[:, 5:9] = quat
    events = {"slide_peak": t0 + 3.5, "slide_trough": t0 + 5.0}
    return poses, wrench, events


def test_extract_keypoints_finds_known_events():
    poses, wrench, ev = _press_slide(noise=0.01)
    frames = np.stack([np.arange(0, 8, 1 / 30), np.arange(240)], 1)
    kps = extract_keypoints(poses, wrench, frames, CFG)
    assert len(kps) == 1
    kp = kps[0]
    t_on = 0.5 + 1.5 * (1.5 / 1.6) / 3.0
    assert kp.period.t_start == pytest.approx(t_on - CFG.pre_contact_s, abs=0.02)
    assert kp.t[0] == pytest.approx(kp.period.t_start, abs=1 / 120)
    assert kp.t[-1] == pytest.approx(kp.period.t_end, abs=1 / 120)
    for name, te in ev.items():
        assert np.min(np.abs(kp.t - te)) < 0.1, f"{name} at {te} s not among keypoints {kp.t}"
    assert len(kp.t) <= CFG.max_keypoints
    assert np.all(np.diff(kp.t) >= CFG.min_spacing_s - 1e-9)
    # the slide peak keypoint holds the peak displacement and the force there
    i = int(np.argmin(np.abs(kp.t - ev["slide_peak"])))
    assert kp.rel_pose[i, 0, 0] == pytest.approx(1.5, abs=0.05)
    assert kp.force[i, 0, 2] == pytest.approx(1.6 * 3.0, abs=0.05)
    assert kp.frame_index[i] == int(round(kp.t[i] * 30))


def test_cap_prefers_large_motion():
    t = np.linspace(0, 10, 1201)
    # many small wiggles plus one big excursion at t = 7
    x = 0.3 * np.sin(2 * np.pi * 1.0 * t) + 3.0 * np.exp(-((t - 7) / 0.2) ** 2)
    sig = np.zeros((t.size, 6)); sig[:, 0] = x
    cfg = KeypointConfig(max_keypoints=4)
    idx = find_keypoints(t, sig, cfg)
    assert len(idx) == 4 and idx[0] == 0 and idx[-1] == t.size - 1
    assert np.min(np.abs(t[idx] - 7.0)) < 0.02
    uncapped = find_keypoints(t, sig, KeypointConfig(max_keypoints=100))
    assert len(uncapped) > 10          # the wiggles are real peaks when not capped


def test_two_indenters_overlapping_merge_into_one_period():
    p0, w0, _ = _press_slide(t0=0.0)
    p1, w1, _ = _press_slide(t0=3.0)
    p1[:, 1] = 1; w1[:, 1] = 1
    p0 = np.concatenate([p0, p0[-1:] + [[1 / 120] + [0] * 8]])  # extend so clocks differ slightly
    kps = extract_keypoints(np.concatenate([p0, p1]), np.concatenate([w0, w1]), None, CFG)
    assert len(kps) == 1
    kp = kps[0]
    assert kp.period.indenters == (0, 1)
    assert kp.position.shape == (len(kp.t), 2, 3)
    # indenter 1's slide peak (t = 6.5) is a keypoint too
    assert np.min(np.abs(kp.t - 6.5)) < 0.1
    assert np.all(kp.frame_index == -1)


def test_find_keypoints_rejects_bad_shape():
    with pytest.raises(ValueError):
        find_keypoints(np.arange(10.0), np.zeros((10, 5)))
