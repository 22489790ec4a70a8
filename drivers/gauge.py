"""Serial force gauge (pyserial): the reference force for field recalibration (docs/recalibration.md).

Two line protocols:

- ``tt`` — TensorTouch gauge line protocol (streaming, e.g. a load-cell amplifier on a microcontroller
  or the twin gauge): one ASCII line per reading, NMEA-style checksum

      F <newtons>*<XX>\\n        e.g.  b"F 2.3150*7D\\n"

  ``<newtons>`` is a decimal float (sign = direction along the gauge axis), ``XX`` two hex digits of
  the XOR of every byte before ``*``. Lines without a valid checksum are garbage and skipped.
- ``mark10`` — the request/reply format of Mark-10 Series 4/5 digital gauges (and several others):
  the host sends ``?`` + CR, the gauge answers ``<value> <unit>`` + CR LF (``4.285 N``, ``-18.78 lbF``);
  units N, kN, mN, lbF, ozF, kgF, gF are converted to N; ``*10``-style error codes are garbage.

Robustness: unparseable lines are counted and skipped; `timeout_s` without a valid reading raises
DeviceNotFoundError ("not responding"); an unplugged port (pyserial SerialException / OSError)
raises DeviceNotFoundError ("disconnected"); too many garbage lines in a row raise CaptureError
("not speaking protocol ..."). Any pyserial URL works (``/dev/ttyUSB0``, ``loop://``, ``socket://``).
"""
from __future__ import annotations

import logging
import re
import threading
import time
from collections import deque
from dataclasses import dataclass

from ..contracts.errors import CaptureError, DeviceNotFoundError
from .serial_port import close_serial, open_serial

log = logging.getLogger(__name__)

PROTOCOLS = ("tt", "mark10")
UNITS_TO_N = {"n": 1.0, "kn": 1000.0, "mn": 1e-3, "lbf": 4.4482216152605, "ozf": 0.27801385095378,
              "kgf": 9.80665, "gf": 9.80665e-3}
_TT_RE = re.compile(rb"^F ([-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\*([0-9A-Fa-f]{2})$")
_M10_RE = re.compile(rb"^([-+]?\d+(?:\.\d*)?)\s*([A-Za-z]+)?$")


def checksum(payload: bytes) -> int:
    c = 0
    for b in payload:
        c ^= b
    return c


def format_tt(force_n: float) -> bytes:
    """One `tt` protocol line for a reading in N (used by emulators and the twin gauge)."""
    body = f"F {force_n:.4f}".encode()
    return body + b"*%02X\n" % checksum(body)


def parse_tt(line: bytes) -> float | None:
    """Force in N from one `tt` line, or None if the line is garbage or its checksum is wrong."""
    m = _TT_RE.match(line.strip())
    if not m:
        return None
    body = line.strip().split(b"*")[0]
    if checksum(body) != int(m.group(2), 16):
        return None
    return float(m.group(1))


def parse_mark10(line: bytes) -> float | None:
    """Force in N from one `<value> <unit>` reply (unit optional = N), or None."""
    m = _M10_RE.match(line.strip())
    if not m:
        return None
    unit = (m.group(2) or b"N").decode().lower()
    if unit not in UNITS_TO_N:
        return None
    return float(m.group(1)) * UNITS_TO_N[unit]


class _Stopped(Exception):
    """close() interrupted a blocking read of the background reader."""


@dataclass(frozen=True)
class GaugeConfig:
    url: str                       # pyserial URL or device path
    protocol: str = "tt"
    baudrate: int = 115200         # Mark-10 gauges default to 9600: set it on the command line
    timeout_s: float = 2.0         # no valid reading for this long → "not responding"
    poll_s: float = 0.02           # mark10: request period
    max_garbage: int = 50          # consecutive garbage lines → "not speaking protocol"
    history: int = 20000           # readings kept by the background reader


@dataclass(frozen=True)
class GaugeReading:
    t: float        # time.monotonic() at arrival, s
    force_n: float


