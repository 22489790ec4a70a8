"""The package's cluster support (tools/train/support.py): chosen on single-contact frames against the F/T."""
from types import SimpleNamespace

import numpy as np
import pytest
from tensortouch.runtime.pipeline import PipelineConfig
from tensortouch.runtime.stages.contacts import ContactConfig
from tensortouch.tools.train.support import SupportConfig, choose_support, score, support_sample
from tensortouch.tools.train.threshold import choose

S = 96


def flat_calibration():
    v, u = np.mgrid[0:S, 0:S].astype(float)
    xyz = np.stack([u * 0.2, v * 0.2, np.zeros_like(u)], -1)
    normals = np.zeros((S, S, 3))
    normals[..., 2] = 1.0
    return SimpleNamespace(surface_xyz=xyz, normals=normals, pixel_area=np.full((S, S), 0.04),
                           mask=np.ones((S, S), bool))


def contact(c=(48, 48), core=(0.0, 0.0, -0.004), tail=(0.00006, 0.0, 0.0), tail_from=12.0, tail_to=25.0):
    """Pixel forces (3, S, S): a 5 px core plus an optional weak shear ring; returns (fp, total force)."""
    v, u = np.mgrid[0:S, 0:S]
    r = np.hypot(u - c[0], v - c[1])
    fp = np.zeros((3, S, S))
    fp[:, r <= 5] = np.asarray(core)[:, None]
    ring = (r >= tail_from) & (r <= tail_to)
    fp[:, ring] = np.asarray(tail)[:, None]
    return fp, fp.reshape(3, -1).sum(1)


def sample(fp, total, c=(48, 48)):
    return {"fp": fp.astype(np.float32), "tip": np.array([c[0] * 0.2, c[1] * 0.2, 0.0]), "force": total}


def test_a_broad_shear_tail_takes_a_farther_support_and_a_compact_contact_keeps_the_default():
    cal, cc = flat_calibration(), ContactConfig()
    fp, total = contact()
    assert np.linalg.norm(total[:2]) > 0.05                      # the ring carries real shear
    cfg = SupportConfig()
    out = choose_support([sample(fp, total)] * 3, [cal] * 3, cc, cfg)
    errs = out["measured"]["support_error_n"]
    assert errs[0] > 0.05 and min(errs) < 1e-6                    # 10 px misses the ring, 30 px holds it
    assert out["support_radius_px"] == 30.0 and out["support_floor_n"] == 0.0
    fp2, total2 = contact(tail=(0.0, 0.0, 0.0))
    same = choose_support([sample(fp2, total2)], [cal], cc, cfg)
    assert (same["support_radius_px"], same["support_floor_n"]) == cfg.candidates[0]


def test_a_missed_contact_counts_its_whole_force_and_no_samples_leave_the_default():
    cal = flat_calibration()
    blank = sample(np.zeros((3, S, S)), np.array([0.0, 0.0, -1.0]))
    assert score([blank], [cal], ContactConfig(), 10, 1e-4) == pytest.approx(1.0)
    none = choose_support([], [], ContactConfig())
    assert none["support_radius_px"] is None and none["measured"]["support_frames"] == 0


def test_support_frames_have_exactly_one_indenter_in_contact():
    fp = np.zeros((3, 4, 4))
    tips = np.zeros((2, 3))
    assert support_sample(fp, tips, [[0, 0, -1.0], [0, 0, 0.01]], 0.05) is not None
    assert support_sample(fp, tips, [[0, 0, -1.0], [0, 0, -0.5]], 0.05) is None     # two contacts
    assert support_sample(fp, tips, [[0, 0, -1.0], [0, 0, -0.1]], 0.05) is None     # the other not at rest
    assert support_sample(fp, tips, [[0, 0, -0.1], [0, 0, 0.0]], 0.05) is None      # too light


def test_threshold_sweeps_without_support_frames_leave_the_support_off():
    s = {"session": "A", "rest_frames": 10, "contact_frames": 10, "rest_with_core": [1, 0],
         "contact_with_core": [10, 10]}
    from tensortouch.tools.train.threshold import ThresholdConfig
    out = choose([s], ThresholdConfig(grid=(0.001, 0.002)))
    assert out["support_radius_px"] is None and out["support_floor_n"] is None


def test_the_runtime_takes_the_support_from_the_manifest_including_a_zero_floor():
    man = {"runtime": {"contacts": {"threshold_n": 0.002, "support_radius_px": 20.0, "support_floor_n": 0.0}}}
    c = PipelineConfig.for_package(SimpleNamespace(manifest=man)).contacts
    assert (c.support_radius_px, c.support_floor_n) == (20.0, 0.0)
    old = {"runtime": {"contacts": {"threshold_n": 0.002, "support_radius_px": None}}}
    c = PipelineConfig.for_package(SimpleNamespace(manifest=old)).contacts
    assert (c.support_radius_px, c.support_floor_n) == (ContactConfig().support_radius_px, ContactConfig().support_floor_n)


def two_peaks(gap_level: float, a=(40, 48), b=(56, 48), peak=0.004):
    """Two 3 px cores joined along the row by pixels at `gap_level` (N per pixel, -z)."""
    fp = np.zeros((3, S, S))
    fp[2, b[1] - 1:b[1] + 2, a[0]:b[0] + 1] = -gap_level
    for c in (a, b):
        fp[2, c[1] - 1:c[1] + 2, c[0] - 1:c[0] + 2] = -peak
    return fp


