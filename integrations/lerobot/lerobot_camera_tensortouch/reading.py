"""One subscribed stream of a TensorTouch sensor, read the way LeRobot reads its devices.

`ZenohReader` subscribes through the runtime's `Subscriber` (Zenoh delivers each message on its own
thread; no polling thread here) and keeps the newest decoded value. Three ways to read it:

- `read()` / `async_read(timeout_ms)`: the newest value not returned before, waiting for it up to the
  timeout (TimeoutError "no new ... within ..." after it);
- `read_latest(max_age_ms)`: the newest value at once; TimeoutError "... ms old" when it arrived more
  than max_age_ms ago (the runtime stopped or stalled), RuntimeError before the first one.

A stale or missing sensor is always an exception, never a zero.
`last_read_seq` is the runtime sequence number of the value a read returned last.
"""
from __future__ import annotations

import threading
import time
from typing import Any


class ZenohReader:
    """Base of the camera and the tactile reader. Subclasses call `_init_reader` in `__init__`,
    `_subscribe(**callbacks)` in `connect`, and `_put(value, seq)` from their callbacks."""

    what = "message"               # the noun the error messages use

    def _init_reader(self, sensor_id: str, connect: str | None, timeout_ms: float) -> None:
        from tensortouch.runtime.apps.zenoh_session import default_endpoint

        # None: the meeting point `tensortouch run` listens on (TENSORTOUCH_ENDPOINT, else loopback 7447)
        self._sensor_id, self._connect, self._timeout_ms = sensor_id, connect or default_endpoint(), timeout_ms
        self._sub = None
        self._cond = threading.Condition()
        self._value: Any = None
        self._arrived = 0.0          # time.perf_counter() when the newest value arrived
        self._seq = -1               # its runtime sequence number
        self._count = 0              # values received
        self._returned = 0           # _count when read()/async_read() last returned
        self.last_read_seq = -1

    # errors: plain ones here; the camera raises LeRobot's device errors instead
    def _already_connected(self) -> Exception:
        return RuntimeError(f"{self} is already connected")

    def _not_connected(self) -> Exception:
        return RuntimeError(f"{self} is not connected")

    @property
    def is_connected(self) -> bool:
        return self._sub is not None

    def _subscribe(self, warmup: bool, **callbacks) -> None:
        from tensortouch.runtime.apps.subscriber import Subscriber

        if self.is_connected:
            raise self._already_connected()
        self._sub = Subscriber(self._sensor_id, connect=[self._connect], **callbacks)
        if warmup:
            try:
                self.async_read(self._timeout_ms)
            except TimeoutError:
                self.disconnect()
                raise ConnectionError(f"{self}: no {self.what} from {self._connect} within {self._timeout_ms:.0f} ms; "
                                      f"is `tensortouch run` publishing sensor {self._sensor_id!r} there?") from None

    def _put(self, value: Any, seq: int) -> None:
        with self._cond:
            self._value, self._arrived, self._seq = value, time.perf_counter(), seq
            self._count += 1
            self._cond.notify_all()

    def _require(self) -> None:
        if not self.is_connected:
            raise self._not_connected()

    def read(self) -> Any:
        return self.async_read(self._timeout_ms)

    def async_read(self, timeout_ms: float = 200) -> Any:
        self._require()
        deadline = time.perf_counter() + timeout_ms / 1e3
        with self._cond:
            while self._count == self._returned:
                left = deadline - time.perf_counter()
                if left <= 0:
                    raise TimeoutError(f"{self}: no new {self.what} within {timeout_ms:.0f} ms")
                self._cond.wait(left)
            self._returned = self._count
            self.last_read_seq = self._seq
            return self._value

    def read_latest(self, max_age_ms: float = 500) -> Any:
        self._require()
        with self._cond:
            value, arrived, seq = self._value, self._arrived, self._seq
        if value is None:
            raise RuntimeError(f"{self} has not received any {self.what} yet")
        age_ms = (time.perf_counter() - arrived) * 1e3
        if age_ms > max_age_ms:
            raise TimeoutError(f"{self}: the latest {self.what} is {age_ms:.0f} ms old (max {max_age_ms:.0f} ms)")
        self.last_read_seq = seq
        return value

    @property
    def latest_seq(self) -> int:
        """Runtime sequence number of the newest value (-1 before the first)."""
        return self._seq

    def disconnect(self) -> None:
        self._require()
        sub, self._sub = self._sub, None
        sub.close()
