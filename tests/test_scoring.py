"""tools/scoring.py: the rig's measurement at frame times (one sign), clusters ↔ indenters, and the
package's own contact stage. Hand-worked values on tiny tables built here; then the acceptance: on
the shipped demo with the shipped package, train's budget scoring, the workbench, recalibration and
replay_session all see the contacts `tensortouch run` publishes (real onnxruntime, OpenCV, Zenoh on
loopback; nothing mocked)."""
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tensortouch.contracts.errors import SessionError
from tensortouch.runtime.stages.contacts import ContactConfig
from tensortouch.tools.scoring import contact_config, ft_to_sensor, match_contacts, measured_at, split_at_tips

ROOT = Path(__file__).resolve().parents[1]


def fake_session(poses, wrench, rot=(1.0, 0, 0, 0)):
    """A session-like object with only the wrench and poses tables and the F/T → indenter rotation."""
    tables = {"poses": np.asarray(poses, float), "wrench": np.asarray(wrench, float)}
    return SimpleNamespace(table=tables.__getitem__, path="fake-session",
                           streams={"wrench": {"ft_to_indenter": {"rotation_wxyz": list(rot)}}})


def test_measured_at_turns_the_ft_reading_into_the_force_on_the_gel():
    poses = [[0.0, 3, 0, 0, 0, 1.0, 0, 0, 0], [1.0, 3, 0, 0, 0, 1.0, 0, 0, 0]]
    wrench = np.array([[0.0, 3, 0, 0, -1.0, 0, 0, 0], [1.0, 3, 0, 0, -3.0, 0, 0, 0]])
    # the F/T reads the gel pushing up the indenter's axis (−z at 0.5 s: −2 N): the indenter pushes +2 N... on
    # the gel the runtime publishes the force the indenter applies, −(the reading)
    np.testing.assert_allclose(measured_at(fake_session(poses, wrench), np.array([0.5]))[3]["force"], [[0, 0, 2.0]])
    yaw = Rotation.from_rotvec([0, 0, np.pi / 2]).as_quat(scalar_first=True)     # F/T x axis = indenter y
    wrench[:, 2:5] = [1.0, 0, 0]
    np.testing.assert_allclose(measured_at(fake_session(poses, wrench, yaw), np.array([0.5]))[3]["force"],
                               [[0, -1.0, 0]], atol=1e-12)


def test_measured_at_interpolates_the_pose_rotation_between_samples():
    """Pose yaw 0° at 0 s, 90° at 1 s: at 0.5 s the reading [1, 0, 0] N is rotated by 45°."""
    q90 = Rotation.from_rotvec([0, 0, np.pi / 2]).as_quat(scalar_first=True)
    poses = [[0.0, 0, 1, 2, 3, 1.0, 0, 0, 0], [1.0, 0, 3, 2, 3, *q90]]
    wrench = [[0.0, 0, 1.0, 0, 0, 0, 0, 0], [1.0, 0, 1.0, 0, 0, 0, 0, 0]]
    m = measured_at(fake_session(poses, wrench), np.array([0.0, 0.5, 1.0]))[0]
    h = np.sqrt(0.5)
    np.testing.assert_allclose(m["force"], [[-1, 0, 0], [-h, -h, 0], [0, -1, 0]], atol=1e-12)
    np.testing.assert_allclose(m["tip"], [[1, 2, 3], [2, 2, 3], [3, 2, 3]])
    np.testing.assert_allclose(m["rotation"][1] @ [1.0, 0, 0], [h, h, 0], atol=1e-12)


def test_measured_at_filters_only_when_asked():
    """average=4 gives window means at the window-mean times; pose_cutoff_hz smooths the tip track."""
    t = np.arange(64) / 100.0
    wrench = np.column_stack([t, np.zeros(64), np.zeros(64), np.zeros(64), -np.arange(64.0), np.zeros((64, 3))])
    tip_x = np.where(np.arange(64) % 2 == 0, 1.0, -1.0)             # a ±1 mm jitter at the sampling rate
    poses = np.column_stack([t, np.zeros(64), tip_x, np.zeros(64), np.zeros(64), np.ones(64), np.zeros((64, 3))])
    raw = measured_at(fake_session(poses, wrench), None)[0]
    np.testing.assert_allclose(raw["t"], t)
    np.testing.assert_allclose(raw["force"][:, 2], np.arange(64.0))
    np.testing.assert_allclose(raw["tip"][:, 0], tip_x)
    avg = measured_at(fake_session(poses, wrench), None, average=4, pose_cutoff_hz=5.0)[0]
    np.testing.assert_allclose(avg["t"], t.reshape(16, 4).mean(1))
    np.testing.assert_allclose(avg["force"][:, 2], np.arange(64.0).reshape(16, 4).mean(1))
    assert np.abs(avg["tip"][4:-4, 0]).max() < 0.1                   # the jitter is gone (away from the ends)


