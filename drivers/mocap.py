"""Motion-capture pose stream (pyserial): indenter tip poses for a recording (docs/bringup.md).

Line protocol (one ASCII line per pose, from a mocap bridge on a serial port or a TCP socket):

    P <indenter> <x> <y> <z> <qw> <qx> <qy> <qz>\\n      e.g. b"P 0 1.5 -2.0 14.2 1 0 0 0\\n"

`<indenter>` is an integer id; x, y, z the tip position in the sensor frame (mm); q the unit
quaternion of the indenter → sensor rotation (docs/session.md, poses.csv). A line that does not
parse, or a quaternion far from unit length, is counted and skipped. Any pyserial URL works
(``/dev/ttyACM0``, ``socket://127.0.0.1:9000``, ``loop://``). Readings are stamped with
`time.monotonic()` on arrival, the clock the camera layer stamps live frames with.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

from ..contracts.errors import CaptureError, DeviceNotFoundError
from .serial_port import close_serial, open_serial

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MocapConfig:
    url: str                       # pyserial URL or device path
    baudrate: int = 115200
    max_garbage: int = 50          # consecutive unreadable lines → "not speaking the protocol"


@dataclass(frozen=True)
class Pose:
    t: float                       # time.monotonic() at arrival, s
    indenter: int
    xyz_mm: tuple[float, float, float]
    q_wxyz: tuple[float, float, float, float]


def format_pose(indenter: int, xyz, q) -> bytes:
    """One protocol line (used by bridges, emulators and tests)."""
    return (f"P {int(indenter)} " + " ".join(f"{float(v):.6g}" for v in (*xyz, *q)) + "\n").encode()


def parse_pose(line: bytes) -> tuple[int, tuple, tuple] | None:
    """(indenter, xyz, q) from one line, or None if it is not a valid pose line."""
    parts = line.strip().split()
    if len(parts) != 9 or parts[0] != b"P":
        return None
    try:
        ind = int(parts[1])
        vals = [float(p) for p in parts[2:]]
    except ValueError:
        return None
    q = vals[3:]
    norm = sum(v * v for v in q) ** 0.5
    if ind < 0 or not all(abs(v) < 1e9 for v in vals) or abs(norm - 1.0) > 0.01:
        return None
    return ind, tuple(vals[:3]), tuple(v / norm for v in q)


class PoseStream:
    """Background reader of a pose stream; `poses()` returns what arrived, `check()` re-raises a failure."""

    def __init__(self, config: MocapConfig, port=None):
        self.cfg = config
        self._port = port
        self._poses: list[Pose] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._error: Exception | None = None
        self._thread: threading.Thread | None = None
        self.garbage = 0

    def open(self) -> PoseStream:
        if self._port is None:
            self._port = open_serial(self.cfg.url, self.cfg.baudrate, "mocap stream",
                                     "check the --mocap argument (e.g. socket://127.0.0.1:9000)")
        return self

    def start(self) -> PoseStream:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"mocap:{self.cfg.url}", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        import serial

        buf = b""
        try:
            while not self._stop.is_set():
                try:
                    chunk = self._port.read(max(1, getattr(self._port, "in_waiting", 0) or 0))
                except (serial.SerialException, OSError) as exc:
                    raise DeviceNotFoundError(f"mocap stream {self.cfg.url}: disconnected ({exc})") from None
                now = time.monotonic()
                buf += chunk
                *lines, buf = buf.split(b"\n")
                for line in lines:
                    if not line.strip():
                        continue
                    pose = parse_pose(line)
                    if pose is None:
                        self.garbage += 1
                        if self.garbage >= self.cfg.max_garbage:
                            raise CaptureError(f"mocap stream {self.cfg.url}: {self.garbage} unreadable lines in a "
                                               f"row (expected 'P <indenter> x y z qw qx qy qz'); last {line[:40]!r}")
                        continue
                    self.garbage = 0
                    with self._lock:
                        self._poses.append(Pose(now, *pose))
        except Exception as exc:  # noqa: BLE001 - handed to the recording thread by check()
            self._error = exc

    def check(self) -> None:
        if self._error is not None:
            raise self._error

    def poses(self) -> list[Pose]:
        with self._lock:
            return list(self._poses)

    def close(self) -> None:
        close_serial(self._port, self._thread, self._stop, f"mocap stream {self.cfg.url}", log)
        self._thread = None

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()
