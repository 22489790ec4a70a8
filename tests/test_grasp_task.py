"""The selective grasp's task distribution (tools/grasp/task.py) and the table's pure parts: seeded
draws within bounds, hand-worked values, the fixed scene's draw unchanged."""
import numpy as np
import pytest
from tensortouch.tools.grasp.task import FIXED_DIAMETER_MM, TaskDistribution, TaskDraw, draw, factors, fixed

PAIRS = {"A+A": ("A", "A"), "A+B": ("A", "B"), "cable+rigid": ("A", "pen"), "rigid+rigid": ("pen", "pen")}


@pytest.mark.parametrize("pair", list(PAIRS.values()))
def test_draws_stay_within_the_distribution(pair):
    dist = TaskDistribution()
    seen_contacts, seen_pulled = set(), set()
    for seed in range(300):
        d = draw(dist, pair, seed)
        assert d == draw(dist, pair, seed)                       # a pure function of the seed
        assert all(abs(x) <= 5.0 for x in d.shift_mm) and abs(d.yaw_deg) <= 15.0
        for name, diam in zip(pair, d.diameters_mm):
            lo, hi = (6.0, 10.0) if name == "pen" else (1.0, 3.0)
            assert lo <= diam <= hi
        assert 0.3 <= d.pull_n <= 1.2 and abs(d.pull_tilt_deg) <= 30.0 and 0 <= d.pull_azimuth_deg <= 180
        assert 0.3 <= d.friction <= 1.0
        seen_contacts.add(d.contact)
        seen_pulled.add(d.pulled)
        if pair == ("A", "A"):
            assert d.diameters_mm[0] == d.diameters_mm[1]        # identical cables
        if pair == ("A", "B"):
            assert d.diameters_mm[0] <= d.diameters_mm[1]        # A is the thinner
    assert seen_contacts == {"soft", "stiff"} and seen_pulled == {0, 1}


def test_draws_spread_over_the_ranges():
    ds = [draw(TaskDistribution(), ("A", "pen"), s) for s in range(400)]
    pull = np.array([d.pull_n for d in ds])
    shift = np.array([d.shift_mm[0] for d in ds])
    assert pull.min() < 0.35 and pull.max() > 1.15               # half to twice today's 0.6 N
    assert shift.min() < -4.5 and shift.max() > 4.5
    assert 0.4 < np.mean([d.contact == "stiff" for d in ds]) < 0.6


def test_a_narrow_distribution_draws_its_own_values():
    dist = TaskDistribution(placement_mm=0.0, yaw_deg=0.0, cable_diameter_mm=(2.0, 2.0), pen_diameter_mm=(7.0, 7.0),
                            pull_scale=(1.5, 1.5), pull_tilt_deg=0.0, friction=(0.5, 0.5), contacts=("stiff",))
    d = draw(dist, ("A", "pen"), 11)
    assert d.shift_mm == (0.0, 0.0) and d.yaw_deg == 0.0 and d.diameters_mm == (2.0, 7.0)
    assert d.pull_n == pytest.approx(0.9) and d.friction == 0.5 and d.contact == "stiff"


def test_bad_ranges_are_refused():
    with pytest.raises(ValueError, match="friction"):
        TaskDistribution(friction=(1.0, 0.3))
    with pytest.raises(ValueError, match="contacts"):
        TaskDistribution(contacts=("jelly",))


def test_pull_direction_hand_worked():
    axis, across, normal = np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])
    d = TaskDraw(0, (0, 0), 0, (2, 2), 0.6, 30.0, 90.0, 1.0, "soft")   # tilted 30° towards the normal
    np.testing.assert_allclose(d.pull_direction(axis, across, normal), [np.sqrt(3) / 2, 0, 0.5], atol=1e-12)
    d = TaskDraw(0, (0, 0), 0, (2, 2), 0.6, -30.0, 0.0, 1.0, "soft")   # 30° the other way, across
    np.testing.assert_allclose(d.pull_direction(axis, across, normal), [np.sqrt(3) / 2, -0.5, 0], atol=1e-12)