def test_measured_at_names_the_session_when_an_indenter_has_no_poses():
    wrench = [[0.0, 5, 0, 0, 1, 0, 0, 0], [1.0, 5, 0, 0, 1, 0, 0, 0]]
    with pytest.raises(SessionError, match="fake-session: indenter 5 has 2 wrench and 0 pose samples"):
        measured_at(fake_session(np.zeros((0, 9)), wrench), np.array([0.5]))


def test_ft_to_sensor_rotations():
    f_ft = np.array([[1.0, 0.0, 0.0]])
    ft_rot = Rotation.from_euler("z", 90, degrees=True).as_quat()[[3, 0, 1, 2]]   # wxyz
    pose = Rotation.from_euler("x", 90, degrees=True).as_quat()[[3, 0, 1, 2]]
    np.testing.assert_allclose(ft_to_sensor(f_ft, pose[None], ft_rot), [[0.0, 0.0, 1.0]], atol=1e-12)


def test_match_contacts_nearest_pairs_and_priority_order():
    tips = np.array([[0.0, 0, 0], [10.0, 0, 0], [50.0, 0, 0]])
    cents = np.array([[9.0, 0, 0], [1.0, 0, 0], [0.5, 0, 0]])
    assert match_contacts(tips, cents, 6.0).tolist() == [2, 0, -1]
    assert match_contacts(tips, cents).tolist() == [2, 0, 1]
    # in priority order the far indenter goes first and takes the nearest free cluster
    assert match_contacts(tips, cents, order=[2, 0]).tolist() == [2, -1, 0]
    assert match_contacts(tips, cents[:0]).tolist() == [-1, -1, -1]
    # more indenters than clusters: the first in order takes the cluster, the others get none (no cluster
    # is counted twice, with or without a distance bound)
    assert match_contacts(tips[:2], cents[:1], order=[0, 1]).tolist() == [0, -1]
    assert match_contacts(tips[:2], cents[:1], order=[1, 0]).tolist() == [-1, 0]
    assert match_contacts(tips[:2], cents[1:2], order=[1, 0]).tolist() == [-1, 0]


def test_split_at_tips_gives_each_pixel_to_the_nearest_tip_by_hand():
    # a 1×4 strip of pixels at x = 0, 1, 2, 3 mm; tips at x = 0.2 and x = 2.9; the last pixel is masked out
    xyz = np.zeros((1, 4, 3))
    xyz[0, :, 0] = [0.0, 1.0, 2.0, 3.0]
    fp = np.zeros((3, 1, 4))
    fp[2, 0] = [1.0, 2.0, 4.0, 8.0]
    fp[0, 0] = [0.5, 0.0, 0.0, 0.0]
    mask = np.array([[True, True, True, False]])
    out = split_at_tips(fp, xyz, mask, np.array([[0.2, 0, 0], [2.9, 0, 0]]))
    assert out.tolist() == [[0.5, 0.0, 3.0], [0.0, 0.0, 4.0]]
    # one tip takes the whole masked field; no tip gets nothing
    assert split_at_tips(fp, xyz, mask, np.array([[9.0, 0, 0]])).tolist() == [[0.5, 0.0, 7.0]]
    assert split_at_tips(fp, xyz, mask, np.zeros((0, 3))).shape == (0, 3)


def test_split_at_tips_checks_shapes():
    with pytest.raises(ValueError, match="force_px"):
        split_at_tips(np.zeros((2, 1, 4)), np.zeros((1, 4, 3)), np.ones((1, 4), bool), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="mask"):
        split_at_tips(np.zeros((3, 1, 4)), np.zeros((1, 4, 3)), np.ones((1, 3), bool), np.zeros((1, 3)))


def test_contact_config_is_the_packages_own():
    man = {"runtime": {"contacts": {"threshold_n": 0.00233, "weak_threshold_n": 0.0008, "min_total_n": 0.13678,
                                    "support_radius_px": 20.0, "merge_n": 0.0012, "min_pixels": None}}}
    cc = contact_config(SimpleNamespace(manifest=man))
    assert (cc.threshold_n, cc.weak_threshold_n, cc.min_total_n, cc.support_radius_px, cc.merge_n) == \
        (0.00233, 0.0008, 0.13678, 20.0, 0.0012)
    assert cc.min_pixels == ContactConfig().min_pixels                  # null keeps the default
    assert contact_config(SimpleNamespace(manifest={})) == ContactConfig()



