"""V4L2 device capabilities (VIDIOC_QUERYCAP) with the standard library: which /dev/video node captures.

A UVC camera registers two nodes on current kernels: one for video capture and one for metadata
(UVC payload headers). Only the capture node delivers frames. `query_caps(path)` opens the node
read-only, asks the driver with the VIDIOC_QUERYCAP ioctl and decodes `struct v4l2_capability`
(include/uapi/linux/videodev2.h); the per-node `device_caps` say what that node does.
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass

# struct v4l2_capability { u8 driver[16]; u8 card[32]; u8 bus_info[32]; u32 version;
#                          u32 capabilities; u32 device_caps; u32 reserved[3]; }  = 104 bytes
_CAP_STRUCT = struct.Struct("<16s32s32sIII12x")
_IOC_READ = 2
VIDIOC_QUERYCAP = (_IOC_READ << 30) | (_CAP_STRUCT.size << 16) | (ord("V") << 8) | 0   # _IOR('V', 0, ...)

CAP_VIDEO_CAPTURE = 0x00000001
CAP_VIDEO_CAPTURE_MPLANE = 0x00001000
CAP_META_CAPTURE = 0x00800000
CAP_STREAMING = 0x04000000
CAP_DEVICE_CAPS = 0x80000000


@dataclass(frozen=True)
class V4l2Caps:
    driver: str
    card: str
    bus_info: str
    capabilities: int          # the whole device
    device_caps: int           # this node

    @property
    def node_caps(self) -> int:
        return self.device_caps if self.capabilities & CAP_DEVICE_CAPS else self.capabilities

    @property
    def is_capture(self) -> bool:
        return bool(self.node_caps & (CAP_VIDEO_CAPTURE | CAP_VIDEO_CAPTURE_MPLANE))

    @property
    def kind(self) -> str:
        c = self.node_caps
        if c & (CAP_VIDEO_CAPTURE | CAP_VIDEO_CAPTURE_MPLANE):
            return "capture"
        if c & CAP_META_CAPTURE:
            return "metadata"
        return "other"


def decode_caps(buf: bytes) -> V4l2Caps:
    """`struct v4l2_capability` bytes → V4l2Caps."""
    driver, card, bus, _version, caps, dcaps = _CAP_STRUCT.unpack(bytes(buf[:_CAP_STRUCT.size]))

    def text(b: bytes) -> str:
        return b.split(b"\0", 1)[0].decode("utf-8", "replace")

    return V4l2Caps(text(driver), text(card), text(bus), caps, dcaps)


def query_caps(path: str) -> V4l2Caps | None:
    """VIDIOC_QUERYCAP on a /dev/video node; None when it cannot be opened or asked (permissions,
    not a V4L2 device, no Linux)."""
    try:
        import fcntl
    except ImportError:  # not Linux
        return None
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        buf = bytearray(_CAP_STRUCT.size)
        fcntl.ioctl(fd, VIDIOC_QUERYCAP, buf, True)
        return decode_caps(bytes(buf))
    except OSError:
        return None
    finally:
        os.close(fd)
