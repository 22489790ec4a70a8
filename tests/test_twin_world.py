"""The twin's worlds (tools/twin/world.py, docs/twin.md "Worlds"): the pure cores of each rig-world
difference on hand-worked values, the session contract's rig calibration (frame, clock offset, bias),
the label world unchanged, and a small rig-world recording that a rig estimate (tools/train/rig_estimate.py)
calibrates from its own data. The physics is the analytic fallback (no FE) to keep it fast."""
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tensortouch.contracts.errors import SessionError
from tensortouch.contracts.session import load_session, mocap_to_sensor, read_table, to_house_frame, validate_manifest
from tensortouch.tools.train.rig_estimate import estimate, write
from tensortouch.tools.twin.geometry import GelSurface
from tensortouch.tools.twin.record import RecordConfig, Recorder, make_physics, record
from tensortouch.tools.twin.world import (
    WorldConfig,
    ar1_filter,
    calibrated_extrinsic,
    distort_ft,
    draw_world,
    sensor_to_mocap,
    stamp,
)

POSE_COLS = ["t", "indenter", "x", "y", "z", "qw", "qx", "qy", "qz"]


# ------------------------------------------------------------------------------------- pure cores

def test_ar1_filter_hand_worked_and_stationary():
    np.testing.assert_allclose(ar1_filter(np.array([1.0, 0.0, 0.0]), 0.5), [1.0, 0.5, 0.25])
    np.testing.assert_allclose(ar1_filter(np.array([1.0, 1.0]), 0.6), [1.0, 0.6 + 0.8])     # √(1 − 0.36) = 0.8
    e = np.arange(6.0).reshape(3, 2)
    assert ar1_filter(e, 0.0) is e or np.array_equal(ar1_filter(e, 0.0), e)                # φ = 0: white
    np.testing.assert_allclose(ar1_filter(e, 0.5)[:, 1], [1.0, 0.5 + np.sqrt(0.75) * 3, 0.25 + 0.5 * np.sqrt(0.75) * 3
                                                          + np.sqrt(0.75) * 5])
    y = ar1_filter(np.random.default_rng(0).normal(0, 2.0, 200_000), 0.9)
    assert abs(y.std() - 2.0) < 0.05                                   # same stationary σ as the white noise
    assert abs(np.corrcoef(y[1:], y[:-1])[0, 1] - 0.9) < 0.01           # lag-1 autocorrelation φ
    with pytest.raises(ValueError):
        ar1_filter(e, 1.0)


def test_distort_ft_is_crosstalk_then_bias():
    C = np.eye(6)
    C[1, 0] = 0.02
    r = distort_ft(np.array([[2.0, 0, 0, 0, 0, 0]]), C, [0.1, 0, 0, 0, 0, 3.0])
    np.testing.assert_allclose(r, [[2.1, 0.04, 0, 0, 0, 3.0]])
    with pytest.raises(ValueError):
        distort_ft(np.zeros((3, 3)), C, np.zeros(6))


