"""The wrench and the top-K contacts of a TensorTouch sensor as named floats (for a LeRobot observation).

    tactile = TensorTouchTactile(TensorTouchTactileConfig(sensor_id="TWIN-DEMO", top_k=3))
    tactile.connect()
    obs.update(tactile.read_latest(max_age_ms=100))      # {"tactile.fx": .., "tactile.c0.fz": .., ...}

Names (prefix = config.name, default "tactile"), all float, units N, N·mm, mm, mm²:
  <prefix>.fx .fy .fz .tx .ty .tz             total contact force and torque about the gel origin
  <prefix>.c<i>.present                        1.0 for a contact, 0.0 for padding (i = 0..top_k-1)
  <prefix>.c<i>.x .y .z                        contact position (sensor frame)
  <prefix>.c<i>.fx .fy .fz                     contact force
  <prefix>.c<i>.area                           contact area
Contacts are ordered by force magnitude, strongest first; missing ones are zeros with present = 0.
A state is one runtime frame: the wrench and the contacts with the same sequence number.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

CONTACT_FIELDS = ("present", "x", "y", "z", "fx", "fy", "fz", "area")
WRENCH_FIELDS = ("fx", "fy", "fz", "tx", "ty", "tz")


@dataclass
class TensorTouchTactileConfig:
    sensor_id: str
    connect: str = "tcp/127.0.0.1:7447"
    top_k: int = 3
    name: str = "tactile"
    timeout_ms: float = 2000.0


def feature_names(name: str, top_k: int) -> list[str]:
    return [f"{name}.{f}" for f in WRENCH_FIELDS] + [
        f"{name}.c{i}.{f}" for i in range(top_k) for f in CONTACT_FIELDS]


def state_floats(name: str, top_k: int, wrench, contacts) -> dict[str, float]:
    """Named floats from a decoded Wrench and a list of decoded Contacts (contracts.wire)."""
    out = dict(zip((f"{name}.{f}" for f in WRENCH_FIELDS), (*map(float, wrench.force_n), *map(float, wrench.torque_nmm))))
    ranked = sorted(contacts, key=lambda c: -float(c.force_mag_n))[:top_k]
    for i in range(top_k):
        if i < len(ranked):
            c = ranked[i]
            vals = (1.0, *map(float, c.position_mm), *map(float, c.force_n), float(c.area_mm2))
        else:
            vals = (0.0,) * len(CONTACT_FIELDS)
        out.update(zip((f"{name}.c{i}.{f}" for f in CONTACT_FIELDS), vals))
    return out


class TensorTouchTactile:
    """Same reading rules as the camera: `read()` / `async_read(timeout_ms)` return the newest state not
    returned yet (waiting for one), `read_latest(max_age_ms)` the newest at once, TimeoutError if stale."""

    def __init__(self, config: TensorTouchTactileConfig):
        if config.top_k < 0:
            raise ValueError(f"top_k {config.top_k}: expected >= 0")
        self.config = config
        self._sub = None
        self._cond = threading.Condition()
        self._pending: dict[int, dict] = {}
        self._state: dict[str, float] | None = None
        self._arrived = 0.0
        self._count = 0
        self._returned = 0

    @property
    def features(self) -> dict[str, type]:
        return {n: float for n in feature_names(self.config.name, self.config.top_k)}

    @property
    def is_connected(self) -> bool:
        return self._sub is not None

    def connect(self, warmup: bool = True) -> None:
        from tensortouch.runtime.apps.subscriber import Subscriber

        if self.is_connected:
            raise RuntimeError(f"tactile {self.config.sensor_id} is already connected")
        self._sub = Subscriber(self.config.sensor_id, connect=[self.config.connect],
                               on_contacts=lambda f: self._on("contacts", f.seq, f.contacts),
                               on_wrench=lambda w: self._on("wrench", w.seq, w))
        if warmup:
            try:
                self.async_read(self.config.timeout_ms)
            except TimeoutError:
                self.disconnect()
                raise ConnectionError(f"tactile {self.config.sensor_id}: nothing from {self.config.connect} within "
                                      f"{self.config.timeout_ms:.0f} ms; is `tensortouch run` running?") from None

    def _on(self, kind: str, seq: int, msg) -> None:
        with self._cond:
            parts = self._pending.setdefault(seq, {})
            parts[kind] = msg
            if len(parts) == 2:
                del self._pending[seq]
                for old in [s for s in self._pending if s < seq]:
                    del self._pending[old]           # a half that never got its other half
                self._state = state_floats(self.config.name, self.config.top_k, parts["wrench"], parts["contacts"])
                self._arrived = time.perf_counter()
                self._count += 1
                self._cond.notify_all()

    def _require(self) -> None:
        if not self.is_connected:
            raise RuntimeError(f"tactile {self.config.sensor_id} is not connected")

    def read(self) -> dict[str, float]:
        return self.async_read(self.config.timeout_ms)

    def async_read(self, timeout_ms: float = 200) -> dict[str, float]:
        self._require()
        deadline = time.perf_counter() + timeout_ms / 1e3
        with self._cond:
            while self._count == self._returned:
                left = deadline - time.perf_counter()
                if left <= 0:
                    raise TimeoutError(f"tactile {self.config.sensor_id}: no new state within {timeout_ms:.0f} ms")
                self._cond.wait(left)
            self._returned = self._count
            return dict(self._state)

    def read_latest(self, max_age_ms: int = 500) -> dict[str, float]:
        self._require()
        with self._cond:
            state, arrived = self._state, self._arrived
        if state is None:
            raise RuntimeError(f"tactile {self.config.sensor_id} has not received any state yet")
        age_ms = (time.perf_counter() - arrived) * 1e3
        if age_ms > max_age_ms:
            raise TimeoutError(f"tactile {self.config.sensor_id}: the latest state is {age_ms:.0f} ms old "
                               f"(max {max_age_ms} ms)")
        return dict(state)

    def disconnect(self) -> None:
        self._require()
        sub, self._sub = self._sub, None
        sub.close()
