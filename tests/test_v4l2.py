"""V4L2 capabilities (drivers/v4l2.py): the ioctl number and `struct v4l2_capability` decoded by hand."""
import struct

import pytest
from tensortouch.drivers.v4l2 import (
    CAP_DEVICE_CAPS,
    CAP_META_CAPTURE,
    CAP_STREAMING,
    CAP_VIDEO_CAPTURE,
    VIDIOC_QUERYCAP,
    decode_caps,
    query_caps,
)


def _caps(caps, dcaps, driver=b"uvcvideo", card=b"TT Dome Cam", bus=b"usb-0000:00:14.0-2"):
    return struct.pack("<16s32s32sIII12x", driver, card, bus, 0x60800, caps, dcaps)


def test_querycap_is_the_number_in_videodev2_h():
    assert VIDIOC_QUERYCAP == 0x80685600            # _IOR('V', 0, struct v4l2_capability): 104 bytes


def test_a_uvc_camera_has_a_capture_node_and_a_metadata_node():
    device = CAP_VIDEO_CAPTURE | CAP_META_CAPTURE | CAP_STREAMING | CAP_DEVICE_CAPS
    video = decode_caps(_caps(device, CAP_VIDEO_CAPTURE | CAP_STREAMING))
    meta = decode_caps(_caps(device, CAP_META_CAPTURE | CAP_STREAMING))
    assert (video.driver, video.card, video.bus_info) == ("uvcvideo", "TT Dome Cam", "usb-0000:00:14.0-2")
    assert video.is_capture and video.kind == "capture"
    assert not meta.is_capture and meta.kind == "metadata"


def test_without_device_caps_the_device_capabilities_count():
    old = decode_caps(_caps(CAP_VIDEO_CAPTURE, 0))          # no CAP_DEVICE_CAPS: device_caps is unset
    assert old.node_caps == CAP_VIDEO_CAPTURE and old.kind == "capture"
    assert decode_caps(_caps(CAP_STREAMING, 0)).kind == "other"
    with pytest.raises(struct.error):
        decode_caps(b"\0" * 10)                             # shorter than the struct


def test_a_node_that_is_not_v4l2_or_missing_is_none(tmp_path):
    assert query_caps("/dev/null") is None                   # the ioctl fails: not a V4L2 device
    assert query_caps(str(tmp_path / "video9")) is None