def test_fixed_scene_is_todays_draw():
    d, jitter = fixed(("A", "pen"), 7)
    rng = np.random.default_rng(7)                               # the order the trial drew in before
    assert d.pulled == int(rng.integers(0, 2))
    np.testing.assert_array_equal(jitter, rng.uniform(-1, 1, 3) * 1.0)
    assert d.diameters_mm == (FIXED_DIAMETER_MM["A"], FIXED_DIAMETER_MM["pen"]) == (2.18, 8.0)
    assert (d.pull_n, d.pull_tilt_deg, d.friction, d.contact) == (0.6, 0.0, 1.0, "soft")


def test_factors_name_only_what_the_pair_has():
    d = TaskDraw(1, (-3.0, 2.0), -10.0, (6.5, 9.0), 0.8, -12.0, 40.0, 0.4, "stiff").as_dict()
    f = factors(d, ("pen", "pen"))
    assert f["thinnest cable (mm)"] is None and f["thickest pen (mm)"] == 9.0
    assert f["shift across, size (mm)"] == 3.0 and f["yaw, size (°)"] == 10.0 and f["pull tilt, size (°)"] == 12.0


def test_wilson_interval_hand_worked():
    pytest.importorskip("mujoco")
    from tensortouch.tools.grasp.trial import wilson

    lo, hi = wilson(17, 20)          # the seed's cable + pen: 85 %, Wilson 64.0–94.8 %
    assert lo == pytest.approx(0.6396, abs=1e-3) and hi == pytest.approx(0.9476, abs=1e-3)
    assert wilson(0, 10)[0] == 0.0 and wilson(10, 10)[1] == 1.0


def _result(pair, seed, outcome, cause, task):
    from tensortouch.tools.grasp.trial import TrialResult

    return TrialResult(pair, seed, task["pulled"], task["pulled"] if outcome == "success" else None, outcome,
                       [[1, 0], [1, 0]], 3, 1.0, cause=cause, task=task, randomized=True)


def test_tables_classify_failures_and_bin_factors(tmp_path):
    pytest.importorskip("mujoco")
    from tensortouch.tools.grasp import trial

    dist = TaskDistribution()
    causes = ["", "other object named", "no decision", "final pinch lost the pulled object",
              "final pinch's gel touches the other object"]
    res = [_result("A+B", s, "success" if s % 5 == 0 else ("false detection" if s % 5 == 1 else "other"),
                   causes[s % 5], draw(dist, ("A", "B"), s).as_dict()) for s in range(20)]
    assert [trial.failure_class(r) for r in res[:5]] == ["", "false detection", "no decision", "lost object",
                                                        "touches both"]
    t = trial.table({"A+B": res})
    assert "| different cables (A+B) | randomized | 4/20 (20 %, 8–42) | 4 | 4 | 4 | 4 | 15/20 (75 %" in t
    f = trial.factor_table({"A+B": res})
    assert "| friction (20) | " in f and "thickest pen" not in f     # no pen in A+B
    assert f.count("/4 (") == 2 * 7                                    # quintiles of 20 trials, 7 factors
    assert all(line.count("|") == 6 for line in f.splitlines())       # a cell never holds a "|"


def test_merge_joins_runs_and_refuses_a_bad_file(tmp_path, capsys):
    pytest.importorskip("mujoco")
    from tensortouch.tools.grasp import trial
    from tensortouch.tools.grasp.cli import _merge

    dist = TaskDistribution()
    for k in range(2):
        trial.save_results({"A+A": [_result("A+A", 10 * k + s, "success", "", draw(dist, ("A", "A"), s).as_dict())
                                    for s in range(3)]}, tmp_path / f"run{k}")
    assert _merge([tmp_path / "run0", tmp_path / "run1"], tmp_path / "all") == 0
    assert "6/6 (100 %" in (tmp_path / "all" / "grasp_table.md").read_text()
    capsys.readouterr()
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "grasp_trials.json").write_text("{\"A+A\": [{\"seed\": 1}]}")
    assert _merge([tmp_path / "bad"], tmp_path / "all2") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad/grasp_trials.json" in err[0]
