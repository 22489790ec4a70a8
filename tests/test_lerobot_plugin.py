"""The LeRobot plugin distributions (integrations/lerobot, integrations/lerobot_robot) against a running
`tensortouch run` on the demo.

Real parts: LeRobot 0.4.4's own plugin discovery, `make_cameras_from_configs` and
`make_robot_from_config`, `tensortouch run` in its own process, Zenoh on loopback. Needs the plugins and
LeRobot installed in the test venv as .ci/run does (lerobot==0.4.4 with --no-deps, draccus, and for the
robot layer the packages LeRobot imports on the way; see docs/lerobot.md).

No stand-in module: LeRobot 0.4.4's robot layer imports torch and torchvision (via lerobot.processor), so
the robot test runs where both import, in the venv .ci/lerobot makes (torch 2.14.1 + torchvision 0.29.1,
docs/lerobot.md says why those). Where the robot plugin is not installed, the robot test is skipped;
where it is installed and LeRobot's robot layer does not import, it fails.
"""
import dataclasses
import importlib.metadata
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from tensortouch.contracts import paths
from tensortouch.runtime.apps.subscriber import Subscriber

from tests.test_e2e_runtime import free_port, stop


def _missing() -> str | None:
    try:
        importlib.metadata.distribution("lerobot_camera_tensortouch")
        import lerobot.cameras  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - the reason is shown in the skip message
        return f"{type(exc).__name__}: {exc} (LeRobot's venv: .ci/lerobot, docs/lerobot.md)"
    if not (paths.demo_dir() / "session.json").is_file():
        return "no demo recording"
    return None


pytestmark = pytest.mark.skipif(_missing() is not None, reason=str(_missing()))