def test_train_budget_clusters_with_the_scored_packages_settings(caplog):
    """`train budget` takes the settings of --package, else of the build's exported package; the runtime
    defaults only when there is no package, and it says so."""
    from tensortouch.tools.train.evaluate import budget_contacts, scored_package

    shipped = ROOT / "exported_models" / "hiera-qup-128"
    if not (shipped / "manifest.json").is_file():
        pytest.skip("no shipped package")
    exported = SimpleNamespace(read_stamp=lambda stage: {"package": str(shipped)} if stage == "export" else {})
    none = SimpleNamespace(read_stamp=lambda stage: {})
    shipped_contacts = budget_contacts(scored_package(exported))
    manifest = json.loads((shipped / "manifest.json").read_text())["runtime"]["contacts"]
    assert all(getattr(shipped_contacts, k) == v for k, v in manifest.items() if v is not None)
    assert shipped_contacts != ContactConfig()
    assert budget_contacts(scored_package(none, str(shipped))) == shipped_contacts
    assert scored_package(none) is None
    with caplog.at_level("WARNING"):
        assert budget_contacts(None) == ContactConfig()
    assert "runtime defaults" in caplog.text



def test_the_workbench_table_holds_measured_at_with_the_ft_sign():
    """The workbench's sample table is measured_at with its filters (the F/T's sign: the load on the
    indenter), on the shipped demo's streams."""
    from tensortouch.contracts import paths
    from tensortouch.contracts.session import load_session
    from tensortouch.contracts.store import CalibrationStore
    from tensortouch.tools.workbench.samples import SampleConfig, build_table

    if not (paths.demo_dir() / "session.json").is_file():
        pytest.skip("no demo recording")
    session = load_session(paths.demo_dir())
    cal = CalibrationStore(ROOT / "calibration_store").load("TWIN-DEMO")
    cfg = SampleConfig()
    table = build_table(session, cal, cfg, brightness=False)
    m = measured_at(session, None, average=cfg.average, pose_cutoff_hz=cfg.pose_cutoff_hz)
    for k, v in m.items():
        rows = table.cols["series"] == k
        np.testing.assert_allclose(table.cols["t"][rows], v["t"])
        np.testing.assert_allclose(table.meas[rows], -v["force"], rtol=1e-12, atol=1e-12)
    assert np.abs(table.meas).max() > 1.0             # real presses, not an empty stream


# ------------------------------------------------------------------ acceptance: one scoring path
def _published(session: Path, package_dir: Path, store_root: Path, sensor: str) -> dict:
    """`tensortouch run` on a recording in its own process, its contacts received over Zenoh (loopback)."""
    from tensortouch.runtime.apps.subscriber import Subscriber

    from tests.test_e2e_runtime import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got, lock = {}, threading.Lock()

    def on_contacts(m):
        with lock:
            got[m.seq] = m

    env = dict(os.environ, TENSORTOUCH_CALIBRATION=str(store_root), PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT))
    with Subscriber(sensor, listen=[endpoint], on_contacts=on_contacts):
        run = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", "run", "--source", f"replay:{session}",
                              "--model", str(package_dir), "--no-fields", "--connect", endpoint], check=False,
                             env=env, capture_output=True, text=True, timeout=300, cwd=ROOT)
        time.sleep(1.0)
    assert run.returncode == 0, run.stderr[-3000:]
    with lock:
        return dict(got)


def _same(a: list, b: list) -> None:
    """Two frames' contacts (objects with position_mm and force_n), in the same order: equal."""
    assert len(a) == len(b)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x.position_mm, y.position_mm, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(x.force_n, y.force_n, rtol=1e-9, atol=1e-12)


def _by_position(clusters: list) -> list:
    return sorted(clusters, key=lambda c: tuple(np.round(c.position_mm, 6)))


