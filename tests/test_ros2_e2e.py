"""ROS 2 mode end to end: `tensortouch run --ros2` in one process, a stand-in rmw_zenoh subscriber
(tests/ros2_fake_subscriber.py, no project import) in another. The subscriber discovers the
publishers from the liveliness tokens alone, checks the attachments and decodes every message
type with rosbags' deserializer; the values are compared here with the runtime's own JSON keys.

No real ROS 2 runs here (see docs/wire.md "ROS 2").
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags.typesys")

from rosbags.typesys import Stores, get_typestore
from tensortouch.tools.bench.models import write_difference_package

from tests.conftest import dome_calibration
from tests.test_e2e_runtime import (
    SENSOR,
    SIZE,
    H,
    W,
    free_port,
    stop,
    write_poke_session,
)

ROOT = Path(__file__).resolve().parents[1]
DOMAIN = "7"


def test_run_ros2_to_a_separate_rmw_zenoh_style_subscriber(tmp_path):
    session = write_poke_session(tmp_path / "session")
    write_difference_package(tmp_path / "models" / "difference-32", SIZE)
    dome_calibration(tmp_path / "calib", SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    env = dict(os.environ, TENSORTOUCH_CALIBRATION=str(tmp_path / "calib"),
               TENSORTOUCH_MODELS=str(tmp_path / "models"), PYTHONUNBUFFERED="1")
    router = f"tcp/127.0.0.1:{free_port()}"
    sub = subprocess.Popen([sys.executable, str(ROOT / "tests" / "ros2_fake_subscriber.py"), router, DOMAIN,
                            "60", "7", "2", "95"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert sub.stdout.readline().strip() == "ready"
    run = subprocess.Popen([sys.executable, "-m", "tensortouch.runtime.shells.cli", "run", "--source", f"replay:{session}", "--loop", "--fast",
                            "--ros2", "--ros2-router", router, "--ros2-domain", DOMAIN, "--ros2-distro", "jazzy",
                            "--ros2-images", "disp_z,fn_z", "--ros2-stamp", "frame"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err_sub = sub.communicate(timeout=90)
    finally:
        err_run = stop(run)
    assert sub.returncode == 0, err_sub
    rep = json.loads(out.strip().splitlines()[-1])
    if os.environ.get("TT_ROS2_REPORT"):
        Path(os.environ["TT_ROS2_REPORT"]).write_text(json.dumps(rep))
    assert not rep["bad"], rep["bad"][:5]
    ts = get_typestore(Stores.ROS2_JAZZY)
    ns = "/tensortouch/TT_E2E"
    expected = {f"{ns}/wrench": "geometry_msgs/msg/WrenchStamped", f"{ns}/contacts": "sensor_msgs/msg/PointCloud2",
                f"{ns}/surface": "sensor_msgs/msg/PointCloud2", f"{ns}/image/disp_z": "sensor_msgs/msg/Image",
                f"{ns}/image/fn_z": "sensor_msgs/msg/Image", "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
                "/tf": "tf2_msgs/msg/TFMessage"}
    pubs = rep["publishers"]
    assert {t: p["type"] for t, p in pubs.items()} == expected, (list(pubs), err_run[-2000:])
    assert [n["node"] for n in rep["nodes"]] == ["tensortouch_TT_E2E"]
    for topic, p in pubs.items():
        assert p["hash"] == ts.hash_rihs01(p["type"]), topic        # RIHS01 from rosbags
        assert p["qos"] == "::,10:,:,:,,", topic                    # reliable, keep last 10
        assert p["msgs"], f"{topic}: nothing decoded ({err_run[-1500:]})"
        assert len(p["gids"]) == 1, topic                           # one GID per publisher
        seqs = p["seqs"]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs), topic
        assert max(p["age_s"]) < 5.0, topic                          # source time is wall clock ns
    assert len({p["gids"][0] for p in pubs.values()}) == len(pubs)  # GIDs differ between publishers

    # wrench: N and N*m (the runtime's JSON says N and N*mm), same frame time
    own = {round(w["t"], 6): w for w in rep["own"]["wrench"]}
    matched = 0
    for m in pubs[f"{ns}/wrench"]["msgs"]:
        assert m["frame"] == "TT_E2E_gel"
        w = own.get(round(m["t"], 6))
        if w is None:
            continue
        matched += 1
        np.testing.assert_allclose(m["force"], w["force_n"], atol=1e-9)
        np.testing.assert_allclose(m["torque"], np.array(w["torque_nmm"]) * 1e-3, atol=1e-12)
    assert matched >= 3
    assert any(abs(m["force"][2]) > 0.05 for m in pubs[f"{ns}/wrench"]["msgs"]), "no poke force seen"

    # contacts: positions m, forces N, area m^2, id
    own_c = {round(c["t"], 6): c["contacts"] for c in rep["own"]["contacts"] if c["contacts"]}
    cmp = 0
    for m in pubs[f"{ns}/contacts"]["msgs"]:
        assert m["fields"] == ["x", "y", "z", "fx", "fy", "fz", "force", "area", "id"]
        cs = own_c.get(round(m["t"], 6))
        if not cs or not m["points"]:
            continue
        cmp += 1
        p, c = m["points"][0], cs[0]
        np.testing.assert_allclose([p["x"], p["y"], p["z"]], np.array(c["position_mm"]) * 1e-3, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose([p["fx"], p["fy"], p["fz"], p["force"]], c["force_n"] + [c["force_mag_n"]],
                                   rtol=1e-6, atol=1e-7)
        assert p["area"] == pytest.approx(c["area_mm2"] * 1e-6, rel=1e-6)
        assert p["id"] == c["id"]
    assert cmp >= 1, "no contact frame compared"

    img = pubs[f"{ns}/image/fn_z"]["msgs"][0]
    assert img["shape"] == [SIZE, SIZE] and img["encoding"] == "32FC1" and img["step"] == 4 * SIZE
    surf = pubs[f"{ns}/surface"]["msgs"][0]
    assert surf["fields"][:3] == ["x", "y", "z"] and "disp_z" in surf["fields"] and "fs_x" in surf["fields"]
    assert 0 < surf["n"] <= SIZE * SIZE // 4                             # every 2nd row/column inside the mask
    assert 0.0 < surf["z_range"][1] < 0.05                              # metres: a dome a few cm high
    assert len(pubs[f"{ns}/surface"]["msgs"]) < len(pubs[f"{ns}/image/fn_z"]["msgs"])   # lower rate
    diag = pubs["/diagnostics"]["msgs"][-1]["status"][0]
    assert diag["hardware_id"] == SENSOR and diag["name"] == f"tensortouch/{SENSOR}"
    assert diag["values"]["sensor_id"] == SENSOR and "fps" in diag["values"]
    tf = pubs["/tf"]["msgs"][0]["transforms"][0]
    assert (tf["parent"], tf["child"], tf["w"]) == ("tensortouch_mount", "TT_E2E_gel", 1.0)


def _demo_like_env(tmp_path):
    session = write_poke_session(tmp_path / "session")
    write_difference_package(tmp_path / "models" / "difference-32", SIZE)
    dome_calibration(tmp_path / "calib", SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    meet = f"tcp/127.0.0.1:{free_port()}"      # the meeting point, moved off 7447 as docs/wire.md says
    env = dict(os.environ, TENSORTOUCH_CALIBRATION=str(tmp_path / "calib"), TENSORTOUCH_MODELS=str(tmp_path / "models"),
               PYTHONUNBUFFERED="1", TENSORTOUCH_ENDPOINT=meet)
    return session, meet, env


def _cli(*args):
    return [sys.executable, "-m", "tensortouch.runtime.shells.cli", *args]


def test_run_ros2_with_defaults_reaches_listen_and_a_plain_ros2_subscriber(tmp_path):
    """`run --ros2` with no router running: it listens at the meeting point itself (and says so in one
    line), so `listen` with its defaults and an rmw_zenoh-style subscriber connecting there both receive."""
    session, meet, env = _demo_like_env(tmp_path)
    run = subprocess.Popen(_cli("run", "--source", f"replay:{session}", "--loop", "--fast", "--ros2", "--ros2-domain", DOMAIN),
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        listen = subprocess.run(_cli("listen", SENSOR, "--count", "5", "--kinds", "wrench", "--timeout", "60"),
                                env=env, capture_output=True, text=True, timeout=90)
        sub = subprocess.run([sys.executable, str(ROOT / "tests" / "ros2_fake_subscriber.py"), f"connect:{meet}", DOMAIN,
                              "60", "7", "2", "20"], env=env, capture_output=True, text=True, timeout=90)
    finally:
        err_run = stop(run)
    assert listen.returncode == 0, (listen.stderr, err_run[-1500:])
    assert listen.stdout.count(f"tensortouch/{SENSOR}/wrench") == 5
    assert f"no Zenoh router at {meet}: this sensor listens there itself" in err_run
    assert sub.returncode == 0, sub.stderr
    rep = json.loads(sub.stdout.strip().splitlines()[-1])
    assert not rep["bad"], rep["bad"][:5]
    wrench = rep["publishers"]["/tensortouch/TT_E2E/wrench"]
    assert wrench["type"] == "geometry_msgs/msg/WrenchStamped" and len(wrench["msgs"]) >= 2


def test_run_ros2_with_defaults_connects_to_a_router_already_at_the_meeting_point(tmp_path):
    """A router (here the rmw_zenohd stand-in, listening) holds the meeting point: `run --ros2` with its
    defaults connects to it, and the ROS 2 messages arrive there."""
    session, meet, env = _demo_like_env(tmp_path)
    sub = subprocess.Popen([sys.executable, str(ROOT / "tests" / "ros2_fake_subscriber.py"), meet, DOMAIN,
                            "60", "7", "2", "20"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert sub.stdout.readline().strip() == "ready"
    run = subprocess.Popen(_cli("run", "--source", f"replay:{session}", "--loop", "--fast", "--ros2", "--ros2-domain", DOMAIN),
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err_sub = sub.communicate(timeout=90)
    finally:
        err_run = stop(run)
    assert sub.returncode == 0, (err_sub, err_run[-1500:])
    assert f"a Zenoh router listens at {meet}" in err_run
    rep = json.loads(out.strip().splitlines()[-1])
    assert not rep["bad"], rep["bad"][:5]
    assert len(rep["publishers"]["/tensortouch/TT_E2E/wrench"]["msgs"]) >= 2