class ForceGauge:
    """A serial force gauge. `read()` blocks for the next reading; `start()` runs a background
    reader whose readings `window(t0, t1)` returns and whose failure `check()` re-raises."""

    def __init__(self, config: GaugeConfig, port=None):
        if config.protocol not in PROTOCOLS:
            raise ValueError(f"gauge protocol {config.protocol!r}, expected one of {PROTOCOLS}")
        self.cfg = config
        self._port = port
        self._parse = parse_tt if config.protocol == "tt" else parse_mark10
        self._buf = b""
        self.garbage = 0
        self.readings: deque[GaugeReading] = deque(maxlen=config.history)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: Exception | None = None
        self._lock = threading.Lock()

    def open(self) -> "ForceGauge":
        if self._port is None:
            self._port = open_serial(self.cfg.url, self.cfg.baudrate, "force gauge",
                                     "check the cable and the --gauge argument (e.g. serial:/dev/ttyUSB0)")
        return self

    def close(self) -> None:
        close_serial(self._port, self._thread, self._stop, f"force gauge {self.cfg.url}", log)
        self._thread = None

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()

    # ----- reading -------------------------------------------------------------------------------
    def _readline(self, deadline: float) -> bytes | None:
        import serial

        while b"\n" not in self._buf and b"\r" not in self._buf:
            if time.monotonic() > deadline or self._stop.is_set():
                return None
            try:
                chunk = self._port.read(self._port.in_waiting or 1)
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                raise DeviceNotFoundError(f"force gauge {self.cfg.url}: disconnected ({exc}); "
                                          "reconnect it and redo the current poke") from None
            self._buf += chunk
            if len(self._buf) > 4096:          # no line end in 4 kB: noise or a wrong baud rate
                self._buf = self._buf[-256:]
                self._count_garbage(b"<4 kB without a line end>")
        m = re.search(rb"\r\n|\n|\r", self._buf)
        line, self._buf = self._buf[:m.start()], self._buf[m.end():]
        return line

    def _count_garbage(self, line: bytes) -> None:
        self.garbage += 1
        log.debug("gauge %s: garbage line %r", self.cfg.url, line[:60])
        if self.garbage >= self.cfg.max_garbage:
            raise CaptureError(f"force gauge {self.cfg.url}: {self.garbage} unreadable lines in a row; is it "
                               f"speaking the '{self.cfg.protocol}' protocol at {self.cfg.baudrate} baud? "
                               f"last line: {line[:40]!r}")

    def read(self) -> GaugeReading:
        """The next valid reading (N), skipping garbage. Raises DeviceNotFoundError / CaptureError."""
        deadline = time.monotonic() + self.cfg.timeout_s
        next_poll = 0.0
        while True:
            now = time.monotonic()
            if self.cfg.protocol == "mark10" and now >= next_poll:
                self._write(b"?\r")
                next_poll = now + self.cfg.poll_s
            line = self._readline(min(deadline, next_poll) if self.cfg.protocol == "mark10" else deadline)
            if line is None and self._stop.is_set():
                raise _Stopped()
            if line is None:
                if time.monotonic() > deadline:
                    raise DeviceNotFoundError(f"force gauge {self.cfg.url}: no valid reading for "
                                              f"{self.cfg.timeout_s:.1f} s (not responding; check power, "
                                              "cable and that it is sending data)")
                continue
            if not line.strip():
                continue
            value = self._parse(line)
            if value is None:
                self._count_garbage(line)
                continue
            self.garbage = 0
            return GaugeReading(time.monotonic(), value)

    def _write(self, data: bytes) -> None:
        import serial

        try:
            self._port.write(data)
        except (serial.SerialException, OSError) as exc:
            raise DeviceNotFoundError(f"force gauge {self.cfg.url}: disconnected ({exc})") from None

    # ----- background reader ---------------------------------------------------------------------
    def start(self) -> "ForceGauge":
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"gauge:{self.cfg.url}", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                r = self.read()
                with self._lock:
                    self.readings.append(r)
        except _Stopped:
            pass
        except Exception as exc:  # handed to the session thread by check()
            self._error = exc

    def check(self) -> None:
        """Re-raise a failure of the background reader (unplug, timeout, garbage) in the caller."""
        if self._error is not None:
            raise self._error

    def window(self, t0: float, t1: float) -> tuple[list[float], list[float]]:
        """Readings (t, N) with t0 <= t <= t1 from the background reader."""
        with self._lock:
            sel = [r for r in self.readings if t0 <= r.t <= t1]
        return [r.t for r in sel], [r.force_n for r in sel]
