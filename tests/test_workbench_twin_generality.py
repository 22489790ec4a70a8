"""The twin generality harness (tools/accept/twin_generality.py): its hidden forms act on the F/T
stream only, scale with their amplitude, and the drag opposes the indenter's motion; altering a
loaded session in memory gives the table of the altered copy; one diagnosed case end to end (slow)."""
import numpy as np
import pytest
from tensortouch.contracts.session import load_session
from tensortouch.tools.accept.alter_forms import FORMS, alter, contribution

GEL = {"radius": 14.0, "center_z": -4.0, "skirt": 1.5}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from dataclasses import replace

    from tensortouch.tools.twin.record import RecordConfig, record

    cfg = RecordConfig(serial="TWIN-GTEST", pokes=8, seed=11, physics="hertz-fallback", frame_format="png",
                       model_size=32)
    cfg.rig = replace(cfg.rig, camera_fps=2.0, temperature_drift_c_per_s=0.3)
    return record(cfg, tmp_path_factory.mktemp("tw") / "s")


def _gel(session):
    from tensortouch.tools.twin.unit import TwinUnit

    g = TwinUnit("TWIN-GTEST").gel
    return {"radius": g.profile.radius_mm, "center_z": g.profile.center_z_mm, "skirt": g.skirt}


@pytest.mark.parametrize("form", FORMS)
def test_each_form_changes_the_force_and_grows_with_its_amplitude(session, form):
    s = load_session(session, check_frames=False)
    f = s.table("wrench")[:, 2:5]
    gel = _gel(session)
    one = contribution(s, form, 0.2, gel) - f
    two = contribution(s, form, 0.4, gel) - f
    assert np.sqrt(np.mean(one ** 2)) > 1e-4
    # contact loss makes relaxation non-linear in its amplitude; the exponential softening is so by its form
    if form not in ("two_term_relaxation", "exp_temperature"):
        np.testing.assert_allclose(two, 2 * one, atol=1e-9)
    else:
        assert np.sqrt(np.mean(two ** 2)) > np.sqrt(np.mean(one ** 2))


def test_the_drag_opposes_the_motion_and_only_the_force_columns_change(session, tmp_path):
    from tensortouch.tools.accept.alter import _quat_matrix
    from tensortouch.tools.accept.alter_forms import _velocity

    s = load_session(session, check_frames=False)
    out = alter(session, tmp_path / "drag", "velocity_drag", 0.01, _gel(session))
    a = load_session(out, check_frames=False)
    w0, w1 = s.table("wrench"), a.table("wrench")
    np.testing.assert_array_equal(w0[:, [0, 1, 5, 6, 7]], w1[:, [0, 1, 5, 6, 7]])
    assert not (out / "truth").exists()
    mount = s.manifest["streams"]["wrench"]["ft_to_indenter"]
    r_mount = _quat_matrix(np.array([mount["rotation_wxyz"]], float))[0]
    p = s.table("poses")
    p = p[p[:, 1] == 0]
    m = w0[:, 1] == 0
    j = np.clip(np.searchsorted(p[:, 0], w0[m, 0]), 0, len(p) - 1)
    rot = _quat_matrix(p[j, 5:9]) @ r_mount
    drag = np.einsum("nij,nj->ni", rot, w1[m, 2:5] - w0[m, 2:5])      # back in the sensor frame
    v = _velocity(p, w0[m, 0])
    moving = np.linalg.norm(v, axis=1) > 1.0
    assert moving.sum() > 50
    np.testing.assert_allclose(drag[moving], -0.01 * v[moving], atol=1e-6)


@pytest.mark.slow
def test_one_case_end_to_end_names_the_velocity_for_a_drag(tmp_path):
    from tensortouch.tools.accept.twin_generality import run_case

    row = run_case("velocity_drag", 2.0, 0, str(tmp_path))
    assert row["size_n"] == pytest.approx(2.0 * row["floor"], rel=0.03)
    assert row["right"], row


