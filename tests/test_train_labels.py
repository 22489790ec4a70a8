"""Frame labels of the re-solved path (tools/train/labels.py): contact, busy and rest frames, keypoint
share, checked frames, sigma words."""
import numpy as np
import pytest
from tensortouch.tools.train.labels import BUSY_ID, frame_labels, keypoint_frame_share
from tensortouch.tools.train.resolve import (
    interp_frames,
)

from tests.test_train_stage2_resolve import _poke_track


def test_frame_labels_contact_busy_rest_and_keypoint_share():
    from types import SimpleNamespace

    tr, *_ = _poke_track()
    frame_t = np.arange(0.0, 3.2, 1 / 30)
    src = SimpleNamespace(times=np.array([1.2, 1.4, 1.6, 2.0, 2.2]), t_init=0.97, slots=[0],
                          is_keypoint=np.array([True, False, True, True, True]))
    f = np.interp(frame_t, [0, 1.0, 1.6, 2.0, 2.5, 3.2], [0, 0, 3.0, 3.0, 0, 0])
    wrench = np.column_stack([frame_t, np.zeros_like(frame_t), np.zeros_like(frame_t), np.zeros_like(frame_t), -f,
                              np.zeros((len(frame_t), 3))])
    lab, sig = frame_labels(frame_t, [src], {0: tr}, wrench)
    inside = (frame_t >= 1.2) & (frame_t <= 2.2)
    assert np.all(lab[inside] == 0) and np.all(np.isfinite(sig[inside])) and np.all(np.isnan(sig[~inside]))
    assert np.all(lab[(frame_t > 0.98) & (frame_t < 1.19)] >= BUSY_ID)     # initial pose → first frame
    assert np.all(lab[(frame_t > 2.21) & (frame_t < 2.45)] >= BUSY_ID)     # light contact after the period
    assert np.all(lab[(frame_t < 0.95) | (frame_t > 2.55)] == -1)
    share = keypoint_frame_share(frame_t, lab, [src])
    assert share["labelled_frames"] == inside.sum() and share["at_keypoint"] == 4 and share["at_fe_frame"] == 5
    from tensortouch.tools.train.labels import LabelConfig

    lab2, _ = frame_labels(frame_t, [src], {0: tr}, wrench, lcfg=LabelConfig(frames="keypoint"))
    assert (lab2 == 0).sum() == 4
    lab3, _ = frame_labels(frame_t, [src], {0: tr}, wrench, lcfg=LabelConfig(frames="fe"))
    assert (lab3 == 0).sum() == 5                       # no interpolated label between FE frames
    assert np.all(lab3[inside & (lab3 != 0)] >= BUSY_ID)   # the others in the span: neither contact nor rest
    with pytest.raises(ValueError, match="LabelConfig.frames"):
        LabelConfig(frames="between")


def test_checked_frames_keeps_interpolated_labels_as_good_as_the_fe_frames():
    from tensortouch.tools.train.labels import checked_frames

    # FE-frame residuals 0.1, 0.2, 0.3, 0.4 N: their 0.5 quantile is 0.25 N (linear between 0.2 and 0.3)
    r = np.array([0.1, 0.2, 0.3, 0.4, 0.24, 0.26, 0.9, 0.0])
    at = np.array([1, 1, 1, 1, 0, 0, 0, 0], bool)
    np.testing.assert_array_equal(checked_frames(r, at, 0.5), [1, 1, 1, 1, 1, 0, 0, 1])
    np.testing.assert_array_equal(checked_frames(r, at, 1.0), [1, 1, 1, 1, 1, 1, 0, 1])   # up to the worst, 0.4
    np.testing.assert_array_equal(checked_frames(r[4:], at[4:], 0.9), [0, 0, 0, 0])       # nothing to compare with
    with pytest.raises(ValueError, match="same \\(n,\\) shape"):
        checked_frames(r, at[:3], 0.5)
    with pytest.raises(ValueError, match="quantile"):
        checked_frames(r, at, 0.0)


def test_frame_labels_checked_drops_interpolated_frames_the_ft_contradicts():
    from types import SimpleNamespace

    from tensortouch.tools.train.labels import LabelConfig

    tr, *_ = _poke_track()
    frame_t = np.arange(0.0, 3.2, 1 / 30)
    times = np.array([1.2, 1.4, 1.6, 2.0, 2.2])
    rf = np.zeros((5, 1, 3))
    rf[:, 0, 2] = [-0.5, -1.5, -3.0, -3.0, -1.0]        # FE reactions at the FE frames
    src = SimpleNamespace(times=times, t_init=0.97, slots=[0], is_keypoint=np.ones(5, bool),
                          result=SimpleNamespace(RF=rf))
    wrench = np.column_stack([frame_t, np.zeros((len(frame_t), 3)), -np.ones_like(frame_t), np.zeros((len(frame_t), 3))])
    ratios = {0: {"ratio": [1.0, 1.0, 1.0]}}
    lab_i, sig = frame_labels(frame_t, [src], {0: tr}, wrench)
    fe_lab = np.array([interp_frames(rf[:, 0], s)[2] if np.isfinite(s) else 0.0 for s in sig])
    meas = np.zeros((len(frame_t), 3))
    meas[:, 2] = fe_lab + 0.05                        # the F/T agrees with every label to 0.05 N ...
    bad = np.flatnonzero((frame_t > 1.7) & (frame_t < 1.9))
    meas[bad, 2] += 0.5                               # ... except during the hold, where it reads 0.5 N more
    lcfg = LabelConfig(frames="checked")
    lab, sig2 = frame_labels(frame_t, [src], {0: tr}, wrench, lcfg=lcfg, measured={0: meas}, ratios=ratios)
    assert np.all(lab[bad] >= BUSY_ID) and np.all(np.isnan(sig2[bad]))       # dropped: neither contact nor rest
    keep = (lab_i == 0) & ~np.isin(np.arange(len(frame_t)), bad)
    assert np.all(lab[keep] == 0)
    np.testing.assert_allclose(sig2[keep], sig[keep])                         # σ stays the pose's
    with pytest.raises(ValueError, match="needs the measured F/T"):
        frame_labels(frame_t, [src], {0: tr}, wrench, lcfg=lcfg)


def test_label_config_checks_the_sigma_word():
    from tensortouch.tools.train.labels import LabelConfig

    with pytest.raises(ValueError, match="LabelConfig.sigma: expected one of pose\\+ft, pose"):
        LabelConfig(sigma="force")


def test_near_times_and_half_period_by_hand():
    from tensortouch.tools.train.labels import half_period, near_times

    assert half_period(np.array([0.0, 0.1, 0.2, 0.4])) == pytest.approx(0.05) and half_period(np.array([1.0])) == 0.0
    t = np.array([0.0, 0.1, 0.2, 0.31, 0.5])
    np.testing.assert_array_equal(near_times(t, [0.3, 0.05], 0.02), [False, False, False, True, False])
    np.testing.assert_array_equal(near_times(t, [0.3, 0.05], 0.05), [True, True, False, True, False])   # ties count
    np.testing.assert_array_equal(near_times(t, [0.2], 0.1), [False, True, True, False, False])
    assert not near_times(t, [], 1.0).any()
