"""Pieces of the twin acceptance benchmark (tools/recalib/twin_bench.py) that run without FE or a
trained model: guided spots on the nominal twin calibration, the correction replayed on recorded
clusters (= the runtime's gain, zero stays zero), held-out poke pairing, the recording configs."""
import numpy as np
import pytest
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.stages.contacts import Cluster
from tensortouch.tools.recalib.fit import fit_correction
from tensortouch.tools.recalib.pokes import PokeRules
from tensortouch.tools.recalib.session import StreamReference
from tensortouch.tools.recalib.synthetic import SyntheticUnit
from tensortouch.tools.recalib.twin_bench import (
    UNITS,
    TwinBenchConfig,
    corrected_frames,
    guided_points,
    held_out_pokes,
    nominal_calibration,
    record_configs,
)

from tests.conftest import dome_calibration


@pytest.fixture(scope="module")
def nominal():
    return nominal_calibration(64)


def test_guided_spots_apex_first_spread_and_within_reach(nominal):
    tables, meta = nominal
    reach = np.radians(31.5)
    pts = np.array(guided_points(tables, 7, reach))
    theta = np.arctan2(np.hypot(pts[:, 0], pts[:, 1]), pts[:, 2] - meta["gel"]["center_z_mm"])
    assert theta[0] < 0.05 and np.all(theta <= reach + 0.03)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(7) * 1e3
    assert d.min() >= PokeRules().min_separation_mm


def test_record_configs_units_and_held_out_sets():
    cfg = TwinBenchConfig()
    fit, held = record_configs(UNITS[0], cfg, [[0.0, 0.0, 8.0]] * 3, 128)
    assert fit.guided.indenter == cfg.probe and fit.unit["stiffness_scale"] == UNITS[0].stiffness_scale
    assert set(held) == {"probe", "other"}                   # TWIN-R001 is in other_units
    assert held["probe"].trajectory.indenters == ("sphere5",) and held["probe"].trajectory.p_two == 0
    _, held = record_configs(UNITS[2], cfg, [[0.0, 0.0, 8.0]] * 3, 128)
    assert set(held) == {"probe"}
    assert len({u.serial for u in UNITS}) == len(UNITS) >= 5
    assert all(0.75 <= u.stiffness_scale <= 1.25 and abs(u.stiffness_scale - 1) >= 0.1 for u in UNITS)


def _cluster(u, v, f, mm=(0.0, 0.0, 8.0)):
    f = np.asarray(f, float)
    return Cluster(id=0, uv_px=(u, v), position_mm=tuple(mm), normal=(0, 0, 1), area_mm2=1.0,
                   force_n=tuple(f), force_mag_n=float(np.linalg.norm(f)), pixels=1, perimeter_px=0.0,
                   circularity=1.0)


def test_replayed_correction_is_the_runtime_gain_and_keeps_zero(tmp_path):
    from tensortouch.runtime.stages.correction import ForceCorrection
    from tensortouch.runtime.stages.geometry import sample_bilinear
    from tensortouch.tools.recalib.store_ops import store_recalibration

    dome_calibration(tmp_path, "TT-B", size=32)
    store = CalibrationStore(tmp_path)
    cal = store.load("TT-B")
    fit = fit_correction(SyntheticUnit(1.3, (0.05, 0.0), 0.3).guided_pokes(np.random.default_rng(0), 6))
    store_recalibration(store, cal, {"pokes": 6}, correction=(fit.spec, fit.onnx_bytes))
    cal2 = store.load("TT-B")
    frames = [(0.0, [_cluster(10.0, 12.0, [0.1, 0.2, -1.5]), _cluster(20.0, 16.0, [0.0, 0.0, 0.0])]),
              (0.1, [])]
    out = corrected_frames(frames, cal2)
    corr = ForceCorrection.from_calibration(cal2)
    c = frames[0][1][0]
    tp = [[sample_bilinear(cal2.theta, c.uv_px[0] - 0.5, c.uv_px[1] - 0.5),
           sample_bilinear(cal2.phi, c.uv_px[0] - 0.5, c.uv_px[1] - 0.5)]]
    expect = corr(np.array([c.force_n]), np.array([c.uv_px]) / 32.0, np.array(tp))[0]
    np.testing.assert_allclose(out[0][1][0].force_n, expect)
    assert not np.allclose(expect, c.force_n)                  # the gain really changed the force
    assert out[0][1][1].force_n == (0.0, 0.0, 0.0) and out[0][1][1].force_mag_n == 0.0
    assert frames[0][1][0].force_n == c.force_n and out[1] == (0.1, [])   # input untouched


def test_held_out_pokes_pairs_single_contact_episodes_with_the_stream():
    rules = PokeRules()
    frames, t = [], 0.0
    for amp, second in ((1.0, 0.0), (2.0, 0.0), (1.5, 0.8)):      # the third poke has a 2nd contact
        for k in range(30):                                          # 8 frames of contact, 0.7 s apart
            cl = [_cluster(30, 30, [0, 0, -amp])] + ([_cluster(5, 5, [0, 0, -amp * second], (-6.0, -6.0, 6.0))]
                                                     if second else [])              # 10 mm away: a 2nd contact
            frames.append((t, cl if 2 <= k < 10 else []))
            t += 1 / 30
    ts = np.array([f[0] for f in frames])
    ref_mag = np.array([1.2 * sum(c.force_mag_n for c in cl[:1]) for _, cl in frames])
    ref = StreamReference(ts, np.column_stack([np.zeros_like(ts), np.zeros_like(ts), ref_mag]), rules=rules)
    m = held_out_pokes(frames, ref, rules, by="detected")
    np.testing.assert_allclose(m["pred"], [1.0, 2.0])
    np.testing.assert_allclose(m["ref"], [1.2, 2.4])


def test_held_out_pokes_are_the_gauges_so_a_missed_poke_counts_with_zero():
    """Default pairing: one row per reference poke, whatever the sensor saw; the sensor missed the 2nd poke,
    split the 3rd into two parts 2 mm apart (summed) and saw a far 2nd contact on the 4th (not counted)."""
    rules = PokeRules()
    frames, ts, ref_mag, t = [], [], [], 0.0
    for k, amp in enumerate((1.0, 2.0, 1.5, 0.8)):
        for i in range(30):
            on = 5 <= i < 20
            if not on or k == 1:
                cl = []
            elif k == 2:
                cl = [_cluster(30, 30, [0, 0, -amp / 2]), _cluster(31, 30, [0, 0, -amp / 2], (2.0, 0.0, 6.0))]
            elif k == 3:
                cl = [_cluster(30, 30, [0, 0, -amp]), _cluster(5, 5, [0, 0, -0.5], (-6.0, -6.0, 6.0))]
            else:
                cl = [_cluster(30, 30, [0, 0, -amp])]
            frames.append((t, cl))
            ts.append(t)
            ref_mag.append(1.1 * amp if on else 0.0)
            t += 1 / 30
    ts = np.array(ts)
    ref = StreamReference(ts, np.column_stack([np.zeros_like(ts), np.zeros_like(ts), ref_mag]), rules=rules)
    m = held_out_pokes(frames, ref, rules)
    np.testing.assert_allclose(m["ref"], [1.1, 2.2, 1.65, 0.88])
    np.testing.assert_allclose(m["pred"], [1.0, 0.0, 1.5, 0.8])
    assert len(held_out_pokes(frames, ref, rules, by="detected")["ref"]) == 2   # detection drops the miss and the 2-contact poke
