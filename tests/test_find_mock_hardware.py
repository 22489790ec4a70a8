"""`tensortouch find` with mocked hardware: no camera is attached to this machine, so the USB bus is
a fake pyusb backend (usb.backend.IBackend: device descriptors and string descriptors over control
transfers, read by pyusb's own code) and sysfs is a fake tree in tmp. The VIDIOC_QUERYCAP ioctl is
replaced by a fake at the same edge in one test; its struct decoding is tested on packed bytes."""
import argparse
import array
import json
import struct
from types import SimpleNamespace

import pytest
import tensortouch.drivers.usb as dusb
import usb.backend
from tensortouch.drivers import v4l2
from tensortouch.runtime.shells import commands

from tests.test_drivers_usb import fake_sysfs


class FakeUsbDevice:
    def __init__(self, vid, pid, bus, address, strings):
        self.desc = SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0xEF, bDeviceSubClass=2, bDeviceProtocol=1,
            bMaxPacketSize0=64, idVendor=vid, idProduct=pid, bcdDevice=0x0100, iManufacturer=1, iProduct=2,
            iSerialNumber=3 if 3 in strings else 0, bNumConfigurations=1, address=address, bus=bus,
            port_number=1, port_numbers=(1,), speed=3)
        self.strings = strings


class FakeBackend(usb.backend.IBackend):
    """Enumerates the given devices and answers GET_DESCRIPTOR(string) control transfers."""

    def __init__(self, devices):
        self.devices = devices
        self.transfers = 0

    def enumerate_devices(self):
        return iter(self.devices)

    def get_device_descriptor(self, dev):
        return dev.desc

    def open_device(self, dev):
        return dev

    def close_device(self, handle):
        pass

    def ctrl_transfer(self, handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        assert bRequest == 0x06 and wValue >> 8 == 3, "only string descriptors are read"
        self.transfers += 1
        index = wValue & 0xFF
        if index == 0:
            payload = bytes([4, 3, 0x09, 0x04])          # LANGID en-US
        else:
            text = handle.strings[index].encode("utf-16-le")
            payload = bytes([2 + len(text), 3]) + text
        n = min(len(data), len(payload))
        data[:n] = array.array("B", payload[:n])
        return n


def bus(tmp_path):
    """A DIGIT-like camera with sysfs serial, a second camera whose serial only the descriptor gives,
    and a keyboard (no video node)."""
    sysfs = tmp_path / "sys"
    fake_sysfs(sysfs, "1-2", 1, 5, "D20001", [("video2", 0), ("video3", 1)])
    fake_sysfs(sysfs, "1-3", 1, 6, "", [("video4", 0), ("video5", 1)])
    (sysfs / "devices" / "pci0000:00" / "usb1" / "1-3" / "serial").unlink()   # serial not in sysfs
    (sysfs / "devices" / "pci0000:00" / "usb1" / "1-2" / "product").write_text("DIGIT\n")
    devices = [FakeUsbDevice(0x2833, 0x0209, 1, 5, {1: "Meta", 2: "DIGIT", 3: "D20001"}),
               FakeUsbDevice(0x0C45, 0x6366, 1, 6, {1: "Sonix", 2: "USB 2.0 Camera", 3: "TT0042"}),
               FakeUsbDevice(0x046D, 0xC31C, 1, 7, {1: "Logitech", 2: "Keyboard", 3: "KB1"})]
    dev_root = tmp_path / "dev"
    dev_root.mkdir()
    return FakeBackend(devices), sysfs, dev_root


def parse(argv):
    parser = argparse.ArgumentParser()
    commands.register(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


def test_find_lists_cameras_with_serial_names_and_capture_node_mocked_hardware(tmp_path, capsys):
    backend, sysfs, dev_root = bus(tmp_path)
    (dev_root / "video4").touch()
    (dev_root / "tensortouch-TT0042").symlink_to(dev_root / "video4")
    cams = dusb.list_cameras(backend=backend, sysfs_root=sysfs, dev_root=dev_root)
    assert [c.device.serial for c in cams] == ["D20001", "TT0042"]     # the keyboard has no video node
    digit, sonix = cams
    assert digit.device.name == "digit" and digit.product == "DIGIT" and digit.manufacturer == "Meta"
    assert [(n.path, n.kind) for n in digit.nodes] == [(str(dev_root / "video2"), "capture?"),
                                                      (str(dev_root / "video3"), "metadata?")]
    assert digit.capture_node == str(dev_root / "video2") and digit.stable_name is None
    # serial, manufacturer and product of the second camera came over (fake) control transfers
    assert sonix.manufacturer == "Sonix" and sonix.product == "USB 2.0 Camera" and backend.transfers >= 3
    assert sonix.stable_name == str(dev_root / "tensortouch-TT0042")
    assert len(dusb.list_cameras(backend=backend, sysfs_root=sysfs, dev_root=dev_root, include_all=True)) == 3
    # the CLI: text and JSON
    assert commands.cmd_find(parse(["find"]), backend=backend, sysfs_root=sysfs, dev_root=dev_root) == 0
    text = capsys.readouterr().out
    assert "D20001  2833:0209 (digit)  Meta DIGIT" in text
    assert f"{dev_root / 'video2'}  capture?  <- capture node" in text
    assert "tensortouch run --source usb:TT0042 --sensor TT0042" in text and "tensortouch-TT0042" in text
    assert commands.cmd_find(parse(["find", "--json"]), backend=backend, sysfs_root=sysfs, dev_root=dev_root) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rows[1]["serial"] == "TT0042" and rows[1]["vendor_id"] == "0c45" and rows[1]["source"] == "usb:TT0042"
    # usb:SERIAL lookup still finds both (sysfs serial and descriptor serial)
    assert dusb.find_by_serial("TT0042", backend=backend, sysfs_root=sysfs).video_node == "/dev/video4"


def test_find_prefers_the_querycap_answer_over_sysfs_index_mocked_ioctl(tmp_path, capsys):
    backend, sysfs, dev_root = bus(tmp_path)
    # a camera whose metadata node got the lower number: only the ioctl can tell
    caps = {"video2": v4l2.CAP_META_CAPTURE, "video3": v4l2.CAP_VIDEO_CAPTURE | v4l2.CAP_STREAMING}

    def fake_querycap(path):
        name = path.rsplit("/", 1)[-1]
        if name not in caps:
            return None
        raw = struct.pack("<16s32s32sIII12x", b"uvcvideo", b"DIGIT: DIGIT", b"usb-0000:00:14.0-2", 0x060800,
                          caps[name] | v4l2.CAP_DEVICE_CAPS | v4l2.CAP_VIDEO_CAPTURE, caps[name])
        return v4l2.decode_caps(raw)

    cams = dusb.list_cameras(backend=backend, sysfs_root=sysfs, dev_root=dev_root, query=fake_querycap)
    digit = cams[0]
    assert [n.kind for n in digit.nodes] == ["metadata", "capture"]
    assert digit.capture_node == str(dev_root / "video3") and digit.nodes[1].card == "DIGIT: DIGIT"


def test_querycap_request_code_and_decoding():
    assert v4l2.VIDIOC_QUERYCAP == 0x80685600          # _IOR('V', 0, struct v4l2_capability), 104 bytes
    raw = struct.pack("<16s32s32sIII12x", b"uvcvideo", b"Cam", b"usb-1", 1, 0x84A00001, 0x04200001)
    caps = v4l2.decode_caps(raw)
    assert (caps.driver, caps.card, caps.bus_info, caps.kind, caps.is_capture) == ("uvcvideo", "Cam", "usb-1", "capture", True)
    assert v4l2.query_caps("/nonexistent/video9") is None


def test_find_says_when_nothing_is_attached_mocked_hardware(tmp_path, capsys):
    backend = FakeBackend([])
    assert commands.cmd_find(parse(["find"]), backend=backend, sysfs_root=tmp_path, dev_root=tmp_path) == 1
    assert "no USB cameras found" in capsys.readouterr().out


@pytest.mark.skipif(not __import__("pathlib").Path("/dev/video0").exists(), reason="no /dev/video0 on this machine")
@pytest.mark.hardware
def test_querycap_on_a_real_node():
    assert v4l2.query_caps("/dev/video0") is not None


def test_find_json_exits_1_when_nothing_is_attached_like_the_text_form_mocked_hardware(tmp_path, capsys):
    backend = FakeBackend([])
    assert commands.cmd_find(parse(["find", "--json"]), backend=backend, sysfs_root=tmp_path, dev_root=tmp_path) == 1
    assert capsys.readouterr().out == ""