@pytest.fixture(scope="module")
def runtime_endpoint():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "tensortouch.runtime.shells.cli", "run", "--loop", "--listen", endpoint],
                            env=dict(os.environ, PYTHONUNBUFFERED="1"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    yield endpoint, proc
    stop(proc)


def test_lerobot_factory_builds_the_camera_and_reads_fields(runtime_endpoint):
    from lerobot.cameras.utils import make_cameras_from_configs
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()                      # imports lerobot_camera_tensortouch (by its dist name)
    from lerobot_camera_tensortouch import (
        TensorTouchCamera,
        TensorTouchCameraConfig,
        from_image,
    )

    endpoint, _ = runtime_endpoint
    cfg = TensorTouchCameraConfig(sensor_id="TWIN-DEMO", connect=endpoint, timeout_ms=15000,
                                  channels=("disp_x", "disp_y", "disp_z"))
    assert cfg.type == "tensortouch"
    cams = make_cameras_from_configs({"gel": cfg})
    cam = cams["gel"]
    assert isinstance(cam, TensorTouchCamera)
    fields = {}
    lock = threading.Lock()

    def keep(f):
        with lock:
            fields[f.seq] = f.data[0:3].copy()

    with Subscriber("TWIN-DEMO", connect=[endpoint], on_fields=keep):
        cam.connect()
        try:
            assert cam.is_connected and (cam.height, cam.width) == (128, 128)
            img = cam.read()
            assert img.shape == (128, 128, 3) and img.dtype == np.uint8
            seen, t0 = set(), time.perf_counter()
            for _ in range(20):
                img = cam.async_read(timeout_ms=2000)
                seen.add(cam.last_read_seq)
            rate = 20 / (time.perf_counter() - t0)
            assert len(seen) == 20, seen                       # each async_read returns a new frame
            compared = 0
            for _ in range(10):
                img, seq = cam.async_read(timeout_ms=2000), cam.last_read_seq
                time.sleep(0.1)
                with lock:
                    ref = fields.get(seq)
                if ref is None:
                    continue                                   # the plain subscriber missed this one
                # fixed full scale 2.5 mm: pixel steps of 2.5/127 mm; half a step of rounding
                assert np.abs(from_image(img, cfg.channels) - ref).max() <= 2.5 / 127 * 0.51 + 1e-3
                compared += 1
            assert compared >= 5, compared
            assert cam.read_latest(max_age_ms=500).shape == (128, 128, 3)
            print(f"LeRobot camera: {rate:.1f} frames/s via async_read")
        finally:
            cam.disconnect()
    assert not cam.is_connected


def test_tactile_floats_wrench_and_top_contacts(runtime_endpoint):
    from lerobot_camera_tensortouch import (
        TensorTouchTactile,
        TensorTouchTactileConfig,
        feature_names,
    )

    endpoint, proc = runtime_endpoint
    tac = TensorTouchTactile(TensorTouchTactileConfig(sensor_id="TWIN-DEMO", connect=endpoint, top_k=8,
                                                      timeout_ms=15000))
    tac.connect()
    try:
        names = feature_names("tactile", 8)
        assert list(tac.features) == names and len(names) == 6 + 8 * 8
        pressed = None
        deadline = time.monotonic() + 20
        while pressed is None and time.monotonic() < deadline:
            s = tac.async_read(timeout_ms=2000)
            assert list(s) == names and all(isinstance(v, float) for v in s.values())
            if s["tactile.c0.present"] == 1.0:
                pressed = s
        assert pressed is not None, "no contact in 20 s of the looping demo"
        n = int(sum(pressed[f"tactile.c{i}.present"] for i in range(8)))
        # the wrench is the sum of the contacts' forces (all of them fit in top_k = 8 here)
        total = sum(pressed[f"tactile.c{i}.fz"] for i in range(n))
        assert abs(total - pressed["tactile.fz"]) < 1e-3 * max(1.0, abs(total))
        mags = [np.linalg.norm([pressed[f"tactile.c{i}.f{a}"] for a in "xyz"]) for i in range(n)]
        assert mags == sorted(mags, reverse=True)
        assert tac.read_latest(max_age_ms=500)["tactile.fz"] == tac.read_latest(max_age_ms=500)["tactile.fz"]
        # staleness: stop the runtime; the latest state ages and async_read times out
        stop(proc)
        time.sleep(0.6)
        with pytest.raises(TimeoutError, match="old"):
            tac.read_latest(max_age_ms=300)
        try:
            tac.async_read(timeout_ms=100)           # at most one state arrived after the last read
        except TimeoutError:
            pass
        with pytest.raises(TimeoutError, match="no new state"):
            tac.async_read(timeout_ms=100)
    finally:
        tac.disconnect()


ROBOT_INSTALL = ("its own venv: pip install torch==2.14.1 torchvision==0.29.1, then lerobot==0.4.4 and the plugins "
                 "with --no-deps and integrations/lerobot_robot/requirements-lerobot-0.4.4.txt; docs/lerobot.md, "
                 ".ci/lerobot")


def _lerobot_robots() -> None:
    """Import LeRobot's real robot layer (lerobot.robots -> lerobot.processor -> torch, torchvision). Called
    with the robot plugin installed, so a layer that does not import is a failure, not a skip."""
    try:
        import lerobot.robots  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - e.g. PyPI's torchvision beside a CPU-only torch (operator torchvision::nms)
        pytest.fail(f"LeRobot's robot layer does not import: {type(exc).__name__}: {exc} ({ROBOT_INSTALL})")


def _expected_floats(wrench, contacts, prefix: str, top_k: int) -> dict[str, float]:
    """What the floats must be, from the wrench and contacts a plain Subscriber decoded (N, N·mm, mm, mm²)."""
    out = {f"{prefix}.fx": wrench.force_n[0], f"{prefix}.fy": wrench.force_n[1], f"{prefix}.fz": wrench.force_n[2],
           f"{prefix}.tx": wrench.torque_nmm[0], f"{prefix}.ty": wrench.torque_nmm[1],
           f"{prefix}.tz": wrench.torque_nmm[2]}
    strongest = sorted(contacts, key=lambda c: c.force_mag_n, reverse=True)
    for i in range(top_k):
        c = strongest[i] if i < len(strongest) else None
        out[f"{prefix}.c{i}.present"] = 1.0 if c else 0.0
        for j, a in enumerate("xyz"):
            out[f"{prefix}.c{i}.{a}"] = c.position_mm[j] if c else 0.0
            out[f"{prefix}.c{i}.f{a}"] = c.force_n[j] if c else 0.0
        out[f"{prefix}.c{i}.area"] = c.area_mm2 if c else 0.0
    return out


def test_robot_factory_reads_floats_and_frames(tmp_path, monkeypatch):
    try:
        importlib.metadata.distribution("lerobot_robot_tensortouch")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip(f"lerobot_robot_tensortouch is not installed ({ROBOT_INSTALL})")
    # the meeting point moved to a free loopback port, for the runtime and for the plugins' defaults;
    # the runtime starts first so that its start-up overlaps LeRobot's imports
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    monkeypatch.setenv("TENSORTOUCH_ENDPOINT", endpoint)
    proc = subprocess.Popen([sys.executable, "-m", "tensortouch.runtime.shells.cli", "run", "--loop"],
                            env=dict(os.environ, PYTHONUNBUFFERED="1"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    robot = None
    try:
        _lerobot_robots()
        import draccus
        from lerobot.cameras.utils import make_cameras_from_configs
        from lerobot.robots import RobotConfig, make_robot_from_config
        from lerobot.utils.errors import DeviceNotConnectedError
        from lerobot.utils.import_utils import register_third_party_plugins

        register_third_party_plugins()            # imports both plugins by their distribution names
        from lerobot_camera_tensortouch import TensorTouchCamera, TensorTouchCameraConfig, from_image
        from lerobot_robot_tensortouch import TensorTouchRobot, TensorTouchRobotConfig

        top_k = 4
        # as `lerobot-record --robot.type=tensortouch ...` builds it: draccus picks the registered type
        @dataclasses.dataclass
        class Command:
            robot: RobotConfig

        cfg = draccus.parse(Command, args=[
            "--robot.type=tensortouch", "--robot.sensor_id=TWIN-DEMO", f"--robot.top_k={top_k}",
            "--robot.timeout_ms=15000", "--robot.max_age_ms=500", f"--robot.calibration_dir={tmp_path}",
            ("--robot.cameras={gel: {type: tensortouch, sensor_id: TWIN-DEMO, timeout_ms: 15000, "
            "width: 128, height: 128, fps: 30}}")]).robot
        assert isinstance(cfg, TensorTouchRobotConfig) and cfg.type == "tensortouch" and cfg.connect is None
        assert isinstance(cfg.cameras["gel"], TensorTouchCameraConfig)
        robot = make_robot_from_config(cfg)
        assert isinstance(robot, TensorTouchRobot) and isinstance(robot.cameras["gel"], TensorTouchCamera)
        names = [f"tactile.{f}" for f in ("fx", "fy", "fz", "tx", "ty", "tz")] + [
            f"tactile.c{i}.{f}" for i in range(top_k) for f in ("present", "x", "y", "z", "fx", "fy", "fz", "area")]
        assert robot.observation_features == {**{n: float for n in names}, "gel": (128, 128, 3)}
        assert robot.action_features == {}

        lock = threading.Lock()
        wrenches, contacts, fields = {}, {}, {}

        def keep(store, value):
            with lock:
                store[value[0]] = value[1]

        with Subscriber("TWIN-DEMO", connect=[endpoint],
                        on_wrench=lambda w: keep(wrenches, (w.seq, w)),
                        on_contacts=lambda f: keep(contacts, (f.seq, f.contacts)),
                        on_fields=lambda f: keep(fields, (f.seq, f.data[0:3].copy()))):
            robot.connect()
            assert robot.is_connected
            assert [c["id"] for c in TensorTouchCamera.find_cameras()] == ["TWIN-DEMO"]
            checked = pressed = frames = 0
            deadline = time.monotonic() + 25
            while (pressed < 3 or frames < 3) and time.monotonic() < deadline:
                obs = robot.get_observation()
                seq, cam_seq = robot.tactile.last_read_seq, robot.cameras["gel"].last_read_seq
                assert list(obs) == [*names, "gel"] and all(isinstance(obs[n], float) for n in names)
                time.sleep(0.05)                         # let the plain subscriber catch up
                with lock:
                    w, cs, ref = wrenches.get(seq), contacts.get(seq), fields.get(cam_seq)
                if w is not None and cs is not None:
                    assert {n: obs[n] for n in names} == _expected_floats(w, cs, "tactile", top_k), seq
                    checked += 1
                    if obs["tactile.c0.present"] == 1.0:
                        pressed += 1
                        # units: contact positions on the gel in mm (not m), forces in N
                        assert 1.0 < np.linalg.norm([obs[f"tactile.c0.{a}"] for a in "xyz"]) < 50.0
                        assert obs["tactile.c0.area"] > 0.0
                        assert abs(obs["tactile.fz"]) > 0.0
                if ref is not None:
                    img = obs["gel"]
                    assert img.shape == (128, 128, 3) and img.dtype == np.uint8
                    assert np.abs(from_image(img, ("disp_x", "disp_y", "disp_z")) - ref).max() <= 2.5 / 127 * 0.51 + 1e-3
                    frames += 1
            assert pressed >= 3 and frames >= 3, (checked, pressed, frames)

            # a missing sensor and a camera config that does not match the published grid fail on connect
            missing = make_robot_from_config(TensorTouchRobotConfig(sensor_id="NO-SUCH-SENSOR", timeout_ms=300,
                                                                    calibration_dir=tmp_path))
            with pytest.raises(ConnectionError, match="NO-SUCH-SENSOR"):
                missing.connect()
            assert not missing.is_connected
            wrong = make_cameras_from_configs({"x": TensorTouchCameraConfig(
                sensor_id="TWIN-DEMO", width=64, height=64, fps=30, timeout_ms=15000)})["x"]
            with pytest.raises(ValueError, match="64×64 but the runtime publishes 128×128"):
                wrong.connect()
            assert not wrong.is_connected

            assert robot.send_action({}) == {}
            with pytest.raises(ValueError, match="no action"):
                robot.send_action({"gripper.pos": 1.0})
            # a stopped runtime: the next observation raises instead of returning old or zero values
            stop(proc)
            time.sleep(0.7)
            with pytest.raises(TimeoutError, match="old"):
                robot.get_observation()
        robot.disconnect()
        assert not robot.is_connected
        with pytest.raises(DeviceNotConnectedError):
            robot.get_observation()
        print(f"LeRobot robot: {checked} observations checked against the subscriber, {pressed} pressed")
    finally:
        if robot is not None and robot.tactile.is_connected:
            robot.disconnect()                       # open Zenoh sessions would hold up the interpreter's exit
        if proc.poll() is None:
            stop(proc)
