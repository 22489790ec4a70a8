"""Live camera through OpenCV: CAP_V4L2 + MJPG, settings read back, a reader thread.

A background thread calls `VideoCapture.read()` continuously and keeps only the newest frame, so
`read_latest()` never returns a frame that sat in a queue and `read()` returns the next one to
arrive. The thread notices a camera that stops delivering (no frame for `read_timeout_s`) or a
device node that disappears (unplugged) and records a CaptureError that the next read raises.
After such a fault the next read reopens the device when `auto_reconnect` is on (a USB serial is
looked up again, so a replugged camera that came back under another /dev/video number is found);
while it stays unplugged each read raises a CaptureError saying why reopening failed.
"""
from __future__ import annotations

import logging
import math
import os
import threading
import time

import cv2
import numpy as np

from ....contracts.errors import CaptureError, DeviceNotFoundError
from ..camera import Camera, Frame, to_rgb
from .config import V4L2_EXPOSURE_UNIT_S, OpenCVCameraConfig

log = logging.getLogger(__name__)

V4L2_AUTO_EXPOSURE_MANUAL = 1  # V4L2_EXPOSURE_MANUAL as OpenCV's CAP_V4L2 expects it
FAILED_READ_PAUSE_S = 0.005    # back-off between failed VideoCapture.read() calls in the thread


def _fourcc_str(value: float) -> str:
    code = int(value)
    return "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4)) if code > 0 else "?"