def test_train_workbench_recalibration_and_replay_score_what_run_publishes(tmp_path):
    """The shipped demo, the shipped package (its measured contact settings) and the demo unit's shipped
    calibration: `tensortouch run` over Zenoh, then every tool's way to the same frames' contacts —
    replay_session, train budget's contact stage (fields → clusters with the package's settings),
    the workbench's kept passes + the runtime's finish and its line-up, recalibration's collected
    frames + the runtime's correction. One network run; the others reuse the replay cache."""
    from tensortouch.contracts import paths
    from tensortouch.contracts.session import load_session
    from tensortouch.contracts.store import CalibrationStore
    from tensortouch.runtime.offline import replay_session
    from tensortouch.runtime.stages.model import load_package
    from tensortouch.tools.recalib.replay import collect_frames, corrected_frames
    from tensortouch.tools.scoring import find_contacts
    from tensortouch.tools.train.evaluate import EvalConfig, budget_contacts, frame_errors, sample_forces
    from tensortouch.tools.workbench.network import NetworkModel, replay, temperature_of
    from tensortouch.tools.workbench.samples import build_table

    demo, sensor = paths.demo_dir(), "TWIN-DEMO"
    package_dir = ROOT / "exported_models" / "hiera-qup-128"
    if not (demo / "session.json").is_file() or not (package_dir / "manifest.json").is_file():
        pytest.skip("no shipped demo recording or package")
    shutil.copytree(ROOT / "calibration_store" / sensor, tmp_path / "calib" / sensor)
    cal = CalibrationStore(tmp_path / "calib").load(sensor)
    package = load_package(package_dir)
    contacts = budget_contacts(package)          # what `train budget` clusters with for this package
    assert contacts != ContactConfig() and contacts.threshold_n == package.manifest["runtime"]["contacts"]["threshold_n"]
    assert contacts.merge_n == package.manifest["runtime"]["contacts"]["merge_n"] > 0

    published = _published(demo, package_dir, tmp_path / "calib", sensor)
    session = load_session(demo)
    meas = measured_at(session, session.table("frames")[:, 0])
    ids = sorted(meas)
    cache = tmp_path / "cache"

    # replay_session (its first pass runs the network and keeps the fields) vs run; train budget's contact
    # stage on the same fields vs the clusters the runtime made of them
    results, compared, touched, defaults_differ = [], 0, 0, 0
    for i, r in enumerate(replay_session(demo, package, cal, cache=cache)):
        results.append(r)
        if r.seq in published:
            pub = published[r.seq]
            assert pub.t == pytest.approx(r.t, abs=1e-9) and [c.id for c in pub.contacts] == [c.id for c in r.clusters]
            _same(pub.contacts, r.clusters)
            compared += 1
            touched += bool(r.clusters)
        if r.fields is None:
            continue
        _same(_by_position(find_contacts(r.fields, cal, contacts)), _by_position(r.clusters))
        tips = np.array([meas[k]["tip"][i] for k in ids])
        forces = np.array([meas[k]["force"][i] for k in ids])
        assert sample_forces(r.fields, cal, tips, forces, contacts)["rows"] == frame_errors(r.clusters, tips, forces, EvalConfig())
        default = _by_position(find_contacts(r.fields, cal, ContactConfig()))
        defaults_differ += len(default) != len(r.clusters) or any(
            not np.allclose(a.force_n, b.force_n) for a, b in zip(default, _by_position(r.clusters)))
        r.fields = None
    n = len(results)
    assert n == len(session.table("frames")) and compared >= n - 5 and touched >= 20, (n, compared, touched)
    assert defaults_differ > 0            # the package's settings matter on this recording: the check can fail

    # the workbench: kept raw passes through the runtime's finish, then its line-up of the matched rows
    model = NetworkModel(package)
    passed = model.frame_pass(session, cal, cache)
    assert model.info["cached"] is True
    out = replay(passed, package, cal, temperature_of(session))
    assert out["stale_at"] is None
    starts = passed["_starts"]
    for j, r in enumerate(results):
        rows = slice(starts[j], starts[j + 1])
        assert passed["cl_id"][rows].astype(int).tolist() == [c.id for c in r.clusters]
        np.testing.assert_allclose(passed["cl_position_mm"][rows].reshape(-1, 3),
                                   np.array([c.position_mm for c in r.clusters]).reshape(-1, 3), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(out["force"][rows].reshape(-1, 3),
                                   np.array([c.force_n for c in r.clusters]).reshape(-1, 3), rtol=1e-9, atol=1e-12)
    table = model.build_table(session, cal, build_table(session, cal, brightness=False), None, cache)
    pred, info = model.deployed(session, table, cal)
    row = table.cols["cluster_row"].astype(int)
    frame = table.cols["frame"].astype(int)
    hit = np.flatnonzero(row >= 0)
    assert len(hit) >= 20 and info["stale_at"] is None
    for h in hit:                         # the table's sign is the F/T's: −(the published force)
        c = results[frame[h]].clusters[row[h] - starts[frame[h]]]
        np.testing.assert_allclose(pred[h], -np.asarray(c.force_n), rtol=1e-9, atol=1e-12)

    # recalibration: the collected frames (correction off) with the runtime's correction stage re-applied
    frames = corrected_frames(collect_frames(demo, cal, package, "int8", cache), cal)
    assert len(frames) == n
    for (t, cl), r in zip(frames, results):
        assert t == r.t and [c.id for c in cl] == [c.id for c in r.clusters]
        _same(cl, r.clusters)
