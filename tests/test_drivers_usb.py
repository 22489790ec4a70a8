"""USB discovery by serial: real error paths on this machine, mocked hardware for the lookup logic."""
import os

import pytest
import tensortouch.drivers.usb as dusb
from tensortouch.contracts.errors import DeviceNotFoundError
from tensortouch.drivers.camera import camera_from_uri


def libusb_available():
    import usb.backend.libusb1

    return usb.backend.libusb1.get_backend() is not None


@pytest.mark.skipif(libusb_available(), reason="libusb is installed here; the missing-libusb path cannot be real")
def test_missing_libusb_is_a_clear_error():
    with pytest.raises(DeviceNotFoundError, match="libusb") as err:
        dusb.find_by_serial("TT0042")
    assert err.value.__cause__ is None and err.value.__suppress_context__  # no library traceback
    with pytest.raises(DeviceNotFoundError, match="libusb"):
        camera_from_uri("usb:TT0042").connect()


@pytest.mark.skipif(not libusb_available(), reason="needs libusb-1.0 to enumerate the real bus")
def test_unknown_serial_on_real_bus_is_a_clear_error():
    with pytest.raises(DeviceNotFoundError, match="no USB device with serial 'NO-SUCH-SERIAL-7f3a'"):
        dusb.find_by_serial("NO-SUCH-SERIAL-7f3a")


def test_empty_serial_is_rejected():
    with pytest.raises(DeviceNotFoundError, match="empty"):
        dusb.find_by_serial("")


def test_no_backend_error_is_translated_mocked_hardware(monkeypatch):
    import usb.core

    def no_backend(**kwargs):
        raise usb.core.NoBackendError("No backend available")

    monkeypatch.setattr(usb.core, "find", no_backend)
    with pytest.raises(DeviceNotFoundError, match="libusb-1.0-0") as err:
        dusb.list_devices()
    assert err.value.__cause__ is None


class FakeDev:
    """Just what drivers.usb reads from a pyusb device."""

    def __init__(self, vid, pid, bus, address, serial=None, readable=True):
        self.idVendor, self.idProduct, self.bus, self.address = vid, pid, bus, address
        self._serial, self._readable = serial, readable

    @property
    def serial_number(self):
        if not self._readable:
            raise ValueError("The device has no langid (permission denied)")
        return self._serial


def fake_sysfs(root, port, bus, devnum, serial, nodes):
    """sysfs as Linux lays it out for a UVC camera with capture + metadata nodes."""
    dev = root / "devices" / "pci0000:00" / "usb1" / port
    iface = dev / f"{port}:1.0"
    (iface / "video4linux").mkdir(parents=True)
    for name, value in (("busnum", bus), ("devnum", devnum), ("serial", serial)):
        (dev / name).write_text(f"{value}\n")
    (root / "class" / "video4linux").mkdir(parents=True, exist_ok=True)
    (root / "bus" / "usb" / "devices").mkdir(parents=True, exist_ok=True)
    os.symlink(dev, root / "bus" / "usb" / "devices" / port)
    os.symlink(iface, root / "bus" / "usb" / "devices" / f"{port}:1.0")
    for name, index in nodes:
        node = iface / "video4linux" / name
        node.mkdir()
        (node / "index").write_text(f"{index}\n")
        os.symlink(iface, node / "device")
        os.symlink(node, root / "class" / "video4linux" / name)


def test_find_by_serial_with_sysfs_mocked_hardware(tmp_path, monkeypatch):
    sysfs = tmp_path / "sys"
    fake_sysfs(sysfs, "1-2", 1, 5, "TT0042", [("video7", 1), ("video6", 0)])
    devices = [(0x046D, 0x0825, 1, 3, FakeDev(0x046D, 0x0825, 1, 3, "WEBCAM1")),
               (0x2833, 0x0209, 1, 5, FakeDev(0x2833, 0x0209, 1, 5, readable=False)),
               (0x1D6B, 0x0002, 1, 1, FakeDev(0x1D6B, 0x0002, 1, 1, readable=False))]
    monkeypatch.setattr(dusb, "_pyusb_devices", lambda backend=None: iter(devices))

    found = dusb.find_by_serial("TT0042", sysfs_root=sysfs)  # serial from sysfs: no permission needed
    assert (found.vid_pid, found.bus, found.address, found.name) == ("2833:0209", 1, 5, "digit")
    assert found.video_node == "/dev/video6"  # the capture node (index 0), not the metadata one
    assert "2833:0209 (digit) serial=TT0042 bus 001 address 005 -> /dev/video6" == found.describe()

    webcam = dusb.find_by_serial("WEBCAM1", sysfs_root=sysfs)  # serial from the descriptor
    assert webcam.vid_pid == "046d:0825" and webcam.video_node is None
    assert [d.vid_pid for d in dusb.list_devices(only_known=True, sysfs_root=sysfs)] == ["2833:0209"]

    with pytest.raises(DeviceNotFoundError, match="'TT9999'.*WEBCAM1.*TT0042"):
        dusb.find_by_serial("TT9999", sysfs_root=sysfs)
    with pytest.raises(DeviceNotFoundError, match="no V4L2 capture node"):
        dusb.find_camera("WEBCAM1", sysfs_root=sysfs)
    # sysfs lists /dev/video6 but this machine has no such node (e.g. container without the device)
    with pytest.raises(DeviceNotFoundError, match="/dev/video6"):
        dusb.find_camera("TT0042", sysfs_root=sysfs)


def test_video_node_unknown_without_sysfs(tmp_path):
    assert dusb.video_node_for(1, 5, sysfs_root=tmp_path / "nothing") is None
