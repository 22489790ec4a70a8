"""Poke detection, acceptance rules and position suggestions (pure cores)."""
import numpy as np
import pytest
from tensortouch.runtime.stages.contacts import Cluster
from tensortouch.tools.recalib.pokes import (
    Poke,
    PokeDetector,
    PokeRules,
    ascii_map,
    check_poke,
    describe,
    reference_from_readings,
    suggest_next,
)
from tensortouch.tools.recalib.synthetic import SyntheticUnit


def cl(f, uv=(16.0, 16.0), xyz=(0.0, 0.0, 16.0)):
    return Cluster(id=-1, uv_px=uv, position_mm=xyz, normal=(0, 0, 1), area_mm2=1.0, force_n=(0.0, 0.0, -f),
                   force_mag_n=f, pixels=5, perimeter_px=8.0, circularity=0.9)


def run(detector, frames):
    out = []
    for t, clusters in frames:
        p = detector.feed(t, clusters)
        if p is not None:
            out.append(p)
    return out


def ramp(t0, peak, uv=(16.0, 16.0), xyz=(0.0, 0.0, 16.0), extra=None, dt=0.02):
    prof = np.r_[np.linspace(0.1, peak, 10), np.full(10, peak), np.linspace(peak, 0.1, 5)]
    frames = [(t0 + i * dt, [cl(f, uv, xyz)] + ([extra(f)] if extra else [])) for i, f in enumerate(prof)]
    return frames + [(t0 + (len(prof) + k) * dt, []) for k in range(4)]


def test_detector_finds_plateau_force_and_position():
    pokes = run(PokeDetector(), ramp(0.0, 2.0, uv=(10.0, 20.0)) + ramp(1.0, 1.0, uv=(25.0, 5.0)))
    assert len(pokes) == 2
    assert pokes[0].pred_mag == pytest.approx(2.0, rel=0.03) and np.allclose(pokes[0].uv_px, [10, 20])
    assert pokes[1].pred_mag == pytest.approx(1.0, rel=0.03)
    assert pokes[0].t0 == 0.0 and pokes[0].frames == 25


def test_tap_is_ignored_and_flush_closes_open_episode():
    d = PokeDetector()
    taps = [(0.0, [cl(1.0)]), (0.02, [cl(1.0)])] + [(0.04 + 0.02 * k, []) for k in range(4)]
    assert run(d, taps) == []
    run(d, ramp(1.0, 1.5)[:20])
    p = d.flush()
    assert p is not None and p.pred_mag == pytest.approx(1.5, rel=0.03)


def _poke(f=2.0, ref=2.2, xyz=(0.0, 0.0, 16.0), second=0.0):
    return Poke(0, 1, 20, np.array([0, 0, -f]), np.array([16.0, 16.0]), np.array(xyz), second, ref)


def test_rules_accept_and_reject_with_reasons():
    assert check_poke(_poke(), []) == ""
    assert check_poke(_poke(f=0.1), []).startswith("too light: the sensor saw 0.10 N")
    assert check_poke(_poke(ref=0.1), []).startswith("too light: the gauge read 0.10 N")
    assert check_poke(_poke(ref=None), []).startswith("no reference force")
    assert check_poke(_poke(f=30, ref=30), []).startswith("too hard")
    near = check_poke(_poke(xyz=(1.0, 1.0, 15.9)), [_poke()])
    assert near.startswith("too close to accepted poke 1 (1.4 mm apart")
    assert check_poke(_poke(xyz=(8.0, 0.0, 13.9)), [_poke()]) == ""


def test_two_fingers_are_not_a_single_contact():
    two = ramp(0.0, 2.0, extra=lambda f: cl(0.5 * f, uv=(5.0, 5.0), xyz=(10.0, 0.0, 12.0)))
    p = run(PokeDetector(), two)[0]
    assert p.second_ratio == pytest.approx(0.5, rel=0.01)
    assert check_poke(_with_ref(p, 2.0), []).startswith("not a single contact")
    weak_second = run(PokeDetector(), ramp(0.0, 2.0, extra=lambda f: cl(0.05 * f, uv=(5.0, 5.0))))[0]
    assert check_poke(_with_ref(weak_second, 2.0), []) == ""


def _with_ref(p, ref):
    p.ref_force_n = ref
    return p


def test_reference_is_plateau_mean_and_latency_tolerant():
    t = np.arange(0, 1.0, 0.01)
    f = np.clip(np.minimum(t - 0.2, 0.8 - t) * 10, 0, 2.0)      # trapezoid to 2 N
    assert reference_from_readings(t, f, 0.2, 0.8) == pytest.approx(2.0, rel=0.05)
    assert reference_from_readings(t + 0.1, f, 0.2, 0.8) == pytest.approx(2.0, rel=0.05)  # 100 ms late gauge
    assert reference_from_readings(t, f, 5.0, 6.0) is None


def test_suggestions_spread_over_the_gel():
    tab = SyntheticUnit(size=32).tables()
    acc, uvs = [], []
    for _ in range(7):
        uv, xyz = suggest_next(tab["mask"], tab["theta"], tab["surface_xyz"], acc)
        acc.append(xyz)
        uvs.append(uv)
    d = np.linalg.norm(np.array(acc)[:, None] - np.array(acc)[None], axis=-1)
    assert d[np.triu_indices(7, 1)].min() > 8.0                      # mm apart on a 16 mm dome
    theta = [tab["theta"][int(v), int(u)] for u, v in uvs]
    assert theta[0] < np.deg2rad(10) and max(theta) < 0.86 * np.deg2rad(90)
    assert all(PokeRules().min_separation_mm < x for x in d[np.triu_indices(7, 1)])
    assert describe(uvs[0], (32, 32), tab["theta"], tab["mask"]).startswith("on the top")
    assert "o'clock" in describe(uvs[1], (32, 32), tab["theta"], tab["mask"])
    m = ascii_map((32, 32), tab["mask"], uvs[:3], uvs[3])
    assert m.count("o") == 3 and m.count("X") == 1


def test_one_contact_split_in_two_clusters_is_one_poke_with_the_summed_force():
    # the model split one probe's patch: a 0.8 × part 2 mm away → one contact of 1.8 × the main force
    split = ramp(0.0, 1.0, uv=(16.0, 16.0), xyz=(0.0, 0.0, 16.0),
                 extra=lambda f: cl(0.8 * f, uv=(17.0, 16.0), xyz=(2.0, 0.0, 16.0)))
    (p,) = run(PokeDetector(), split)
    assert p.second_ratio == 0.0 and p.pred_mag == pytest.approx(1.8, rel=0.03)
    assert 0.0 < p.xyz_mm[0] < 2.0                    # force-weighted between the parts
    p.ref_force_n = 1.8
    assert check_poke(p, []) == ""
    # a second probe 10 mm away is still a second contact
    two = ramp(0.0, 1.0, extra=lambda f: cl(0.8 * f, uv=(24.0, 16.0), xyz=(10.0, 0.0, 16.0)))
    (q,) = run(PokeDetector(), two)
    assert q.second_ratio == pytest.approx(0.8) and q.pred_mag == pytest.approx(1.0, rel=0.03)
    q.ref_force_n = 1.0
    assert check_poke(q, []).startswith("not a single contact")
    # merging off (radius 0): the split patch is refused as before
    (r,) = run(PokeDetector(PokeRules(merge_radius_mm=0.0)), split)
    assert r.second_ratio == pytest.approx(0.8)
