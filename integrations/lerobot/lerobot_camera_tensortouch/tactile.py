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

from dataclasses import dataclass

from .reading import ZenohReader

CONTACT_FIELDS = ("present", "x", "y", "z", "fx", "fy", "fz", "area")
WRENCH_FIELDS = ("fx", "fy", "fz", "tx", "ty", "tz")


@dataclass
class TensorTouchTactileConfig:
    sensor_id: str
    connect: str | None = None          # None: the meeting point (TENSORTOUCH_ENDPOINT, else loopback 7447)
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


class TensorTouchTactile(ZenohReader):
    """The camera's reading rules (reading.ZenohReader) for named floats: `read()` / `async_read(timeout_ms)`
    return the newest state not returned yet (waiting for one), `read_latest(max_age_ms)` the newest at
    once, TimeoutError when stale. Each returns a new dict."""

    what = "state"

    def __init__(self, config: TensorTouchTactileConfig):
        if config.top_k < 0:
            raise ValueError(f"top_k {config.top_k}: expected >= 0")
        self.config = config
        self._init_reader(config.sensor_id, config.connect, config.timeout_ms)
        self._pending: dict[int, dict] = {}

    def __str__(self) -> str:
        return f"TensorTouchTactile({self.config.sensor_id})"

    @property
    def features(self) -> dict[str, type]:
        return {n: float for n in feature_names(self.config.name, self.config.top_k)}

    def connect(self, warmup: bool = True) -> None:
        self._subscribe(warmup, on_contacts=lambda f: self._on("contacts", f.seq, f.contacts),
                        on_wrench=lambda w: self._on("wrench", w.seq, w))

    def _on(self, kind: str, seq: int, msg) -> None:
        with self._cond:
            parts = self._pending.setdefault(seq, {})
            parts[kind] = msg
            if len(parts) < 2:
                return
            del self._pending[seq]
            for old in [s for s in self._pending if s < seq]:
                del self._pending[old]           # a half that never got its other half
        self._put(state_floats(self.config.name, self.config.top_k, parts["wrench"], parts["contacts"]), seq)

    def read(self) -> dict[str, float]:
        return dict(super().read())

    def async_read(self, timeout_ms: float = 200) -> dict[str, float]:
        return dict(super().async_read(timeout_ms))

    def read_latest(self, max_age_ms: float = 500) -> dict[str, float]:
        return dict(super().read_latest(max_age_ms))