def test_summary_counts_right_verdicts_removal_nulls_and_the_mde_bins(tmp_path):
    import json

    from tensortouch.tools.accept.twin_generality import markdown, picture, read_rows, summarize

    def row(form, size, right, verdict, size_mde, removed=None, draw=0):
        r = {"form": form, "size_floor": size, "draw": draw, "right": right, "verdict": verdict, "p": 0.01 if verdict else None,
             "best_p": 0.5, "top_covariate": "velocity", "covariate_p": 0.001, "size_mde": size_mde}
        if removed is not None:
            r["removed"] = removed
        return r

    rows = [row("rim_profile", 1.0, True, "rim_stiffening", 3.0, 0.8),
            row("rim_profile", 1.0, False, "temperature_softening", 3.0, 0.2, draw=1),
            row("rim_profile", 0.15, False, "strain_stiffening", 0.4),
            row("rim_profile", 0.15, False, None, 0.45, draw=1),
            row("velocity_drag", 1.0, True, None, 3.0)]
    nulls = [{"null": 0, "verdict": None, "covariate_p": 0.2}, {"null": 1, "verdict": "ft_bias_drift", "covariate_p": 0.01}]
    log = tmp_path / "log"
    log.write_text("WARNING something\n" + "\n".join(json.dumps(r) for r in rows + nulls + rows[:1]) + "\n")
    got_rows, got_nulls = read_rows(str(log))
    assert len(got_rows) == 5 and len(got_nulls) == 2
    s = summarize(got_rows, got_nulls)
    assert s["right_at_or_above_floor"] == "2/3"
    assert s["removed_at_or_above_floor"]["at_least_70"] == "1/1"      # only right verdicts count
    assert s["null_false_alarms"] == "1/2" and s["null_covariate_alarms"] == "1/2"
    assert s["mde_2x_found"] == "1/2" and s["mde_half_claimed"] == "1/2"
    assert s["detection"]["rim_profile"] == {"0.15": "0/2", "1": "1/2"}
    assert "| rim_profile | 1× floor | 1/2 |" in markdown(got_rows)
    assert picture(got_rows, got_nulls, tmp_path / "p.png").stat().st_size > 1000


def test_rows_at_mde_multiples_count_in_the_mde_check_only_and_a_work_folder_resumes(tmp_path):
    import argparse
    import json

    from tensortouch.tools.accept import twin_generality as tg

    def row(size, right, verdict, target=None, draw=0, clean=None):
        r = {"form": "two_term_relaxation", "size_floor": size, "draw": draw, "right": right, "verdict": verdict,
             "p": 0.01 if verdict else None, "best_p": 0.5, "top_covariate": "time", "covariate_p": 0.3,
             "size_mde": 9.0, "pair": False}
        if target is not None:
            r["mde_target"] = target
        if clean is not None:
            r["size_clean_mde"] = clean
        return r

    rows = [row(1.0, True, "viscoelastic_relaxation", clean=3.0),
            row(0.15, False, None, clean=0.45),                          # the unaltered session's MDE bins it
            row(0.2, False, None, target=0.5), row(0.2, False, "ft_bias_drift", target=0.5, draw=1),
            row(0.7, True, "viscoelastic_relaxation", target=2.0)]
    s = tg.summarize(rows, [])
    assert s["detection"] == {"two_term_relaxation": {"0.15": "0/1", "1": "1/1"}}      # targeted rows not in the curve
    assert s["mde_targeted"] == {"0.5": {"right": "0/2", "claimed": "1/2"}, "2": {"right": "1/1", "claimed": "1/1"}}
    assert s["mde_half_claimed"] == "1/3" and s["mde_2x_found"] == "2/2"
    assert "| two_term_relaxation | 0.5× MDE | 0/2 |" in tg.markdown(rows)
    assert ("| two_term_relaxation | 0/1 | 1/1 | 0/2 (1 claimed) | 1/1 (1 claimed) |"
            in tg.counts(rows).splitlines())
    # a run's rows are files in work/rows; the next run reads them back instead of diagnosing again
    args = ("two_term_relaxation", 0.0, 1, str(tmp_path), (1, 2))
    f = tg._task_file(tmp_path, "case", args, 0.5)
    assert f.name == "case-two_term_relaxation-mde0.5-1.json"
    f.parent.mkdir(parents=True)
    for r in rows:
        mult = r.get("mde_target")
        f = tg._task_file(tmp_path, "case", (r["form"], r["size_floor"], r["draw"]), mult)
        f.write_text(json.dumps(r))
    (tmp_path / "rows" / "null-0.json").write_text(json.dumps({"null": 0, "verdict": None, "covariate_p": 0.4}))
    (tmp_path / "rows" / "clean-two_term_relaxation-0.json").write_text(json.dumps({"verdict": "ft_bias_drift"}))
    got, nulls = tg.read_rows(str(tmp_path))
    assert len(got) == 5 and len(nulls) == 1                       # the unaltered sessions' diagnoses are apart
    assert tg.read_clean(tmp_path) == [{"verdict": "ft_bias_drift"}]
    a = argparse.Namespace(draws=2, sizes=[0.15, 1.0], nulls=1, first_null=0, forms=["two_term_relaxation"],
                           jobs=1, work=str(tmp_path), out=None, pictures=None, summarize=None, mde_multiples=[0.5])
    done = {tg._task_file(tmp_path, "case", (r["form"], r["size_floor"], r["draw"]), r.get("mde_target"))
            for r in rows}
    called = []
    orig = tg._do
    tg._do = lambda kind, args, mult: called.append((kind, args[:3], mult)) or {**rows[0], "draw": args[2]}
    try:
        tg.run(a)
    finally:
        tg._do = orig
    # not yet done: 1x draw 1, 0.5xMDE ... (draw 0 and 1 done), 0.15x draw 1
    assert called == [("case", ("two_term_relaxation", 1.0, 1), None),
                      ("case", ("two_term_relaxation", 0.15, 1), None)]
    assert all(f.is_file() for f in done)


