"""Twin recordings: FE physics acceptance (F/T = -RF transformed + noise, deeper press -> larger
image change and force), zero contact = rest, determinism, resume, hysteresis, effects, CLI."""
import argparse
import json

import numpy as np
import pytest
from tensortouch.contracts.session import load_session, read_table
from tensortouch.tools.sessions.writer import read_frames
from tensortouch.tools.twin.record import RecordConfig, Recorder, record

POSE_COLS = ["t", "indenter", "x", "y", "z", "qw", "qx", "qy", "qz"]
RF_COLS = ["t", "indenter", "fx", "fy", "fz", "mx", "my", "mz"]


def _quat_matrix(q):
    w, x, y, z = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


@pytest.fixture(scope="module")
def fe_session(tmp_path_factory):
    pytest.importorskip("felupe")
    from tensortouch.tools.fe import MeshSettings
    from tensortouch.tools.twin.fe_physics import FEPhysics

    root = tmp_path_factory.mktemp("fe")
    cfg = RecordConfig(serial="TWIN-FE", pokes=1, seed=11, physics="fe", frame_format="png")
    cfg.trajectory.kinds = ("press",)
    cfg.trajectory.p_two = 0.0
    cfg.rig.camera_fps = 10.0
    physics = FEPhysics(mesh=MeshSettings(size_top=1.2, size_inside=2.5), cache=root / "cache")
    rec = Recorder(cfg, root / "s", physics=physics)
    rec.run()
    return rec, physics


def test_ft_equals_minus_fe_reaction_in_ft_frame_plus_noise(fe_session):
    rec, physics = fe_session
    out, rig = rec.out, rec.cfg.rig
    s = load_session(out)
    wr = s.table("wrench")
    pose = read_table(out / "truth" / "poses.csv", POSE_COLS)
    rf = read_table(out / "truth" / "reaction_fe.csv", RF_COLS)
    # the nominal reaction stored in truth IS the FE result at the keypoints
    from tensortouch.tools.twin.physics import interpolate

    poke = rec.plan[0]
    res = physics.result(poke)
    span = (rf[:, 0] >= poke.times[0]) & (rf[:, 0] <= poke.times[-1])
    at = interpolate(physics.solve(poke), poke, rf[span, 0], "RF")[:, 0]
    np.testing.assert_allclose(rf[span, 2:5], at, atol=1e-12)
    np.testing.assert_allclose(interpolate(physics.solve(poke), poke, poke.times, "RF")[:, 0], res.RF[:, 0])
    assert np.all(rf[~span, 2:5] == 0)
    assert np.abs(res.RF[:, 0, 2]).max() > 0.3  # the press really loads the gel
    # expected F/T: -(scale * RF) with the moment moved to the F/T origin, in the F/T frame
    scale = rec.unit.params.stiffness_scale
    q = np.array([np.interp(wr[:, 0], pose[:, 0], pose[:, c]) for c in range(5, 9)]).T
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    tip = np.array([np.interp(wr[:, 0], pose[:, 0], pose[:, c]) for c in range(2, 5)]).T
    R_ind = _quat_matrix(q)
    tf = s.streams["wrench"]["ft_to_indenter"]
    R_fi = _quat_matrix(np.array([tf["rotation_wxyz"]]))[0]
    R_ft = R_ind @ R_fi
    o_ft = tip + R_ind @ np.array(tf["translation_mm"])
    F = -scale * rf[:, 2:5]
    M = -scale * rf[:, 5:8] + np.cross(tip - o_ft, F)
    exp_f = np.einsum("nji,nj->ni", R_ft, F)
    exp_t = np.einsum("nji,nj->ni", R_ft, M)
    res_f, res_t = wr[:, 2:5] - exp_f, wr[:, 5:8] - exp_t
    assert np.abs(res_f.mean(0)).max() < 0.01
    assert 0.5 * rig.ft_noise_n < res_f.std() < 1.5 * rig.ft_noise_n
    assert 0.5 * rig.ft_noise_nmm < res_t.std() < 1.5 * rig.ft_noise_nmm + 0.05


def test_deeper_fe_press_larger_image_difference_and_force(fe_session):
    rec, physics = fe_session
    poke = rec.plan[0]
    sol = physics.solve(poke)
    r = rec.unit.renderer
    W = rec.gel.interpolator(sol.nodes, r.view.points[r.view.mask])
    rest = r.render_float(None)
    press = [j for j in range(1, len(poke.times)) if sol.depth[j, 0] > sol.depth[j - 1, 0] + 1e-6]
    assert len(press) >= 2
    diffs, forces = [], []
    for j in press:
        u = np.zeros(r.view.points.shape)
        u[r.view.mask] = W @ sol.U[j]
        diffs.append(np.abs(r.render_float(u) - rest).mean())
        forces.append(np.linalg.norm(sol.RF[j, 0]))
    assert all(a < b for a, b in zip(diffs, diffs[1:])), diffs
    assert all(a < b for a, b in zip(forces, forces[1:])), forces


