"""The scorecard's pure core (tools/train/scorecard.py) on hand-made values."""
from __future__ import annotations

import numpy as np
import pytest
from tensortouch.tools.train import scorecard as S


def test_direction_error_by_hand():
    d = S.direction_error_deg([[1, 0, 0], [0, 0, 2], [0, 1, 0], [0, 0, 0]], [[1, 1, 0], [0, 0, -1], [0, 3, 0], [1, 0, 0]])
    assert d[:3] == pytest.approx([45.0, 180.0, 0.0])
    assert np.isnan(d[3])


def test_poke_segments_by_hand():
    t = np.arange(12) * 0.1
    c = np.array([0, 0, 1, 1, 0, 1, 0, 0, 0, 0, 1, 0], bool)      # 0.2–0.5 (gap 0.2 s merged), 1.0
    assert S.poke_segments(t, c, merge_s=0.3).tolist() == [0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1]
    assert S.poke_segments(t, c, merge_s=0.15).tolist() == [0, 0, 0, 0, 1, 1, 2, 2, 2, 2, 2, 2]
    assert S.poke_segments(t, np.zeros(12, bool)).tolist() == [0] * 12


def test_ratio_stats_by_hand():
    # clusters: unit A pokes a1 (rows 1, 3), a2 (row 5); unit B poke b1 (row 10)
    sums, counts = np.array([4.0, 5.0, 10.0]), np.array([2.0, 1.0, 1.0])
    W = np.array([[1, 1, 1],      # everything once: (4 + 5 + 10) / 4 = 4.75
                  [2, 0, 0],      # a1 twice: 8 / 4 = 2
                  [0, 0, 2],      # b1 twice: 10
                  [0, 0, 0]])     # nothing drawn: left out
    s = S.ratio_stats(W.astype(float), sums, counts, level=0.5)
    assert s["n"] == 4 and s["mean"] == pytest.approx(4.75)
    assert s["ci"] == pytest.approx(list(np.percentile([4.75, 2.0, 10.0], [25, 75])))


def test_bootstrap_ci_fixed_seed_two_units():
    """Two units of one poke each, values 0 and 1: replicates are 0, 0.5, 1 with p = 1/4, 1/2, 1/4, so
    the 95 % interval is [0, 1] and about half the replicates sit at 0.5."""
    W = S.resample_counts([1, 1], 4000, np.random.default_rng(3))
    assert W.shape == (4000, 2) and (W.sum(1) == 2).all()
    reps = (W @ np.array([0.0, 1.0])) / (W @ np.ones(2))
    assert set(np.unique(reps)) == {0.0, 0.5, 1.0}
    assert abs((reps == 0.5).mean() - 0.5) < 0.03
    s = S.ratio_stats(W, np.array([0.0, 1.0]), np.ones(2))
    assert s["mean"] == 0.5 and s["ci"] == [0.0, 1.0]
    # pokes are redrawn inside a drawn unit only: one unit, three pokes → every replicate draws 3
    W = S.resample_counts([3, 0], 500, np.random.default_rng(0))
    assert (W.sum(1) % 3 == 0).all()


def _table():
    """Unit A: poke 0 sphere3 single 1.0 N read 0.8 N, poke 1 sphere3 + flat4 (multi) 2.0 N read 2.5 N and 0.6 N
    missed; unit B: poke 0 flat4 single 0.3 N read 0.3 N at 90°; rest frames: A 1 phantom of 2, B 0 of 2."""
    contacts = {"unit": ["A", "A", "A", "B"], "poke": [0, 1, 1, 0],
                "indenter": ["sphere3", "sphere3", "flat4", "flat4"], "n_contact": [1, 2, 2, 1],
                "meas": [[0, 0, 1.0], [0, 0, 2.0], [0, 0, 0.6], [0, 0.3, 0]], "pred": [[0, 0, 0.8], [0, 0, 2.5], [0, 0, 0], [0.3, 0, 0]],
                "miss": [False, False, True, False]}
    rest = {"unit": ["A", "A", "B", "B"], "poke": [0, 1, 0, 0], "phantom": [True, False, False, False]}
    return contacts, rest