@pytest.fixture(scope="module")
def lab(session, tmp_path_factory):
    """The unit's true calibration and a contact law fitted on the session (as the harness has)."""
    from tensortouch.contracts.store import CalibrationStore
    from tensortouch.tools.twin.unit import TwinUnit, write_true_calibration
    from tensortouch.tools.workbench.compare import load_table
    from tensortouch.tools.workbench.models import ContactLaw

    root = tmp_path_factory.mktemp("store")
    write_true_calibration(TwinUnit("TWIN-GTEST"), root, 32)
    store = CalibrationStore(root)
    return store, ContactLaw.fit(load_table(session, store.load("TWIN-GTEST"), cache=False)[0])


@pytest.mark.parametrize("form", ["two_term_relaxation", "velocity_drag"])
def test_altering_in_memory_gives_the_table_of_the_altered_copy(session, lab, tmp_path, form):
    """The harness alters a loaded recording in memory instead of writing a copy per amplitude: its
    sample table must be the one of alter()'s copy read back, number for number."""
    from tensortouch.contracts.session import load_session
    from tensortouch.runtime.stages.effects import Registry
    from tensortouch.tools.accept.alter_forms import altered_session
    from tensortouch.tools.workbench.compare import run_compare

    store, law = lab
    reg = Registry.default(entry_points=False)
    clean = load_session(session, check_frames=False)
    amp = 0.3 if form == "two_term_relaxation" else 0.01
    copy = alter(session, tmp_path / "copy", form, amp, _gel(session))
    want = run_compare(copy, "TWIN-GTEST", store, law, reg, cache=False).table
    got = run_compare(session, "TWIN-GTEST", store, law, reg, session=altered_session(clean, form, amp, _gel(session))).table
    assert set(got.cols) == set(want.cols) and set(got.vec) == set(want.vec)
    for k in want.cols:
        np.testing.assert_array_equal(got.cols[k], want.cols[k], err_msg=k)
    for k in want.vec:
        np.testing.assert_array_equal(got.vec[k], want.vec[k], err_msg=k)
    np.testing.assert_array_equal(got.meas, want.meas)
    np.testing.assert_array_equal(got.model, want.model)
    assert not np.array_equal(got.meas, run_compare(session, "TWIN-GTEST", store, law, reg, cache=False).table.meas)