class OpenCVCamera(Camera):
    """A V4L2 (or any OpenCV) capture device. See module doc for threading and faults."""

    def __init__(self, config: OpenCVCameraConfig):
        super().__init__(config)
        self.config: OpenCVCameraConfig = config
        self._cap: cv2.VideoCapture | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._cond = threading.Condition()
        self._latest: tuple[np.ndarray, float, int] | None = None  # (BGR image, t, index)
        self._last_returned = -1
        self._error: CaptureError | None = None
        self._device: int | str | None = None
        self._actual: dict = {}
        self._wanted = False  # connect() called and not disconnect()ed: recover from faults
        self._count = 0       # frames captured since construction (Frame.index keeps rising across reconnects)

    # -- description -----------------------------------------------------------------------
    @property
    def name(self) -> str:
        if self._device is not None:
            return str(self._device)
        c = self.config
        return f"usb:{c.serial}" if c.device is None else str(c.device)

    def info(self) -> dict:
        return {"source": self.name, "api": self.config.api, **self._actual}

    @property
    def is_connected(self) -> bool:
        return self._cap is not None

    # -- lifecycle -------------------------------------------------------------------------
    def _resolve_device(self) -> int | str:
        c = self.config
        if c.device is None:
            from ...usb import find_camera

            return find_camera(c.serial)
        device = c.device
        if isinstance(device, str) and device.isdigit():
            device = int(device)
        if c.api == "v4l2":
            path = f"/dev/video{device}" if isinstance(device, int) else device
            if not os.path.exists(path):
                raise DeviceNotFoundError(f"{path}: no such video device (camera unplugged? "
                                          "list cameras with: ls /dev/video*)")
        elif isinstance(device, str) and not os.path.exists(device) and "://" not in device:
            raise DeviceNotFoundError(f"{device}: no such device or file")
        return device

    def connect(self) -> None:
        if self.is_connected:
            return
        self._wanted = True
        self._open(self.config.connect_timeout_s)

    def disconnect(self) -> None:
        self._wanted = False
        self._close()

    def _open(self, first_frame_timeout_s: float) -> None:
        c = self.config
        self._device = self._resolve_device()
        api = cv2.CAP_V4L2 if c.api == "v4l2" else cv2.CAP_ANY
        cap = cv2.VideoCapture(self._device, api)
        if not cap.isOpened():
            cap.release()
            raise CaptureError(f"{self._device}: OpenCV could not open the camera (in use by another "
                               "program? no permission: add the user to the 'video' group)")
        self._cap = cap
        self._apply_settings()
        self._stop.clear()
        self._error, self._latest = None, None
        self._thread = threading.Thread(target=self._reader, name=f"camera-{self._device}", daemon=True)
        self._thread.start()
        with self._cond:
            self._cond.wait_for(lambda: self._latest is not None or self._error is not None,
                                timeout=first_frame_timeout_s)
            error, ok = self._error, self._latest is not None
        if not ok:
            self._close()
            raise error or CaptureError(f"{self._device}: opened, but no frame arrived within "
                                        f"{first_frame_timeout_s} s (wrong format? try fourcc=None)")
        log.info("camera %s connected: %s", self._device, self._actual)

    def _close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def _recover(self) -> None:
        """After a fault: reopen the device (auto_reconnect) or raise the fault."""
        cause = self._error or CaptureError(f"{self.name}: camera is closed after an earlier fault")
        if not self.config.auto_reconnect:
            raise cause
        self._close()
        try:
            self._open(self.config.read_timeout_s)
        except CaptureError as exc:
            raise CaptureError(f"{cause} (reconnect failed: {exc})") from None
        log.warning("camera %s reconnected after: %s", self._device, cause)

    def _require_connected(self) -> None:
        if not self._wanted:
            raise CaptureError(f"{self.name}: not connected (call connect() or use 'with camera:')")
        if self._cap is None or (self._error is not None and not self._has_fresh()):
            self._recover()

    def _has_fresh(self) -> bool:
        return self._latest is not None and self._latest[2] > self._last_returned

    # -- settings --------------------------------------------------------------------------
    def _apply_settings(self) -> None:
        c, cap = self.config, self._cap
        requested = {}
        if c.fourcc is not None:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*c.fourcc))
            requested["fourcc"] = c.fourcc
        if c.width is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, c.width)
            requested["width"] = c.width
        if c.height is not None:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, c.height)
            requested["height"] = c.height
        if c.fps is not None:
            cap.set(cv2.CAP_PROP_FPS, c.fps)
            requested["fps"] = c.fps
        if c.exposure_s is not None:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_AUTO_EXPOSURE_MANUAL)
            cap.set(cv2.CAP_PROP_EXPOSURE, c.exposure_s / V4L2_EXPOSURE_UNIT_S)
            requested["exposure_s"] = c.exposure_s
        exposure = cap.get(cv2.CAP_PROP_EXPOSURE)
        self._actual = {
            "fourcc": _fourcc_str(cap.get(cv2.CAP_PROP_FOURCC)),
            "width": int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            "height": int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            "fps": float(cap.get(cv2.CAP_PROP_FPS)),
            "exposure_s": float(exposure) * V4L2_EXPOSURE_UNIT_S if exposure > 0 else None,
        }
        for key, want in requested.items():
            got = self._actual[key]
            same = (got == want) if isinstance(want, str) else (
                got is not None and math.isclose(float(got), float(want), rel_tol=0.02))
            if not same:
                log.warning("camera %s refused %s=%s, delivers %s (continuing with the device's value)",
                            self._device, key, want, got)

    # -- reader thread ---------------------------------------------------------------------
    def _fail(self, message: str) -> None:
        with self._cond:
            self._error = CaptureError(message)
            self._cond.notify_all()
        log.error("%s", message)

    def _reader(self) -> None:
        cap, timeout = self._cap, self.config.read_timeout_s
        node = self._device if isinstance(self._device, str) else (
            f"/dev/video{self._device}" if self.config.api == "v4l2" else None)
        if node is not None and not os.path.exists(node):
            node = None  # not a filesystem path (e.g. a URL): cannot watch for it to disappear
        failing_since = None
        while not self._stop.is_set():
            try:
                ok, image = cap.read()
            except cv2.error as exc:
                ok, image = False, None
                log.debug("%s: read raised %s", self._device, exc)
            now = time.monotonic()
            if not ok or image is None:
                if node is not None and not os.path.exists(node):
                    self._fail(f"{node}: camera disappeared (unplugged?)")
                    return
                failing_since = failing_since or now
                if now - failing_since > timeout:
                    self._fail(f"{self._device}: camera stopped delivering frames "
                               f"(none for {timeout:.2f} s)")
                    return
                time.sleep(FAILED_READ_PAUSE_S)
                continue
            failing_since = None
            with self._cond:
                self._latest = (image, now, self._count)
                self._count += 1
                self._cond.notify_all()

    # -- frames ----------------------------------------------------------------------------
    def read(self, timeout_s: float | None = None) -> Frame:
        self._require_connected()
        timeout = self.config.read_timeout_s if timeout_s is None else timeout_s
        with self._cond:
            self._cond.wait_for(lambda: self._has_fresh() or self._error is not None, timeout=timeout)
            if self._has_fresh():
                latest = self._latest
            elif self._error is not None:
                raise self._error
            else:
                raise CaptureError(f"{self._device}: no new frame within {timeout:.2f} s "
                                   "(camera stopped delivering frames?)")
        image, t, index = latest
        self._last_returned = index
        return Frame(to_rgb(image, f"{self._device} frame {index}"), t, index)

    def read_latest(self) -> Frame:
        self._require_connected()
        with self._cond:
            if self._latest is None:
                self._cond.wait_for(lambda: self._latest is not None or self._error is not None,
                                    timeout=self.config.read_timeout_s)
            if self._error is not None and (self._latest is None or self._latest[2] <= self._last_returned):
                raise self._error
            if self._latest is None:
                raise CaptureError(f"{self._device}: no frame yet after {self.config.read_timeout_s:.2f} s")
            latest = self._latest
        image, t, index = latest
        self._last_returned = index
        return Frame(to_rgb(image, f"{self._device} frame {index}"), t, index)
