"""Find USB devices (cameras, gauges) by serial number with pyusb; map a camera to its /dev/video node.

pyusb enumerates the bus (it needs libusb-1.0 from the OS: Debian/Ubuntu `libusb-1.0-0`). Serial
numbers and the V4L2 node are read from sysfs when it is there (no device permissions needed);
otherwise the serial comes from the USB string descriptor (may need udev permissions).

Every failure is a `DeviceNotFoundError` with a message saying what to do, never a library traceback:
libusb missing, pyusb missing, or no attached device with that serial.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

from ..contracts.errors import DeviceNotFoundError

log = logging.getLogger(__name__)

KNOWN_DEVICES: dict[str, tuple[int, int]] = {
    # name: (vendor id, product id). Listing a device here only labels it in `list_devices()`;
    # lookup by serial searches every USB device, so any UVC camera works without an entry.
    "digit": (0x2833, 0x0209),  # Meta DIGIT tactile sensor (UVC)
}

SYSFS_ROOT = Path("/sys")
LIBUSB_HINT = ("pyusb needs the libusb-1.0 library to list USB devices; install it "
               "(Debian/Ubuntu: sudo apt install libusb-1.0-0; macOS: brew install libusb)")


@dataclass(frozen=True)
class UsbDevice:
    """One attached USB device."""

    vid: int
    pid: int
    bus: int
    address: int
    serial: str | None = None
    name: str | None = None          # label from KNOWN_DEVICES, if the VID:PID is listed there
    video_node: str | None = None    # /dev/videoN of its capture interface, if it is a camera

    @property
    def vid_pid(self) -> str:
        return f"{self.vid:04x}:{self.pid:04x}"

    def describe(self) -> str:
        label = f" ({self.name})" if self.name else ""
        node = f" -> {self.video_node}" if self.video_node else ""
        return (f"{self.vid_pid}{label} serial={self.serial or '?'} "
                f"bus {self.bus:03d} address {self.address:03d}{node}")


# -- sysfs --------------------------------------------------------------------------------------
def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except OSError:
        return None


def _sysfs_usb_dir(bus: int, address: int, sysfs_root: Path) -> Path | None:
    """The /sys/bus/usb/devices/<port> directory of the device at bus/address, if sysfs has it."""
    base = sysfs_root / "bus" / "usb" / "devices"
    if not base.is_dir():
        return None
    for entry in base.iterdir():
        if ":" in entry.name:  # interfaces (1-2:1.0), not devices
            continue
        if _read(entry / "busnum") == str(bus) and _read(entry / "devnum") == str(address):
            return entry
    return None


def video_node_for(bus: int, address: int, sysfs_root: Path = SYSFS_ROOT) -> str | None:
    """The /dev/videoN capture node of the USB device at bus/address, via sysfs; None if unknown.

    A UVC camera usually registers two nodes (capture + metadata); the capture one has
    `index` 0 in sysfs. Among several candidates the lowest-numbered capture node wins.
    """
    v4l = sysfs_root / "class" / "video4linux"
    if not v4l.is_dir():
        return None
    candidates = []
    for node in v4l.iterdir():
        try:
            iface = (node / "device").resolve()
        except OSError:
            continue
        usb_dir = iface.parent  # .../1-2/1-2:1.0 -> .../1-2
        if _read(usb_dir / "busnum") != str(bus) or _read(usb_dir / "devnum") != str(address):
            continue
        index = _read(node / "index")
        number = int("".join(c for c in node.name if c.isdigit()) or 0)
        candidates.append((0 if index in (None, "0") else 1, number, node.name))
    if not candidates:
        return None
    return f"/dev/{min(candidates)[2]}"


# -- pyusb ---------------------------------------------------------------------------------------
def _pyusb_devices(backend=None) -> Iterator[tuple[int, int, int, int, object]]:
    """(vid, pid, bus, address, pyusb device) for every attached device; raises DeviceNotFoundError."""
    try:
        import usb.core
    except ImportError as exc:  # pragma: no cover - pyusb is a runtime dependency
        raise DeviceNotFoundError(f"pyusb is not installed ({exc}); pip install pyusb") from None
    try:
        devices = list(usb.core.find(find_all=True, backend=backend))
    except usb.core.NoBackendError:
        raise DeviceNotFoundError(f"cannot list USB devices: {LIBUSB_HINT}") from None
    except usb.core.USBError as exc:
        raise DeviceNotFoundError(f"cannot list USB devices: {exc} (permissions? try udev rules)") from None
    for dev in devices:
        yield int(dev.idVendor), int(dev.idProduct), int(dev.bus or 0), int(dev.address or 0), dev


def _descriptor_serial(dev) -> str | None:
    """Serial from the USB string descriptor; None when it cannot be read (often permissions)."""
    try:
        return dev.serial_number
    except Exception as exc:  # USBError, ValueError ("no langid"), NotImplementedError
        log.debug("cannot read serial of %04x:%04x: %s", dev.idVendor, dev.idProduct, exc)
        return None


def list_devices(known: dict[str, tuple[int, int]] | None = None, only_known: bool = False,
                 backend=None, sysfs_root: Path = SYSFS_ROOT) -> list[UsbDevice]:
    """All attached USB devices (or only those whose VID:PID is in `known`), with serial and node."""
    known = KNOWN_DEVICES if known is None else known
    labels = {ids: name for name, ids in known.items()}
    found = []
    for vid, pid, bus, address, dev in _pyusb_devices(backend):
        name = labels.get((vid, pid))
        if only_known and name is None:
            continue
        usb_dir = _sysfs_usb_dir(bus, address, sysfs_root)
        serial = _read(usb_dir / "serial") if usb_dir is not None else None
        if serial is None:
            serial = _descriptor_serial(dev)
        found.append(UsbDevice(vid, pid, bus, address, serial, name,
                               video_node_for(bus, address, sysfs_root)))
    return found


def find_by_serial(serial: str, devices: Iterable[UsbDevice] | None = None, **kwargs) -> UsbDevice:
    """The attached device with this serial number; DeviceNotFoundError listing what *is* attached."""
    if not serial:
        raise DeviceNotFoundError("USB serial number is empty")
    devices = list(list_devices(**kwargs) if devices is None else devices)
    for device in devices:
        if device.serial == serial:
            log.info("USB serial %s: %s", serial, device.describe())
            return device
    seen = [d.describe() for d in devices if d.serial] or ["none with a readable serial"]
    raise DeviceNotFoundError(f"no USB device with serial {serial!r} is attached "
                              f"(attached: {'; '.join(seen)})")


def find_camera(serial: str, **kwargs) -> str:
    """The /dev/videoN node of the camera with this USB serial; DeviceNotFoundError otherwise."""
    device = find_by_serial(serial, **kwargs)
    if device.video_node is None:
        raise DeviceNotFoundError(f"USB device {device.describe()} has no V4L2 capture node "
                                  "(not a UVC camera, or /sys/class/video4linux is not available)")
    if not os.path.exists(device.video_node):
        raise DeviceNotFoundError(f"{device.video_node}: listed in sysfs for serial {serial!r} "
                                  "but missing in /dev (container without the device mapped?)")
    return device.video_node


# -- cameras: every /dev/video node of a USB device, and which one captures ----------------------
DEV_ROOT = Path("/dev")
STABLE_PREFIX = "tensortouch-"   # drivers/udev/99-tensortouch.rules: /dev/tensortouch-<serial>


@dataclass(frozen=True)
class VideoNode:
    """One /dev/videoN of a camera. `kind`: capture | metadata | other (VIDIOC_QUERYCAP), or
    capture? / metadata? when only sysfs's `index` could be read (index 0 is the capture node)."""

    path: str
    kind: str
    card: str | None = None