def test_zero_contact_frames_equal_rest_up_to_noise(fe_session):
    rec, _ = fe_session
    s = load_session(rec.out)
    t = s.table("frames")[:, 0]
    before = np.flatnonzero(t < rec.plan[0].t_start)
    assert len(before) >= 3
    rest = rec.unit.renderer.render_float(None)
    nz = rec.unit.renderer.noise
    bound = 2.0 * np.sqrt(nz.read_sigma ** 2 + nz.shot_sigma ** 2) + 1 / 255
    for _i, f in read_frames(s, before):
        d = f.astype(np.float64) / 255 - rest
        assert abs(d.mean()) < 0.002 and d.std() < bound
    keys = read_table(rec.out / "truth" / "frames.csv", ["t", "index", "poke", "sigma"])
    inside = (t >= rec.plan[0].times[0]) & (t <= rec.plan[0].times[-1])
    assert np.all(keys[inside, 2] == 0) and np.all(keys[~inside, 2] == -1)
    assert np.all(np.diff(keys[inside, 3]) > 0) and keys[inside, 3].max() <= len(rec.plan[0].times) - 1


def _small(serial="TWIN-R", **kw):
    cfg = RecordConfig(serial=serial, pokes=2, seed=4, physics="hertz-fallback", frame_format="png", **kw)
    cfg.rig.camera_fps = 10.0
    return cfg


def test_deterministic_and_resumable(tmp_path):
    a = record(_small(), tmp_path / "a")

    class Stop(Exception):
        pass

    def interrupt(stage, i, n):
        if stage == "frames" and i == 20:
            raise Stop

    with pytest.raises(Stop):
        Recorder(_small(), tmp_path / "b", progress=interrupt).run()
    assert not (tmp_path / "b" / "session.json").exists()
    rec = Recorder(_small(), tmp_path / "b")
    b = rec.run()
    assert rec.timing["frames_rendered"] < len(load_session(a).table("frames"))  # really resumed
    sa, sb = load_session(a), load_session(b)
    for name in ("poses", "wrench", "temperature", "frames"):
        np.testing.assert_array_equal(sa.table(name), sb.table(name))
    for (_i, fa), (_, fb) in zip(read_frames(sa), read_frames(sb)):
        np.testing.assert_array_equal(fa, fb)
    with pytest.raises(Exception, match="already holds a finished session"):
        record(_small(), tmp_path / "a")
    c = Recorder(_small(), tmp_path / "c")
    c._claim()
    with pytest.raises(Exception, match="other settings"):
        record(RecordConfig(serial="OTHER", physics="hertz-fallback"), tmp_path / "c")


def test_effects_change_measurements_not_truth_reaction(tmp_path):
    cfg = _small("TWIN-E", effects=[("ft_bias_drift", {"bx": 0.0, "by": 0.0, "bz": 0.02}),
                                    ("temperature_softening", {"alpha": 0.03, "t_ref": 24.0})])
    out = record(cfg, tmp_path / "s")
    base = record(_small("TWIN-E"), tmp_path / "b")
    w, wb = load_session(out).table("wrench"), load_session(base).table("wrench")
    idle = np.linalg.norm(read_table(out / "truth" / "reaction_fe.csv", RF_COLS)[:, 2:5], axis=1) == 0
    drift = (w[idle, 4] - wb[idle, 4])
    np.testing.assert_allclose(drift, 0.02 * w[idle, 0], atol=1e-9)  # same noise, bias only
    truth = read_table(out / "truth" / "reaction.csv", RF_COLS)
    truth_b = read_table(base / "truth" / "reaction.csv", RF_COLS)
    loaded = ~idle
    assert np.all(np.abs(truth[loaded, 4]) < np.abs(truth_b[loaded, 4]))  # warmer than t_ref: softer
    info = json.loads((out / "truth" / "truth.json").read_text())
    assert [e["name"] for e in info["effects"]] == ["ft_bias_drift", "temperature_softening"]
    assert "ft_bias_drift" not in (out / "session.json").read_text()


