"""Golden bytes: contracts/ros2_cdr.py against rosbags' CDR serializer (byte-identical to rclpy's),
and the RIHS01 type hashes in contracts/ros2_wire.py against rosbags' hash computation."""
from __future__ import annotations

import numpy as np
import pytest

rosbags_typesys = pytest.importorskip("rosbags.typesys")

from tensortouch.contracts import ros2_cdr as cdr
from tensortouch.contracts import ros2_wire as rw

STORES = {"humble": "ROS2_HUMBLE", "jazzy": "ROS2_JAZZY", "kilted": "ROS2_KILTED",
          "rolling": "ROS2_LYRICAL"}   # rosbags' newest store stands for rolling


def _store(distro="jazzy"):
    return rosbags_typesys.get_typestore(getattr(rosbags_typesys.Stores, STORES[distro]))


def _header(ts, t, frame):
    sec, nsec = cdr.stamp_of(t)
    Time = ts.types["builtin_interfaces/msg/Time"]
    return ts.types["std_msgs/msg/Header"](stamp=Time(sec=sec, nanosec=nsec), frame_id=frame)


@pytest.mark.parametrize("t", [1718000000.125, 0.0, 12.999999999, 3.5e-9])
def test_wrench_stamped_golden(t):
    ts = _store()
    V = ts.types["geometry_msgs/msg/Vector3"]
    msg = ts.types["geometry_msgs/msg/WrenchStamped"](
        header=_header(ts, t, "dome01_gel"),
        wrench=ts.types["geometry_msgs/msg/Wrench"](force=V(x=0.05, y=0.0, z=-0.8),
                                                    torque=V(x=1.6e-3, y=-1.9e-3, z=1e-4)))
    ours = cdr.wrench_stamped(t, "dome01_gel", (0.05, 0.0, -0.8), (1.6e-3, -1.9e-3, 1e-4))
    assert ours == bytes(ts.serialize_cdr(msg, "geometry_msgs/msg/WrenchStamped"))
    assert ours[:4] == b"\x00\x01\x00\x00"


@pytest.mark.parametrize("frame", ["g", "ab", "abc", "dome01_gel"])   # every string padding case
def test_image_golden(frame):
    ts = _store()
    img = np.arange(5 * 7, dtype=np.float32).reshape(5, 7) * -0.25
    msg = ts.types["sensor_msgs/msg/Image"](
        header=_header(ts, 17.25, frame), height=5, width=7, encoding="32FC1", is_bigendian=0,
        step=28, data=img.astype("<f4").view(np.uint8).ravel())
    assert cdr.image_32fc1(17.25, frame, img) == bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))


def test_point_cloud2_golden():
    ts = _store()
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("force", "<f4"), ("id", "<u4")])
    pts = np.zeros(3, dt)
    pts["x"], pts["z"], pts["force"], pts["id"] = [1e-3, 2e-3, 3e-3], 0.014, [0.5, 1.0, 2.0], [3, 9, 11]
    PF = ts.types["sensor_msgs/msg/PointField"]
    fields = [PF(name=n, offset=dt.fields[n][1], datatype=7 if n != "id" else 6, count=1) for n in dt.names]
    msg = ts.types["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, 5.5, "dome01_gel"), height=1, width=3, fields=fields, is_bigendian=False,
        point_step=dt.itemsize, row_step=3 * dt.itemsize, data=pts.view(np.uint8).ravel(), is_dense=True)
    assert cdr.point_cloud2(5.5, "dome01_gel", pts) == bytes(
        ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    empty = np.zeros(0, dt)
    msg_empty = ts.types["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, 5.5, "x"), height=1, width=0, fields=fields, is_bigendian=False,
        point_step=dt.itemsize, row_step=0, data=np.zeros(0, np.uint8), is_dense=True)
    assert cdr.point_cloud2(5.5, "x", empty) == bytes(ts.serialize_cdr(msg_empty, "sensor_msgs/msg/PointCloud2"))


def test_diagnostic_array_golden():
    ts = _store()
    KV, DS = ts.types["diagnostic_msgs/msg/KeyValue"], ts.types["diagnostic_msgs/msg/DiagnosticStatus"]
    ours = [cdr.DiagnosticStatus(1, "tensortouch/dome01", "contact", "dome01",
                                 (("fps", "118.4"), ("flags", "model_fallback"), ("é", ""))),
            cdr.DiagnosticStatus(0, "tensortouch/b", "", "b", ())]
    msg = ts.types["diagnostic_msgs/msg/DiagnosticArray"](
        header=_header(ts, 1.5, ""),
        status=[DS(level=s.level, name=s.name, message=s.message, hardware_id=s.hardware_id,
                   values=[KV(key=k, value=v) for k, v in s.values]) for s in ours])
    assert cdr.diagnostic_array(1.5, ours) == bytes(
        ts.serialize_cdr(msg, "diagnostic_msgs/msg/DiagnosticArray"))


def test_tf_message_golden():
    ts = _store()
    V, Q = ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Quaternion"]
    trs = [cdr.Transform(2.25, "tensortouch_mount", "dome01_gel", (0.0, 0.01, 0.02), (0.0, 0.0, 0.7071, 0.7071)),
           cdr.Transform(2.25, "m", "b_gel")]
    msg = ts.types["tf2_msgs/msg/TFMessage"](transforms=[
        ts.types["geometry_msgs/msg/TransformStamped"](
            header=_header(ts, tr.t, tr.parent), child_frame_id=tr.child,
            transform=ts.types["geometry_msgs/msg/Transform"](
                translation=V(x=tr.translation_m[0], y=tr.translation_m[1], z=tr.translation_m[2]),
                rotation=Q(x=tr.rotation_xyzw[0], y=tr.rotation_xyzw[1], z=tr.rotation_xyzw[2],
                           w=tr.rotation_xyzw[3])))
        for tr in trs])
    assert cdr.tf_message(trs) == bytes(ts.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))


def test_round_trip_through_rosbags_deserializer():
    ts = _store()
    img = np.linspace(-1, 1, 12, dtype=np.float32).reshape(3, 4)
    back = ts.deserialize_cdr(cdr.image_32fc1(3.0, "f", img), "sensor_msgs/msg/Image")
    assert back.encoding == "32FC1" and (back.height, back.width, back.step) == (3, 4, 16)
    np.testing.assert_array_equal(np.frombuffer(bytes(back.data), "<f4").reshape(3, 4), img)


def test_stamp_rejects_non_finite_and_overflow():
    with pytest.raises(ValueError):
        cdr.stamp_of(float("nan"))
    with pytest.raises(ValueError):
        cdr.stamp_of(2.0**31)
    assert cdr.stamp_of(1.9999999996) == (2, 0)


@pytest.mark.parametrize("distro", ["jazzy", "kilted", "rolling"])
def test_type_hashes_match_rosbags_rihs01(distro):
    ts = _store(distro)
    for ros_type in rw.TYPES:
        assert rw.type_hash(ros_type, distro) == ts.hash_rihs01(ros_type), ros_type


def test_humble_uses_the_placeholder_and_dds_names():
    assert rw.type_hash("sensor_msgs/msg/Image", "humble") == "TypeHashNotSupported"
    assert rw.dds_type("geometry_msgs/msg/WrenchStamped") == "geometry_msgs::msg::dds_::WrenchStamped_"