@dataclass(frozen=True)
class CameraInfo:
    device: UsbDevice
    manufacturer: str | None
    product: str | None
    nodes: tuple[VideoNode, ...]
    stable_name: str | None          # /dev/tensortouch-<serial> when the udev rule made it

    @property
    def capture_node(self) -> str | None:
        for wanted in ("capture", "capture?"):
            for n in self.nodes:
                if n.kind == wanted:
                    return n.path
        return None

    def to_dict(self) -> dict:
        d = self.device
        return {"serial": d.serial, "vendor_id": f"{d.vid:04x}", "product_id": f"{d.pid:04x}",
                "manufacturer": self.manufacturer, "product": self.product, "bus": d.bus, "address": d.address,
                "nodes": [{"path": n.path, "kind": n.kind, "card": n.card} for n in self.nodes],
                "capture_node": self.capture_node, "stable_name": self.stable_name,
                "source": f"usb:{d.serial}" if d.serial else self.capture_node}


def video_nodes_for(bus: int, address: int, sysfs_root: Path = SYSFS_ROOT, dev_root: Path = DEV_ROOT,
                    query=None) -> list[VideoNode]:
    """Every V4L2 node of the USB device at bus/address, in node-number order, each with its kind
    (`query(path)` → drivers.v4l2.V4l2Caps or None; default: the VIDIOC_QUERYCAP ioctl)."""
    if query is None:
        from .v4l2 import query_caps as query
    v4l = sysfs_root / "class" / "video4linux"
    if not v4l.is_dir():
        return []
    found = []
    for node in v4l.iterdir():
        try:
            usb_dir = (node / "device").resolve().parent
        except OSError:
            continue
        if _read(usb_dir / "busnum") != str(bus) or _read(usb_dir / "devnum") != str(address):
            continue
        path = str(dev_root / node.name)
        caps = query(path)
        if caps is not None:
            kind, card = caps.kind, caps.card
        else:
            index = _read(node / "index")
            kind = "capture?" if index in (None, "0") else "metadata?"
            card = _read(node / "name")
        number = int("".join(c for c in node.name if c.isdigit()) or 0)
        found.append((number, VideoNode(path, kind, card)))
    return [n for _, n in sorted(found)]


