"""CDR encoding of the few ROS 2 message types the runtime publishes (docs/wire.md "ROS 2").

Pure struct/numpy, no ROS and no zenoh import. Each function returns a complete serialized
message: the 4-byte encapsulation header `00 01 00 00` (CDR, little endian) followed by the body,
with primitives aligned to their size relative to the end of the header, strings as uint32 length
(including the NUL) + bytes + NUL, sequences as uint32 count + elements. The bytes are what
rclpy's `serialize_message` produces (tests/test_ros2_cdr.py compares them with rosbags'
serializer for every type).

Values are SI, as ROS expects (REP 103): m, N, N·m, Pa, s.
"""
from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

CDR_LE_HEADER = b"\x00\x01\x00\x00"

# sensor_msgs/PointField datatypes
POINTFIELD_TYPES = {np.dtype("<i1"): 1, np.dtype("u1"): 2, np.dtype("<i2"): 3, np.dtype("<u2"): 4,
                    np.dtype("<i4"): 5, np.dtype("<u4"): 6, np.dtype("<f4"): 7, np.dtype("<f8"): 8}

# diagnostic_msgs/DiagnosticStatus levels
DIAG_OK, DIAG_WARN, DIAG_ERROR, DIAG_STALE = 0, 1, 2, 3


class _Writer:
    """Little-endian CDR writer; alignment is counted from the end of the encapsulation header."""

    def __init__(self) -> None:
        self.buf = bytearray(CDR_LE_HEADER)

    def _align(self, n: int) -> None:
        pad = (-(len(self.buf) - 4)) % n
        if pad:
            self.buf += b"\x00" * pad

    def prim(self, fmt: str, value) -> None:
        size = struct.calcsize(fmt)
        self._align(size)
        self.buf += struct.pack("<" + fmt, value)

    def u8(self, v: int) -> None:
        self.buf.append(int(v) & 0xFF)

    def u32(self, v: int) -> None:
        self.prim("I", int(v))

    def i32(self, v: int) -> None:
        self.prim("i", int(v))

    def f64s(self, values: Iterable[float]) -> None:
        vals = [float(v) for v in values]
        self._align(8)
        self.buf += struct.pack(f"<{len(vals)}d", *vals)

    def string(self, s: str) -> None:
        raw = str(s).encode("utf-8")
        self.u32(len(raw) + 1)
        self.buf += raw + b"\x00"

    def octets(self, data: bytes | bytearray | memoryview) -> None:
        """uint8[] sequence: count + raw bytes."""
        self.u32(len(data))
        self.buf += data

    def stamp(self, t: float) -> None:
        sec, nsec = stamp_of(t)
        self.i32(sec)
        self.u32(nsec)

    def header(self, t: float, frame_id: str) -> None:
        self.stamp(t)
        self.string(frame_id)

    def bytes(self) -> bytes:
        return bytes(self.buf)


def stamp_of(t: float) -> tuple[int, int]:
    """Seconds (float) -> builtin_interfaces/Time (sec int32, nanosec uint32 in [0, 1e9))."""
    t = float(t)
    if not math.isfinite(t):
        raise ValueError(f"time stamp {t!r} is not finite")
    ns = round(t * 1e9)
    sec, nsec = divmod(ns, 1_000_000_000)
    if not -2**31 <= sec < 2**31:
        raise ValueError(f"time stamp {t} s does not fit builtin_interfaces/Time (int32 seconds)")
    return sec, nsec


# --------------------------------------------------------------------------- messages

def wrench_stamped(t: float, frame_id: str, force_n: Sequence[float], torque_nm: Sequence[float]) -> bytes:
    """geometry_msgs/WrenchStamped: force in N, torque in N·m."""
    w = _Writer()
    w.header(t, frame_id)
    w.f64s(list(force_n)[:3] + list(torque_nm)[:3])
    return w.bytes()


def image_32fc1(t: float, frame_id: str, image: np.ndarray) -> bytes:
    """sensor_msgs/Image, encoding 32FC1, little endian, rows packed (step = 4·width)."""
    a = np.ascontiguousarray(image, dtype="<f4")
    if a.ndim != 2:
        raise ValueError(f"image: expected a 2-D array, got shape {a.shape}")
    h, wd = a.shape
    w = _Writer()
    w.header(t, frame_id)
    w.u32(h)
    w.u32(wd)
    w.string("32FC1")
    w.u8(0)                      # is_bigendian
    w.u32(4 * wd)                # step
    w.octets(memoryview(a).cast("B"))
    return w.bytes()


def point_cloud2(t: float, frame_id: str, points: np.ndarray) -> bytes:
    """sensor_msgs/PointCloud2 from a structured array (one record per point, unorganized: height 1).

    Field names, offsets and datatypes come from the array's dtype (little-endian int/uint/float
    fields only); `is_dense` is true when no float field holds NaN/inf."""
    pts = np.ascontiguousarray(points)
    if pts.dtype.names is None or pts.ndim != 1:
        raise ValueError("point_cloud2: expected a 1-D structured array")
    w = _Writer()
    w.header(t, frame_id)
    w.u32(1)                     # height
    w.u32(len(pts))              # width
    names = pts.dtype.names
    w.u32(len(names))
    dense = True
    for name in names:
        dt, offset = pts.dtype.fields[name][:2]
        base = dt.base.newbyteorder("<") if dt.base.byteorder == ">" else dt.base
        if base not in POINTFIELD_TYPES:
            raise ValueError(f"point_cloud2: field {name!r} has dtype {dt}, not a PointField type")
        w.string(name)
        w.u32(offset)
        w.u8(POINTFIELD_TYPES[base])
        w.u32(int(np.prod(dt.shape)) if dt.shape else 1)
        if base.kind == "f" and len(pts) and not np.isfinite(pts[name]).all():
            dense = False
    w.u8(0)                      # is_bigendian
    w.u32(pts.dtype.itemsize)    # point_step
    w.u32(pts.dtype.itemsize * len(pts))   # row_step
    w.octets(pts.tobytes())
    w.u8(1 if dense else 0)      # is_dense
    return w.bytes()


@dataclass(frozen=True)
class DiagnosticStatus:
    level: int                                 # DIAG_OK / DIAG_WARN / DIAG_ERROR / DIAG_STALE
    name: str
    message: str
    hardware_id: str
    values: tuple[tuple[str, str], ...] = ()   # diagnostic_msgs/KeyValue pairs


def diagnostic_array(t: float, statuses: Sequence[DiagnosticStatus], frame_id: str = "") -> bytes:
    """diagnostic_msgs/DiagnosticArray."""
    w = _Writer()
    w.header(t, frame_id)
    w.u32(len(statuses))
    for s in statuses:
        w.u8(s.level)
        w.string(s.name)
        w.string(s.message)
        w.string(s.hardware_id)
        w.u32(len(s.values))
        for k, v in s.values:
            w.string(k)
            w.string(v)
    return w.bytes()


@dataclass(frozen=True)
class Transform:
    """geometry_msgs/TransformStamped: `child` expressed in `parent`; translation m, rotation (x,y,z,w)."""
    t: float
    parent: str
    child: str
    translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)


def tf_message(transforms: Sequence[Transform]) -> bytes:
    """tf2_msgs/TFMessage."""
    w = _Writer()
    w.u32(len(transforms))
    for tr in transforms:
        w.header(tr.t, tr.parent)
        w.string(tr.child)
        w.f64s(tuple(tr.translation_m) + tuple(tr.rotation_xyzw))
    return w.bytes()
