"""ROS1 / ROS2 bags and MCAP files written here with rosbags / mcap, read back as sessions."""
import json

import cv2
import numpy as np
import pytest
from tensortouch.contracts.errors import SessionError
from tensortouch.contracts.session import load_session
from tensortouch.tools.sessions.bags import TopicMap, convert
from tensortouch.tools.sessions.writer import read_frames

pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

T0 = 1_700_000_000
N_IMG, N_POSE, N_WR = 4, 12, 20


def _truth():
    rng = np.random.default_rng(5)
    imgs = [rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) for _ in range(N_IMG)]
    pose_t = T0 + 0.5 + np.arange(N_POSE) / 120
    pos_m = rng.normal(0, 0.01, (N_POSE, 3))
    wr_t = T0 + 0.5 + np.arange(N_WR) / 200
    wr = rng.normal(0, 1, (N_WR, 6))
    img_t = T0 + 0.5 + np.arange(N_IMG) / 30
    return imgs, img_t, pose_t, pos_m, wr_t, wr


def _msgs(ts):
    imgs, img_t, pose_t, pos_m, wr_t, wr = _truth()
    ros1 = any(f[0] == "seq" for f in ts.fielddefs["std_msgs/msg/Header"][1])

    def H(t):
        stamp = ts.types["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))
        extra = {"seq": 0} if ros1 else {}
        return ts.types["std_msgs/msg/Header"](stamp=stamp, frame_id="x", **extra)
    G = lambda n: ts.types[f"geometry_msgs/msg/{n}"]  # noqa: E731
    out = []
    for t, p in zip(pose_t, pos_m):
        m = G("PoseStamped")(header=H(t), pose=G("Pose")(position=G("Point")(x=p[0], y=p[1], z=p[2]),
                                                         orientation=G("Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0)))
        out.append(("/mocap/ind0", "geometry_msgs/msg/PoseStamped", t, m))
    base = G("PoseStamped")(header=H(T0 + 0.5), pose=G("Pose")(position=G("Point")(x=0.001, y=0.0, z=0.0),
                                                             orientation=G("Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0)))
    out.append(("/mocap/base", "geometry_msgs/msg/PoseStamped", T0 + 0.5, base))
    for t, w in zip(wr_t, wr):
        m = G("WrenchStamped")(header=H(t), wrench=G("Wrench")(force=G("Vector3")(x=w[0], y=w[1], z=w[2]),
                                                               torque=G("Vector3")(x=w[3], y=w[4], z=w[5])))
        out.append(("/ati0/wrench", "geometry_msgs/msg/WrenchStamped", t, m))
    for t, img in zip(img_t, imgs):
        ok, buf = cv2.imencode(".png", img)
        m = ts.types["sensor_msgs/msg/CompressedImage"](header=H(t), format="png", data=buf.ravel())
        out.append(("/cam/compressed", "sensor_msgs/msg/CompressedImage", t, m))
    m = ts.types["sensor_msgs/msg/Temperature"](header=H(T0 + 0.6), temperature=298.15, variance=0.0)
    out.append(("/gel/temp", "sensor_msgs/msg/Temperature", T0 + 0.6, m))
    return sorted(out, key=lambda r: r[2])


MAP = {"sensor_id": "BAG-1", "clock": "header", "units": {"length": "m", "torque": "N*m", "temperature": "K"},
       "ft_to_indenter": {"rotation_wxyz": [1, 0, 0, 0], "translation_mm": [0, 0, 44]},
       "frames": {"topic": "/cam/compressed"},
       "poses": [{"topic": "/mocap/ind0", "indenter": 0, "base_topic": "/mocap/base"}],
       "wrench": [{"topic": "/ati0/wrench", "indenter": 0}],
       "temperature": {"topic": "/gel/temp"}}


def _check(session_dir):
    imgs, img_t, pose_t, pos_m, wr_t, wr = _truth()
    s = load_session(session_dir)
    assert s.sensor_id == "BAG-1"
    poses = s.table("poses")
    np.testing.assert_allclose(poses[:, 2:5], pos_m * 1000 - [1.0, 0, 0], atol=1e-6)   # m -> mm, minus base
    np.testing.assert_allclose(poses[:, 0], pose_t - (T0 + 0.5), atol=1e-6)
    w = s.table("wrench")
    np.testing.assert_allclose(w[:, 2:5], wr[:, :3], atol=1e-9)
    np.testing.assert_allclose(w[:, 5:8], wr[:, 3:] * 1000, atol=1e-6)               # N*m -> N*mm
    np.testing.assert_allclose(s.table("temperature")[:, 1], [25.0], atol=1e-9)         # K -> degC
    frames = dict(read_frames(s))
    for i, img in enumerate(imgs):
        np.testing.assert_array_equal(frames[i], img)
    assert s.streams["wrench"]["ft_to_indenter"]["translation_mm"] == [0, 0, 44]


def _write_bag(writer, ts, serialize):
    """Every test message through a rosbags bag writer (ROS1 or ROS2), one connection per topic."""
    conns = {}
    for topic, typ, t, m in _msgs(ts):
        if topic not in conns:
            conns[topic] = writer.add_connection(topic, typ, typestore=ts)
        writer.write(conns[topic], int(t * 1e9), serialize(m, typ))


def test_ros1_bag_to_session(tmp_path):
    from rosbags.rosbag1 import Writer

    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "rec.bag"
    with Writer(bag) as w:
        _write_bag(w, ts, ts.serialize_ros1)
    _check(convert(bag, TopicMap.load(MAP), tmp_path / "s"))


@pytest.mark.parametrize("plugin", ["SQLITE3", "MCAP"])
def test_ros2_bag_to_session(tmp_path, plugin):
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = get_typestore(Stores.ROS2_HUMBLE)
    bag = tmp_path / "rec2"
    with Writer(bag, version=9, storage_plugin=getattr(StoragePlugin, plugin)) as w:
        _write_bag(w, ts, ts.serialize_cdr)
    _check(convert(bag, TopicMap.load(MAP), tmp_path / "s"))


def test_mcap_cdr_to_session(tmp_path):
    from mcap.writer import Writer

    ts = get_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "rec.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2")
        chans = {}
        for topic, typ, t, m in _msgs(ts):
            if topic not in chans:
                sid = w.register_schema(typ, "ros2msg", ts.generate_msgdef(typ, ros_version=2)[0].encode())
                chans[topic] = w.register_channel(topic, "cdr", sid)
            w.add_message(chans[topic], int(t * 1e9), bytes(ts.serialize_cdr(m, typ)), int(t * 1e9))
        w.finish()
    _check(convert(path, TopicMap.load(MAP), tmp_path / "s"))


def test_mcap_json_log_clock_and_missing_topic(tmp_path):
    from mcap.writer import Writer

    path = tmp_path / "rec.mcap"
    img = np.full((8, 8, 3), 7, np.uint8)
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("Img", "jsonschema", b"{}")
        ch = w.register_channel("/cam", "json", sid)
        for i in range(3):
            msg = {"height": 8, "width": 8, "encoding": "bgr8", "step": 24, "data": img.ravel().tolist()}
            w.add_message(ch, (i + 1) * 10**8, json.dumps(msg).encode(), 0)
        w.finish()
    m = TopicMap.load({"sensor_id": "J", "clock": "log", "frames": {"topic": "/cam"}})
    s = load_session(convert(path, m, tmp_path / "s"))
    np.testing.assert_allclose(s.table("frames")[:, 0], [0.0, 0.1, 0.2], atol=1e-9)
    bad = TopicMap.load({"sensor_id": "J", "frames": {"topic": "/cam"}, "wrench": [{"topic": "/nope", "indenter": 0}]})
    with pytest.raises(SessionError, match="/nope.*missing stream"):
        convert(path, bad, tmp_path / "s2")


def test_topic_map_rejects_unknown_keys_and_units():
    with pytest.raises(SessionError, match="unknown keys"):
        TopicMap.load({"sensor_id": "x", "frames": {"topic": "/a"}, "posez": []})
    with pytest.raises(SessionError, match="units.length"):
        TopicMap.load({"sensor_id": "x", "frames": {"topic": "/a"}, "units": {"length": "inch"}})