def _descriptor_text(dev, attr: str) -> str | None:
    try:
        return getattr(dev, attr)
    except Exception as exc:  # noqa: BLE001 - USBError, ValueError ("no langid"), NotImplementedError
        log.debug("cannot read %s of %04x:%04x: %s", attr, dev.idVendor, dev.idProduct, exc)
        return None


def list_cameras(backend=None, sysfs_root: Path = SYSFS_ROOT, dev_root: Path = DEV_ROOT, query=None,
                 include_all: bool = False) -> list[CameraInfo]:
    """USB devices with at least one V4L2 node (every USB device with `include_all`): serial,
    vendor/product ids and names, their /dev/video nodes and which one captures."""
    out = []
    for vid, pid, bus, address, dev in _pyusb_devices(backend):
        nodes = video_nodes_for(bus, address, sysfs_root, dev_root, query)
        if not nodes and not include_all:
            continue
        usb_dir = _sysfs_usb_dir(bus, address, sysfs_root)
        serial = _read(usb_dir / "serial") if usb_dir is not None else None
        manufacturer = _read(usb_dir / "manufacturer") if usb_dir is not None else None
        product = _read(usb_dir / "product") if usb_dir is not None else None
        serial = serial or _descriptor_serial(dev)
        manufacturer = manufacturer or _descriptor_text(dev, "manufacturer")
        product = product or _descriptor_text(dev, "product")
        labels = {ids: name for name, ids in KNOWN_DEVICES.items()}
        capture = next((n.path for n in nodes if n.kind.startswith("capture")), None)
        stable = None
        if serial:
            link = dev_root / f"{STABLE_PREFIX}{serial}"
            if link.exists() and (capture is None or os.path.realpath(link) == os.path.realpath(capture)):
                stable = str(link)
        device = UsbDevice(vid, pid, bus, address, serial, labels.get((vid, pid)), capture)
        out.append(CameraInfo(device, manufacturer, product, tuple(nodes), stable))
    return out