def test_scorecard_means_and_breakdown_counts():
    card = S.scorecard(*_table(), S.ScoreConfig(n_boot=200))
    o = card["overall"]
    assert card["units"] == 2 and card["pokes"] == 3 and o["contacts"] == 4
    assert o["miss_rate"]["mean"] == pytest.approx(0.25)
    assert o["force_mae_n"]["mean"] == pytest.approx((0.2 + 0.5 + 0.0) / 3)
    assert o["force_mae_with_misses_n"]["mean"] == pytest.approx((0.2 + 0.5 + 0.6 + 0.0) / 4)
    assert o["direction_error_deg"]["mean"] == pytest.approx(30.0)
    assert o["phantom_rate"]["mean"] == pytest.approx(0.25) and o["phantom_rate"]["n"] == 4
    for s in (o["miss_rate"], o["force_mae_n"], o["phantom_rate"]):
        assert s["ci"][0] <= s["mean"] <= s["ci"][1]
    assert {k: v["contacts"] for k, v in card["by indenter"].items()} == {"flat4": 2, "sphere3": 2}
    assert card["by indenter"]["flat4"]["miss_rate"]["mean"] == 0.5
    assert card["by contacts"]["single"]["contacts"] == 2 and card["by contacts"]["multi"]["contacts"] == 2
    assert card["by contacts"]["multi"]["pokes"] == 1 and card["by contacts"]["single"]["units"] == 2
    assert {k: v["contacts"] for k, v in card["by force"].items()} == {"0.2-0.5 N": 1, "0.5-1.5 N": 2, "1.5-3 N": 1}
    assert o["force_bias_n"]["mean"] == pytest.approx((-0.2 + 0.5 + 0.0) / 3)
    assert {k: v["contacts"] for k, v in card["by indenter and contacts"].items()} == {
        "flat4, single": 1, "flat4, multi": 1, "sphere3, single": 1, "sphere3, multi": 1}
    # ceilings: unit A's best gain is 0.8 (the p-weighted median of 1.25 at 0.8 and 0.8 at 2.5): |0.64 − 1| left
    ceil = card["scale ceilings"]
    assert ceil["as scored"] == pytest.approx(0.7 / 3) and ceil["per unit"] == pytest.approx(0.36 / 3)
    assert ceil["per poke"] == pytest.approx(0.0) and ceil["per indenter and contacts"] == pytest.approx(0.0)
    # the field split at the tips is scored on every contact (misses too); n 0 where no split was given
    assert o["split_force_mae_n"]["n"] == 0
    c, r = _table()
    c["split"] = [[0, 0, 1.1], [0, 0, 1.0], [0, 0, 0.4], [0, 0.3, 0]]
    card = S.scorecard(c, r, S.ScoreConfig(n_boot=50))
    assert card["overall"]["split_force_mae_n"]["mean"] == pytest.approx((0.1 + 1.0 + 0.2 + 0.0) / 4)
    assert card["by contacts"]["multi"]["split_force_mae_n"]["n"] == 2
    # below the contact threshold a row is not scored
    card = S.scorecard(*_table(), S.ScoreConfig(n_boot=50, contact_n=0.5))
    assert card["overall"]["contacts"] == 3


def test_best_gain_is_the_weighted_median_ratio():
    assert S.best_gain(np.array([1.0, 1, 1]), np.array([1.0, 2, 3])) == 2.0
    assert S.best_gain(np.array([0.8, 2.5]), np.array([1.0, 2.0])) == pytest.approx(0.8)
    assert S.best_gain(np.array([0.0]), np.array([1.0])) == 1.0          # nothing read: no gain to fit
    p, m = np.array([0.5, 1.0, 2.0, 4.0]), np.array([0.7, 0.9, 2.6, 3.0])
    g = S.best_gain(p, m)
    grid = np.linspace(0.5, 2.0, 1501)
    assert np.abs(g * p - m).sum() <= np.abs(grid[:, None] * p - m).sum(1).min() + 1e-9
    with pytest.raises(ValueError, match="two"):
        S.best_gain(p, m[:3])


def test_session_table_from_evaluation_rows():
    frames = [{"frame": i, "t": 0.1 * i, "fields": True, "meas_mags": m, "cluster_forces": c}
              for i, (m, c) in enumerate([([0.0, 0.0], [0.08]), ([1.0, 0.0], [0.9]), ([1.0, 0.5], [0.9]),
                                          ([0.1, 0.0], []), ([0.0, 0.0], []), ([0.0, 0.0], [0.01]),
                                          ([0.0, 0.4], [0.5])])]
    rows = [{"frame": 1, "indenter": 0, "meas_force": [0, 0, 1.0], "pred_force": [0, 0, 0.9], "miss": False},
            {"frame": 2, "indenter": 0, "meas_force": [0, 0, 1.0], "pred_force": [0, 0, 0.9], "miss": False},
            {"frame": 2, "indenter": 1, "meas_force": [0, 0, 0.5], "pred_force": [0, 0, 0], "miss": True},
            {"frame": 6, "indenter": 1, "meas_force": [0, 0.4, 0], "pred_force": [0, 0.5, 0], "miss": False,
             "split_force": [0, 0.45, 0]}]
    c, r = S.session_table("U", {"frames": frames, "rows": rows}, {0: "sphere3", 1: "flat4"})
    assert c["poke"] == [0, 0, 0, 1] and c["n_contact"] == [1, 2, 2, 1]
    assert c["indenter"] == ["sphere3", "sphere3", "flat4", "flat4"]
    assert np.isnan(c["split"][0]).all() and c["split"][3] == [0, 0.45, 0]
    assert r["poke"] == [0, 1, 1] and r["phantom"] == [True, False, False]      # frame 3 (0.1 N) is no rest frame


def test_fit_seed_spread_by_hand():
    hs = [{"force_mae_n": v, "miss_rate": 0.1} for v in (0.2, 0.3, 0.4)]
    s = S.fit_seed_spread(hs)
    assert s["force_mae_n"]["mean"] == pytest.approx(0.3) and s["force_mae_n"]["sd"] == pytest.approx(0.1)
    assert s["force_mae_n"]["min"] == 0.2 and s["force_mae_n"]["max"] == 0.4 and s["miss_rate"]["sd"] == pytest.approx(0.0)