def test_merging_joins_a_split_contact_and_keeps_two_real_contacts_apart():
    from tensortouch.tools.train.support import choose_merge, merge_counts

    cal, cc = flat_calibration(), ContactConfig(weak_threshold_n=0.0012, min_total_n=0.04)
    split = two_peaks(0.0015)                           # one contact whose field dips between two peaks
    total = split.reshape(3, -1).sum(1)
    single = [sample(split, total, c=(40, 48))] * 2
    far = two_peaks(0.0002, a=(30, 48), b=(66, 48))     # two contacts 7 mm apart, nothing between them
    two = [{"fp": far.astype(np.float32), "tips": np.array([[6.0, 9.6, 0.0], [13.2, 9.6, 0.0]])}]
    assert merge_counts(single, [cal] * 2, two, [cal], cc) == (2, 1)
    out = choose_merge(single, [cal] * 2, two, [cal], cc)
    assert out["merge_n"] == pytest.approx(0.0012)
    assert out["measured"]["merge_phantom_frames"] == [2, 0, 0] and out["measured"]["merge_two_apart_frames"] == [1, 1, 1]
    # when the "two contacts" are bridged too, merging would publish them as one: stays off
    joined = [{"fp": split.astype(np.float32), "tips": np.array([[8.0, 9.6, 0.0], [11.2, 9.6, 0.0]])}]
    assert choose_merge(single, [cal] * 2, joined, [cal], cc)["merge_n"] is None


def test_the_runtime_takes_merging_from_the_manifest():
    man = {"runtime": {"contacts": {"threshold_n": 0.002, "merge_n": 0.0012}}}
    assert PipelineConfig.for_package(SimpleNamespace(manifest=man)).contacts.merge_n == 0.0012
    assert PipelineConfig.for_package(SimpleNamespace(manifest={"runtime": {"contacts": {"merge_n": None}}})).contacts.merge_n == 0.0


def test_the_threshold_pass_measures_merging_always_and_the_support_only_on_request():
    from tensortouch.tools.train.threshold import ThresholdConfig

    cal = flat_calibration()
    fp, total = contact()
    split = two_peaks(0.0015)
    sweep = {"session": "A", "rest_frames": 10, "contact_frames": 10, "rest_with_core": [1, 0],
             "contact_with_core": [10, 10], "calibration": cal,
             "support": [sample(fp, total), sample(split, split.reshape(3, -1).sum(1), c=(40, 48))], "two": []}
    cfg = ThresholdConfig(grid=(0.0015, 0.0015))
    plain = choose([sweep], cfg)
    assert plain["support_radius_px"] is None and plain["merge_n"] is not None
    assert plain["measured"]["merge_phantom_frames"][0] == 1
    asked = choose([sweep], ThresholdConfig(grid=(0.0015, 0.0015), measure_support=True))
    assert asked["support_radius_px"] > 10.0 and "support_error_n" in asked["measured"]
    fixed = choose([sweep], ThresholdConfig(grid=(0.0015, 0.0015), support_px=20.0))
    assert (fixed["support_radius_px"], fixed["support_floor_n"]) == (20.0, 0.0)
    assert "20 px" in fixed["measured"]["support_rule"] and fixed["merge_n"] == plain["merge_n"]


def test_a_build_fixes_the_support_in_the_export_key_only_when_set():
    from tensortouch.tools.train.build import BuildConfig, stage_keys

    base, fixed = BuildConfig(), BuildConfig(support_px=20.0)
    assert stage_keys(base)["fit"] == stage_keys(fixed)["fit"]          # the weights are the same ...
    assert stage_keys(base)["export"] != stage_keys(fixed)["export"]    # ... the package is not


def gauss_pair(peaks, centres, sigma=6.0):
    """Pixel forces (3, S, S) of Gaussian presses along the row v = 48 (N per pixel, -z)."""
    v, u = np.mgrid[0:S, 0:S].astype(float)
    g = sum(p * np.exp(-((u - c) ** 2 + (v - 48) ** 2) / (2 * sigma ** 2)) for p, c in zip(peaks, centres))
    return np.stack([np.zeros_like(g), np.zeros_like(g), -g])


def test_splitting_keeps_two_joined_presses_apart_without_splitting_one_contact():
    from tensortouch.tools.train.support import SupportConfig, choose_split

    cal, cc = flat_calibration(), ContactConfig(threshold_n=0.001)
    two_fp = gauss_pair((0.006, 0.005), (36, 60))         # 24 px apart: joined at 0.0015 N, dip 0.70
    two = [{"fp": two_fp.astype(np.float32), "tips": np.array([[7.2, 9.6, 0.0], [12.0, 9.6, 0.0]])}]
    one = gauss_pair((0.006, 0.0055), (40, 56))           # one contact, a 17 % dip between its two peaks
    single = [sample(one, one.reshape(3, -1).sum(1), c=(48, 48))] * 3
    cfg = SupportConfig(split_dips=(0.0, 0.8, 0.6, 0.05))
    out = choose_split(single, [cal] * 3, two, [cal], cc, cfg)
    m = out["measured"]
    assert m["split_two_apart_frames"] == [0, 0, 1, 1]
    assert m["split_phantom_frames"][:3] == [0, 0, 0] and m["split_phantom_frames"][3] == 3   # 0.05 splits one contact
    assert out["split_dip"] == pytest.approx(0.6)           # the least splitting of the best
    # no two-contact frames: nothing to choose on, off
    assert choose_split(single, [cal] * 3, [], [], cc, cfg)["split_dip"] is None
    # the runtime reads it from the manifest
    man = {"runtime": {"contacts": {"threshold_n": 0.001, "split_dip": 0.6}}}
    assert PipelineConfig.for_package(SimpleNamespace(manifest=man)).contacts.split_dip == 0.6
