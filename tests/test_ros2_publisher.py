"""ROS 2 mode in one process: options, names and tokens, wall-clock stamps, and a publisher that
never raises into the frame loop. Real Zenoh sessions on loopback."""
import time

import pytest
import zenoh
from tensortouch.contracts import ros2_wire as rw
from tensortouch.runtime.apps.publisher import open_session
from tensortouch.runtime.apps.ros2_publisher import Ros2Config, Ros2Node

from tests.test_e2e_runtime import free_port


def test_config_checks_each_option():
    assert Ros2Config(domain_id=3).qos.token() == "::,10:,:,:,,"
    assert Ros2Config(reliability="best_effort", depth=5).qos.token() == "2::,5:,:,:,,"
    for bad, word in [({"distro": "iron"}, "distro"), ({"domain_id": 300}, "ROS_DOMAIN_ID"),
                      ({"namespace": "tensortouch"}, "namespace"), ({"namespace": "/a/1b"}, "namespace"),
                      ({"reliability": "sure"}, "reliability"), ({"depth": 0}, "depth"),
                      ({"images": ("fn_q",)}, "images"), ({"mount_xyzw": (0, 0, 0, 2)}, "quaternion"),
                      ({"stamp": "gps"}, "stamp"), ({"node": "9x"}, "node")]:
        with pytest.raises(rw.Ros2Error, match=word):
            Ros2Config(**bad)


def test_domain_default_comes_from_the_environment(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert Ros2Config().domain_id == 42


def test_wall_stamps_and_closed_publisher_never_raises():
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    ep = f"tcp/127.0.0.1:{free_port()}"
    got = []
    with open_session(listen=[ep], multicast=False) as s_pub, open_session(connect=[ep], multicast=False) as s_sub:
        node = Ros2Node(s_pub, Ros2Config(domain_id=9, images=(), surface_every=0))
        sensor = node.sensor("dome-1")
        key = rw.data_key(9, "/tensortouch/dome_1/wrench", "geometry_msgs/msg/WrenchStamped", "jazzy")
        sub = s_sub.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))
        time.sleep(0.5)
        t0 = time.time()
        assert sensor.publish_wrench((0, 0, -1), (1000, 0, 0), 1, 5.0)       # frame clock t = 5 s
        assert sensor.publish_wrench((0, 0, -2), (0, 0, 0), 2, 5.5)
        deadline = time.monotonic() + 3
        while len(got) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        msgs = [ts.deserialize_cdr(b, "geometry_msgs/msg/WrenchStamped") for b in got]
        stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in msgs]
        assert abs(stamps[0] - t0) < 1.0 and stamps[1] - stamps[0] == pytest.approx(0.5, abs=1e-6)
        assert msgs[0].wrench.torque.x == pytest.approx(1.0)                  # 1000 N*mm = 1 N*m
        node.close()
        assert not sensor.publish_wrench((0, 0, 0), (0, 0, 0), 3, 6.0)       # counted, not raised
        assert sensor.topics["wrench"].errors == 1
        sub.undeclare()
    assert isinstance(s_pub, zenoh.Session)


def test_hand_config_ros2_table_and_two_fingers_on_ros2(tmp_path, monkeypatch):
    from rosbags.typesys import Stores, get_typestore
    from tensortouch.runtime.apps.hand import Hand
    from tensortouch.runtime.apps.hand_config import HandConfigError, parse_hand_config

    from tests.hand_util import (
        hand_cfg,
        make_package,
        make_store,
        make_video,
        wait_until,
    )

    with pytest.raises(HandConfigError, match=r"\[ros2\]: unknown key 'distr'"):
        parse_hand_config({"ros2": {"distr": "jazzy"}, "finger": [{"name": "a", "serial": "S1"}]}, "h.toml")
    with pytest.raises(HandConfigError, match=r"\[ros2\].*distro"):
        parse_hand_config({"ros2": {"distro": "iron"}, "finger": [{"name": "a", "serial": "S1"}]}, "h.toml")
    monkeypatch.setenv("TENSORTOUCH_ENDPOINT", f"tcp/127.0.0.1:{free_port()}")    # no router runs there
    cfg = parse_hand_config({"hand": {"name": "left"}, "ros2": {"domain_id": 4, "images": []},
                             "finger": [{"name": "a", "serial": "S1"}]}, "h.toml")
    assert cfg.listen == () and cfg.connect == ()           # router "auto", none there: the hand listens there
    cfg = parse_hand_config({"hand": {"name": "left"}, "ros2": {"router": "tcp/127.0.0.1:7447"},
                             "finger": [{"name": "a", "serial": "S1"}]}, "h.toml")
    assert cfg.listen == () and cfg.connect == ("tcp/127.0.0.1:7447",)      # a named router: connect to it
    cfg = parse_hand_config({"hand": {"name": "left"}, "ros2": {"domain_id": 4, "images": []},
                             "finger": [{"name": "a", "serial": "S1"}]}, "h.toml")
    assert cfg.ros2.node == "tensortouch_left" and cfg.ros2.images == ()

    pkg = make_package(tmp_path / "models" / "difference-32")
    make_store(tmp_path / "store", ("TT-A", "TT-B"))
    videos = {s: make_video(tmp_path / f"{s}.avi", seed=i) for i, s in enumerate(("TT-A", "TT-B"))}
    router = f"tcp/127.0.0.1:{free_port()}"
    base = hand_cfg(tmp_path, pkg, {s: f"file:{v}" for s, v in videos.items()})
    import dataclasses

    cfg = dataclasses.replace(base, listen=(), connect=(router,),
                              ros2=Ros2Config(domain_id=4, node="tensortouch_hand", images=("fn_z",), router=router))
    ts = get_typestore(Stores.ROS2_JAZZY)
    tokens, wrenches = set(), {}
    with open_session(listen=[router], multicast=False) as s:
        lv = s.liveliness().declare_subscriber("@ros2_lv/4/**", lambda smp: tokens.add(str(smp.key_expr)),
                                               history=True)
        sub = s.declare_subscriber("4/tensortouch/*/wrench/**", lambda smp: wrenches.setdefault(
            str(smp.key_expr).split("/")[2], []).append(
            ts.deserialize_cdr(smp.payload.to_bytes(), "geometry_msgs/msg/WrenchStamped")))
        with Hand(cfg):
            assert wait_until(lambda: {"TT_A", "TT_B"} <= set(wrenches) and all(len(v) > 5 for v in wrenches.values()), 15)
        assert any(t.endswith("/NN/%/%tensortouch/tensortouch_hand") for t in tokens)
        mp = [t for t in tokens if "/MP/" in t]
        assert len(mp) == 2 + 2 * 4          # /diagnostics, /tf + wrench, contacts, image/fn_z, surface per finger
        assert {m.header.frame_id for m in wrenches["TT_A"]} == {"TT_A_gel"}
        sub.undeclare()
        lv.undeclare()
