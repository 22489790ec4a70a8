"""ROS 2 mode in one process: options, names and tokens, wall-clock stamps, and a publisher that
never raises into the frame loop. Real Zenoh sessions on loopback."""
import struct
import time

import pytest
import zenoh

from runtime import ros2_wire as rw
from runtime.publisher import open_session
from runtime.ros2_publisher import Ros2Config, Ros2Node
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


def test_names_tokens_and_attachment():
    assert rw.name_token("TT-0001") == "TT_0001" and rw.name_token("01.a") == "s01_a"
    q = rw.Qos()
    tok = rw.publisher_token(0, "abc", 0, 3, "/", "n", "/ns/x/wrench", "geometry_msgs/msg/WrenchStamped", "humble", q)
    assert tok == ("@ros2_lv/0/abc/0/3/MP/%/%/n/%ns%x%wrench/geometry_msgs::msg::dds_::WrenchStamped_/"
                   "TypeHashNotSupported/::,10:,:,:,,")
    assert rw.node_token(5, "abc", 0, "/tensortouch", "n") == "@ros2_lv/5/abc/0/0/NN/%/%tensortouch/n"
    assert rw.data_key(5, "/a/b", "sensor_msgs/msg/Image", "kilted").startswith(
        "5/a/b/sensor_msgs::msg::dds_::Image_/RIHS01_d31d41a9")
    gid = rw.gid_of(tok)
    att = rw.attachment(7, 123456789, gid)
    assert len(att) == 33 and att[16] == 16 and struct.unpack_from("<qq", att) == (7, 123456789)
    assert rw.parse_attachment(att) == (7, 123456789, gid)
    with pytest.raises(rw.Ros2Error):
        rw.parse_attachment(att[:-1])


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