def test_extrinsic_hand_worked_and_the_contract_inverts_it():
    R = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix()            # mocap x → sensor y
    t = np.array([10.0, 0.0, 0.0])
    p_m, rv_m = sensor_to_mocap(np.array([[10.0, 1.0, 0.0]]), np.array([[0.0, 0.0, 0.0]]), R, t)
    np.testing.assert_allclose(p_m, [[1.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(rv_m, [[0.0, 0.0, -np.pi / 2]], atol=1e-12)
    q = Rotation.from_matrix(R).as_quat()
    rows = np.array([[0.0, 0.0, *p_m[0], *Rotation.from_rotvec(rv_m[0]).as_quat()[[3, 0, 1, 2]]]])
    back = mocap_to_sensor(rows, [q[3], q[0], q[1], q[2]], t)
    np.testing.assert_allclose(back[0, 2:5], [10.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(back[0, 5:9], [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    Rc, tc = calibrated_extrinsic(np.eye(3), [1.0, 2.0, 3.0], np.eye(3), [0.1, 0.0, 0.0])
    np.testing.assert_allclose(tc, [1.1, 2.0, 3.0])
    np.testing.assert_allclose(Rc, np.eye(3))
    np.testing.assert_allclose(stamp([0.0, 1.0], 0.012), [0.012, 1.012])


def test_the_contract_applies_clock_offset_bias_and_checks_them():
    w = np.array([[0.5, 0, 1, 2, 3, 4, 5, 6], [0.5, 1, 1, 2, 3, 4, 5, 6]], float)
    out = to_house_frame(w, "wrench", {"clock_offset_s": 0.02, "bias": {"1": [1, 1, 1, 1, 1, 1]}})
    np.testing.assert_allclose(out, [[0.48, 0, 1, 2, 3, 4, 5, 6], [0.48, 1, 0, 1, 2, 3, 4, 5]])
    assert to_house_frame(w, "wrench", {}) is w
    base = {"schema": "tensortouch.session", "schema_version": 1, "sensor_id": "X", "units": {},
            "streams": {"frames": {"file": "frames.csv"}}}
    for info, msg in (({"frame": "camera"}, "streams.poses.frame"), ({"frame": "mocap"}, "mocap_to_sensor"),
                      ({"frame": "mocap", "mocap_to_sensor": {"rotation_wxyz": [0, 0, 0, 0], "translation_mm": [0, 0, 0]}},
                       "mocap_to_sensor"), ({"clock_offset_s": "soon"}, "clock_offset_s")):
        with pytest.raises(SessionError, match=msg):
            validate_manifest({**base, "streams": {**base["streams"], "poses": info}})
    with pytest.raises(SessionError, match="streams.wrench.bias"):
        validate_manifest({**base, "streams": {**base["streams"], "wrench": {"bias": {"0": [1, 2]}}}})


def test_off_axis_camera_rays_hit_the_skirt_where_they_should():
    gel = GelSurface()
    pts, ok = gel.intersect(np.array([0.5, 0.0, 0.5]), np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(pts, [[12.0, 0.0, 0.5], [-12.0, 0.0, 0.5]])
    assert ok.all()


def test_each_unit_draws_its_own_world_within_its_sizes():
    cfg = WorldConfig()
    a, b = draw_world("TWIN-A"), draw_world("TWIN-B")
    assert a.to_dict() == draw_world("TWIN-A").to_dict() and a.to_dict() != b.to_dict()
    for w in (a, b):
        assert abs(w.gel.cap_height - 6.0) <= cfg.cap_height_mm and abs(w.gel.radius - 12.0) <= cfg.radius_mm
        assert max(abs(v) for v in w.camera_offset_mm) <= cfg.center_mm
        assert abs(w.yeoh[0] / 0.03 - 1) <= cfg.c10 and abs(w.yeoh[1] / 0.002 - 1) <= cfg.c20
        assert all(abs(v) <= cfg.clock_ft_s for v in w.clock_offset_s.values())
        assert len(w.ft_bias) == 2 and all(abs(x) <= cfg.ft_bias_n for b_ in w.ft_bias for x in b_[:3])
        C = np.asarray(w.ft_crosstalk[0])
        assert np.allclose(np.diag(C), 1.0) and np.abs(C - np.eye(6)).max() <= cfg.ft_crosstalk
        assert C[0, 3] == 0.0                                           # no force ↔ torque terms
        m = w.material()
        assert m.C10 == w.yeoh[0] and abs(m.bulk_modulus / m.shear_modulus - 50.0) < 1e-9
    with pytest.raises(Exception, match="unknown world parameters"):
        WorldConfig.with_overrides({"gravity": 1.0})
    for bad, msg in (({"noise_ar1": "x"}, "noise_ar1"), ({"noise_ar1": 1.0}, "noise_ar1"),
                     ({"c10": -0.1}, "c10"), ({"mocap_origin_mm": [1, 2]}, "mocap_origin_mm"), ({"fe_order": 3}, "fe_order")):
        with pytest.raises(Exception, match=msg):
            WorldConfig.with_overrides(bad)
    assert WorldConfig.with_overrides({"clock_ft_s": 0, "fe_order": 2}).fe_order == 2


def test_the_rig_world_fe_is_the_units_own_gel_yeoh_and_finer_mesh():
    rec = Recorder(RecordConfig(serial="TWIN-W1", world="rig", physics="fe"), "/nonexistent-not-written")
    fe = make_physics(rec.cfg, rec.unit)
    w = rec.world
    assert (fe.material.C10, fe.material.C20, fe.material.C30) == w.yeoh
    assert fe.mesh.size_top == 0.7 and fe.gel.radius == w.gel.radius and fe.gel.cap_height == w.gel.cap_height
    label = make_physics(RecordConfig(serial="TWIN-W1", physics="fe"), Recorder(RecordConfig(serial="TWIN-W1"),
                                                                                 "/nonexistent").unit)
    assert label.material.C10 == 0.03 and label.mesh.size_top == 1.0 and label.gel.radius == 12.0
    assert fe.scenario(rec.plan[0]).hash() != label.scenario(rec.plan[0]).hash()


# ------------------------------------------------------------------------------------- recordings

def _small(world="label", pokes=2, **kw):
    cfg = RecordConfig(serial="TWIN-R", pokes=pokes, seed=4, physics="hertz-fallback", frame_format="png",
                       world=world, **kw)
    cfg.rig.camera_fps = 10.0
    return cfg


# `_small()` as recorded by the twin before worlds existed (commit ce0d048), as a fingerprint of every
# file of the session (streams, PNG frames, session.json, truth/): the file names exactly, CSV headers
# exactly and each numeric column's sum, sum of squares and row-weighted sum, each frame's pixel mean and
# mean square, and every JSON value. Numbers are compared to 1e-6 of their scale, not bit for bit:
# numpy and OpenCV pick SIMD kernels by CPU (AVX2 / AVX-512), whose last bits differ, so a byte digest
# holds on one machine only. Any change to what the label world records moves these far more.
LABEL_WORLD = Path(__file__).parent / "data" / "twin_label_world_fingerprint.json"


def _fingerprint(folder) -> dict:
    import cv2
    out = {}
    for p in sorted(q for q in folder.rglob("*") if q.is_file()):
        name = str(p.relative_to(folder))
        if p.suffix == ".csv":
            header = p.read_text().splitlines()[0]
            x = np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)
            w = (np.arange(len(x)) + 1.0)[:, None] / max(len(x), 1)
            out[name] = {"header": header, "rows": len(x), "sum": x.sum(0).tolist(),
                         "sumsq": (x * x).sum(0).tolist(), "weighted": (w * x).sum(0).tolist(),
                         "abs": np.abs(x).sum(0).tolist()}
        elif p.suffix == ".png":
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(float)
            out[name] = {"shape": list(img.shape), "mean": img.mean(), "meansq": (img * img).mean()}
        elif p.suffix == ".json":
            out[name] = json.loads(p.read_text())
        else:
            out[name] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _same(a, b, path="") -> list[str]:
    """Where fingerprints a (recorded) and b (reference) differ beyond 1e-6 of each number's scale."""
    if isinstance(b, dict):
        if not isinstance(a, dict) or sorted(a) != sorted(b):
            return [f"{path}: keys {sorted(a) if isinstance(a, dict) else a} != {sorted(b)}"]
        if "sum" in b and "abs" in b:   # a CSV column set: scale by each column's sum of |x|
            if a["header"] != b["header"] or a["rows"] != b["rows"]:
                return [f"{path}: header/rows {a['header']!r} {a['rows']} != {b['header']!r} {b['rows']}"]
            scale = np.asarray(b["abs"]) + 1e-9
            bad = []
            for k, sc in (("sum", scale), ("weighted", scale), ("abs", scale), ("sumsq", scale * (scale / b["rows"] + 1e-9))):
                if np.any(np.abs(np.asarray(a[k]) - np.asarray(b[k])) > 1e-6 * sc):
                    bad.append(f"{path}.{k}")
            return bad
        return [m for k in b for m in _same(a[k], b[k], f"{path}/{k}")]
    if isinstance(b, list):
        if not isinstance(a, list) or len(a) != len(b):
            return [f"{path}: length"]
        return [m for x, y in zip(a, b) for m in _same(x, y, path + "[]")]
    if isinstance(b, float) or isinstance(a, float):
        return [] if abs(float(a) - float(b)) <= 1e-6 * max(1.0, abs(float(b))) else [f"{path}: {a} != {b}"]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def test_the_label_world_records_todays_sessions(tmp_path):
    cfg = _small()
    assert "world" not in cfg.to_dict() and "world_params" not in cfg.to_dict()
    plain = RecordConfig(serial="TWIN-R", pokes=2, seed=4, physics="hertz-fallback", frame_format="png")
    plain.rig.camera_fps = 10.0
    assert cfg.key() == plain.key()                                      # resume keys of old recordings hold
    s = record(cfg, tmp_path / "s")
    assert _same(_fingerprint(s), json.loads(LABEL_WORLD.read_text())) == []    # as before worlds
    truth = json.loads((s / "truth" / "truth.json").read_text())
    assert "world" not in truth and "world" not in truth["unit"]
    assert load_session(s).streams["poses"]["frame"] == "sensor"


@pytest.fixture(scope="module")
def rig_session(tmp_path_factory):
    out = tmp_path_factory.mktemp("rig") / "s"
    cfg = _small("rig", pokes=8)
    rec = Recorder(cfg, out)
    rec.run()
    return rec, out


def test_a_rig_world_recording_differs_from_the_labels_as_drawn(rig_session):
    rec, out = rig_session
    w = rec.world
    ses = load_session(out)
    info = ses.streams["poses"]
    assert info["frame"] == "mocap" and "clock_offset_s" not in info            # a rig does not know its offsets
    truth = json.loads((out / "truth" / "truth.json").read_text())
    assert truth["world"]["name"] == "rig" and truth["world"]["yeoh"] == list(w.yeoh)
    raw = ses.recorded("poses")
    assert np.linalg.norm(raw[:, 2:5], axis=1).min() > 100.0                     # mocap frame: far from the gel
    true = read_table(out / "truth" / "poses.csv", POSE_COLS)
    # through the calibrated extrinsic: the truth moved by the calibration's error (+ mocap noise), and
    # stamped late by the mocap's clock offset
    R_e = Rotation.from_rotvec(w.extrinsic_error_rotvec).as_matrix()
    k0 = true[:, 1] == 0
    got = ses.table("poses")
    g0 = got[got[:, 1] == 0]
    d = w.clock_offset_s["poses"]
    assert np.allclose(g0[:, 0], true[k0, 0][-len(g0):] + d, atol=1e-9) or np.allclose(g0[:, 0] - d, true[k0, 0][:len(g0)])
    sel = true[k0][:len(g0)] if d >= 0 else true[k0][-len(g0):]
    expect = sel[:, 2:5] @ R_e.T + np.asarray(w.extrinsic_error_mm)
    err = np.linalg.norm(g0[:, 2:5] - expect, axis=1)
    assert np.median(err) < 0.15                                                  # mocap noise σ 0.05 mm/axis
    assert np.median(np.linalg.norm(g0[:, 2:5] - sel[:, 2:5], axis=1)) > 0.05     # the calibration error shows


def test_a_rig_estimates_the_rig_world_from_the_session(rig_session):
    rec, out = rig_session
    w = rec.world
    est = estimate(load_session(out))
    for name in ("wrench", "poses"):
        assert abs(est["clock_offset_s"][name] - w.clock_offset_s[name]) < 0.006, (name, est, w.clock_offset_s)
    for k, b in est["bias"].items():
        np.testing.assert_allclose(b[:3], w.ft_bias[int(k)][:3], atol=0.03)
    assert est["onsets"] >= 6 and est["mocap_translation_mm"] is not None
    true = read_table(out / "truth" / "poses.csv", POSE_COLS)

    def pose_error(ses):
        got = ses.table("poses")
        errs = []
        for k in (0, 1):
            g, t = got[got[:, 1] == k], true[true[:, 1] == k]
            near = t[:, 3] ** 2 + t[:, 2] ** 2 < 100.0                       # over the gel, not parked
            p = np.stack([np.interp(t[near, 0], g[:, 0], g[:, j]) for j in (2, 3, 4)], 1)
            errs.append(np.linalg.norm(p - t[near, 2:5], axis=1))
        return float(np.median(np.concatenate(errs)))

    before = pose_error(load_session(out))
    write(out, est)
    after_ses = load_session(out)
    after = pose_error(after_ses)
    assert after < before
    assert after_ses.manifest["provenance"]["rig_estimate"]["onsets"] == est["onsets"]
    wr = after_ses.table("wrench")
    rest = wr[np.abs(wr[:, 4]) < 0.1]
    assert abs(np.median(rest[:, 2:5])) < 0.03                                   # tared
    again = estimate(after_ses)                                                   # a second pass finds ~nothing
    assert all(abs(v) < 0.003 for v in again["clock_offset_s"].values())


def test_a_rig_world_fe_recording_solves_the_units_own_scenario(tmp_path, monkeypatch):
    """One press in FE (a coarse world mesh to keep it short): the recording's FE is the unit's gel and
    Yeoh (its scenario hash is the world's, not the label solver's), and its true force is the FE
    reaction itself (no force factor)."""
    pytest.importorskip("felupe")
    monkeypatch.setenv("TENSORTOUCH_CACHE", str(tmp_path / "cache"))
    cfg = RecordConfig(serial="TWIN-FE", pokes=1, seed=11, physics="fe", frame_format="png", world="rig",
                       world_params={"fe_mesh_top": 1.2, "fe_mesh_inside": 2.5})
    cfg.trajectory.kinds = ("press",)
    cfg.trajectory.p_two = 0.0
    cfg.rig.camera_fps = 10.0
    rec = Recorder(cfg, tmp_path / "s")
    rec.run()
    truth = json.loads((tmp_path / "s" / "truth" / "truth.json").read_text())
    world_fe = make_physics(cfg, rec.unit)
    assert truth["fe_scenarios"] == [world_fe.scenario(rec.plan[0]).hash()]
    label_cfg = RecordConfig(serial="TWIN-FE", pokes=1, seed=11, physics="fe")
    assert truth["fe_scenarios"][0] != make_physics(label_cfg, Recorder(label_cfg, tmp_path / "x").unit).scenario(
        rec.plan[0]).hash()
    cols = ["t", "indenter", "fx", "fy", "fz", "mx", "my", "mz"]
    np.testing.assert_array_equal(read_table(tmp_path / "s" / "truth" / "reaction.csv", cols),
                                  read_table(tmp_path / "s" / "truth" / "reaction_fe.csv", cols))
    assert np.abs(read_table(tmp_path / "s" / "truth" / "reaction.csv", cols)[:, 4]).max() > 0.5


def test_a_recipe_session_in_the_rig_world_is_estimated_once(rig_session, tmp_path):
    """SessionSpec.world reaches the recording and the build's keys (a label-world spec keeps its old
    key); the build's sessions stage folds a rig estimate into a rig session once."""
    import shutil

    from tensortouch.tools.train.build import BuildConfig, SessionSpec, stage_keys
    from tensortouch.tools.train.rig_estimate import prepare

    label, rig = SessionSpec("TWIN-X", 1, 2), SessionSpec("TWIN-X", 1, 2, world="rig")
    assert rig.record_config("hertz-fallback", 128).world == "rig"
    assert "world" not in BuildConfig(train=[label]).to_dict()["train"][0]
    assert stage_keys(BuildConfig(train=[label]))["sessions"] != stage_keys(BuildConfig(train=[rig]))["sessions"]
    _, out = rig_session
    s = shutil.copytree(out, tmp_path / "s")
    man = json.loads((s / "session.json").read_text())
    man["streams"] = {k: {f: v for f, v in info.items() if f not in ("clock_offset_s", "bias")}
                      for k, info in man["streams"].items()}
    man["provenance"].pop("rig_estimate", None)
    (s / "session.json").write_text(json.dumps(man))
    first = prepare(s)
    assert first["onsets"] >= 6 and "clock_offset_s" in load_session(s).streams["wrench"]
    before = (s / "session.json").read_bytes()
    assert prepare(s) == first and (s / "session.json").read_bytes() == before


def test_a_rewritten_stream_carries_its_calibration_in_the_numbers(rig_session, tmp_path):
    """A tool that rewrites a stream from `Session.table` (e.g. tools/accept/alter.py) writes it through
    `write_stream`: the calibration leaves the manifest, so it is not applied twice."""
    import shutil

    from tensortouch.contracts.session import write_stream

    _, out = rig_session
    s = shutil.copytree(out, tmp_path / "s")
    ses = load_session(s)
    man = json.loads((s / "session.json").read_text())
    man["streams"]["wrench"].update(clock_offset_s=0.01, bias={"0": [0.1, 0, 0, 0, 0, 0]})
    (s / "session.json").write_text(json.dumps(man))
    ses = load_session(s)
    w = ses.table("wrench").copy()
    w[:, 2] *= 2.0
    again = write_stream(s, "wrench", w)
    info = again.streams["wrench"]
    assert "bias" not in info and "clock_offset_s" not in info and info["rows"] == len(w)
    np.testing.assert_allclose(again.table("wrench"), w, rtol=1e-8, atol=1e-8)
    np.testing.assert_array_equal(again.table("poses"), ses.table("poses"))     # other streams untouched