def test_cli_record_show_calibration(tmp_path, capsys):
    from tensortouch.tools.twin.cli import register

    parser = argparse.ArgumentParser(prog="tensortouch")
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["twin", "record", "--unit", "TWIN-CLI", "--pokes", "1", "--seed", "2",
                              "--physics", "hertz-fallback", "--frames", "mjpg", "--fps", "10",
                              "--effect", "led_drift:c=-0.01", "--out", str(tmp_path / "s"),
                              "--calibration", "--store", str(tmp_path / "store")])
    assert args.func(args) == 0
    assert (tmp_path / "store" / "TWIN-CLI" / "CURRENT").is_file()
    assert load_session(tmp_path / "s").streams["frames"]["codec"] == "MJPG"
    args = parser.parse_args(["twin", "show", str(tmp_path / "s"), "--out", str(tmp_path / "sheet.png")])
    assert args.func(args) == 0
    import cv2

    sheet = cv2.imread(str(tmp_path / "sheet.png"))
    assert sheet is not None and sheet.shape[0] > 400


def test_recorded_gel_returns_to_rest_slowly(tmp_path):
    """After the last release the frames stay deformed and relax toward rest (hysteresis on);
    with no slow part they are back at rest up to noise."""
    def tail_diffs(fraction, out):
        cfg = _small("TWIN-H")
        cfg.pokes = 1
        cfg.rig.hysteresis_fraction, cfg.rig.hysteresis_tau_s = fraction, 2.0
        rec = Recorder(cfg, out)
        rec.run()
        s = load_session(out)
        t = s.table("frames")[:, 0]
        idx = np.flatnonzero(t > rec.plan[-1].times[-1] + 0.05)
        rest = rec.unit.renderer.render_float(None)
        return [np.abs(f.astype(np.float64) / 255 - rest).mean() for _, f in read_frames(s, idx)]

    slow = tail_diffs(0.5, tmp_path / "slow")
    none = tail_diffs(0.0, tmp_path / "none")
    noise_floor = max(none)
    assert slow[0] > 2 * noise_floor           # still visibly deformed after the release
    assert slow[-1] < slow[0]                  # and relaxing
    assert max(none) - min(none) < 0.002       # no slow part: at rest (noise only) right away


def test_stills_are_the_videos_frames_around_each_pokes_start_and_deepest_moment(tmp_path):
    """camera "stills" renders a subset of the camera clock: each still is pixel for pixel the video's
    frame at that time (same state, same noise), every poke has a rest frame before its start and frames
    at its deepest planned moment, and an interrupted stills recording resumes to the same session."""
    from tensortouch.contracts.errors import SessionError

    video = record(_small(), tmp_path / "video")
    rec = Recorder(_small(camera="stills"), tmp_path / "stills")
    stills = rec.run()
    fv, fs = load_session(video).table("frames"), load_session(stills).table("frames")
    assert 0 < len(fs) < 0.6 * len(fv)
    assert np.array_equal(fs[:, 1], np.arange(len(fs)))
    at = np.searchsorted(fv[:, 0], fs[:, 0])
    assert np.array_equal(fv[at, 0], fs[:, 0])                       # stills lie on the camera clock
    img_v = dict(read_frames(load_session(video), fv[at, 1].astype(int)))
    for (_i, img), j in zip(read_frames(load_session(stills)), fv[at, 1].astype(int)):
        assert np.array_equal(img, img_v[j])
    kv = read_table(video / "truth" / "frames.csv", ["t", "index", "poke", "sigma"])
    ks = read_table(stills / "truth" / "frames.csv", ["t", "index", "poke", "sigma"])
    assert np.array_equal(ks[:, [0, 2, 3]], kv[at][:, [0, 2, 3]]) and np.array_equal(ks[:, 1], fs[:, 1])
    contact = read_table(stills / "truth" / "contact.csv", ["t", "indenter", "depth", "x", "y", "z", "area", "touching"])
    for p in rec.plan:
        assert np.any((fs[:, 0] < p.t_start) & (fs[:, 0] > p.t_start - 0.2))
        c = contact[(contact[:, 0] >= p.t_start) & (contact[:, 0] <= p.t_end)]
        deepest = c[np.argmax(c[:, 2]), 0]
        assert np.abs(fs[:, 0] - deepest).min() <= 0.5 / rec.cfg.rig.camera_fps + 1e-9

    class Stop(Exception):
        pass

    def interrupt(stage, i, n):
        if stage == "frames" and i >= 12:
            raise Stop

    with pytest.raises(Stop):
        Recorder(_small(camera="stills"), tmp_path / "resumed", progress=interrupt).run()
    resumed = Recorder(_small(camera="stills"), tmp_path / "resumed").run()
    assert np.array_equal(load_session(resumed).table("frames"), fs)
    for (_, a), (_, b) in zip(read_frames(load_session(resumed)), read_frames(load_session(stills))):
        assert np.array_equal(a, b)
    with pytest.raises(SessionError, match="camera"):
        Recorder(_small(camera="film"), tmp_path / "bad")
