"""CAN output shell: sends each finger's contact summary at a fixed rate over python-can.

The frame loops only call `update(slot, summary)` (a dict assignment under a lock), so a slow,
erroring or bus-off CAN interface can never stall them. A sender thread encodes the newest summary
of every slot (contracts/can_frame.py, layout in docs/hand.md) `rate_hz` times per second and sends
it with a non-blocking `send`. Send errors are counted and reported through `flags()`; after
`reopen_after_errors` consecutive failures (bus-off, interface gone) the bus is shut down and
reopened every `reopen_wait_s` until it works again.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

from ..contracts.can_frame import FingerSummary, check_id_range, encode_finger
from ..contracts.errors import DeviceNotFoundError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CanConfig:
    """Where and how often the summary goes. Rates in Hz, times in s."""
    interface: str = "socketcan"          # any python-can interface name; "virtual" for tests
    channel: str = "can0"
    bitrate: int | None = None            # None: leave the interface's bitrate alone
    id_base: int = 0x300                  # finger slot k uses ids id_base+2k and id_base+2k+1
    rate_hz: float = 100.0                # summaries per finger per second
    extended_id: bool = False             # 29-bit ids
    send_timeout_s: float = 0.0           # 0: never wait for room in the TX queue
    reopen_after_errors: int = 20         # consecutive send errors before the bus is reopened
    reopen_wait_s: float = 0.5
    stale_after_s: float = 0.25           # summary older than this goes out with the "stale" bit

    def __post_init__(self):
        if self.rate_hz <= 0:
            raise ValueError(f"can.rate_hz is {self.rate_hz}, expected > 0")


def open_bus(cfg: CanConfig):
    """Open a python-can bus, with a clear error when the interface is not there."""
    import can

    kw = {"interface": cfg.interface, "channel": cfg.channel}
    if cfg.bitrate:
        kw["bitrate"] = cfg.bitrate
    try:
        return can.Bus(**kw)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        raise DeviceNotFoundError(f"CAN interface {cfg.interface}:{cfg.channel} cannot be opened: "
                                  f"{type(exc).__name__}: {exc}") from None


@dataclass
class CanStats:
    sent: int = 0
    errors: int = 0
    reopens: int = 0
    last_error: str | None = None
    bus_ok: bool = True
    per_slot: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"sent": self.sent, "errors": self.errors, "reopens": self.reopens,
                "last_error": self.last_error, "bus_ok": self.bus_ok}


class CanSummarySender:
    """Background sender of per-finger summaries. Pass `bus` to use an open python-can bus (not
    shut down by `stop()` and not reopened on errors); otherwise one is opened from `cfg`."""

    def __init__(self, cfg: CanConfig, n_slots: int, bus=None):
        check_id_range(cfg.id_base, n_slots, cfg.extended_id)
        self.cfg = cfg
        self.n_slots = n_slots
        self._own_bus = bus is None
        self.bus = bus if bus is not None else open_bus(cfg)
        self.stats = CanStats()
        self._lock = threading.Lock()
        self._latest: dict[int, tuple[FingerSummary, float]] = {}
        self._counter = 0
        self._errors_seen = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------- frame-loop side (never blocks)
    def update(self, slot: int, summary: FingerSummary) -> None:
        if not 0 <= slot < self.n_slots:
            raise ValueError(f"CAN slot {slot}: expected 0..{self.n_slots - 1}")
        with self._lock:
            self._latest[slot] = (summary, time.monotonic())

    def flags(self) -> set[str]:
        """{"can_errors"} while the bus is down or errors happened since the previous call."""
        with self._lock:
            new = self.stats.errors - self._errors_seen
            self._errors_seen = self.stats.errors
            ok = self.stats.bus_ok
        return {"can_errors"} if new or not ok else set()

    # ------------------------------------------------------------- sender thread
    def start(self) -> "CanSummarySender":
        self._thread = threading.Thread(target=self._run, name="can-summary", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._own_bus and self.bus is not None:
            try:
                self.bus.shutdown()
            except Exception as exc:  # noqa: BLE001
                log.debug("CAN shutdown: %s", exc)

    def __enter__(self) -> "CanSummarySender":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def frames_now(self) -> list[tuple[int, bytes]]:
        """Encode the current summaries (stale bit set where due); advances the counter."""
        now = time.monotonic()
        with self._lock:
            items = sorted(self._latest.items())
        self._counter = (self._counter + 1) & 0x0F
        out = []
        for slot, (s, t) in items:
            status = set(s.status)
            if now - t > self.cfg.stale_after_s:
                status.add("stale")
            s2 = FingerSummary(s.count, s.position_mm, s.force_n, s.total_force_n, status, self._counter)
            out += encode_finger(s2, self.cfg.id_base, slot)
        return out

    def send_once(self) -> int:
        """Send one round; returns the number of frames that failed."""
        import can

        failed = 0
        for arb, data in self.frames_now():
            msg = can.Message(arbitration_id=arb, data=data, is_extended_id=self.cfg.extended_id)
            try:
                self.bus.send(msg, timeout=self.cfg.send_timeout_s)
            except Exception as exc:  # noqa: BLE001 - any interface error: count, never raise
                failed += 1
                with self._lock:
                    self.stats.errors += 1
                    self.stats.last_error = f"{type(exc).__name__}: {exc}"
                    n = self.stats.errors
                if n == 1 or n % 1000 == 0:
                    log.warning("CAN send failed (%d so far): %s", n, exc)
            else:
                with self._lock:
                    self.stats.sent += 1
        return failed

    def _run(self) -> None:
        period = 1.0 / self.cfg.rate_hz
        next_t = time.monotonic()
        consecutive = 0
        while not self._stop.is_set():
            failed = self.send_once()
            consecutive = consecutive + failed if failed else 0
            with self._lock:
                self.stats.bus_ok = consecutive < self.cfg.reopen_after_errors
            if consecutive >= self.cfg.reopen_after_errors and self._own_bus:
                self._reopen()
                consecutive = 0
                next_t = time.monotonic()
            next_t += period
            wait = next_t - time.monotonic()
            if wait < -period:           # fell behind (slow interface): skip, don't burst
                next_t = time.monotonic()
                wait = 0.0
            self._stop.wait(max(wait, 0.0))

    def _reopen(self) -> None:
        log.warning("CAN %s:%s: %d consecutive send errors, reopening the bus (last: %s)",
                    self.cfg.interface, self.cfg.channel, self.cfg.reopen_after_errors, self.stats.last_error)
        try:
            self.bus.shutdown()
        except Exception as exc:  # noqa: BLE001
            log.debug("CAN shutdown: %s", exc)
        while not self._stop.wait(self.cfg.reopen_wait_s):
            try:
                self.bus = open_bus(self.cfg)
            except DeviceNotFoundError as exc:
                with self._lock:
                    self.stats.last_error = str(exc)
                continue
            with self._lock:
                self.stats.reopens += 1
            log.info("CAN %s:%s reopened", self.cfg.interface, self.cfg.channel)
            return


def receive_summaries(bus, id_base: int, n_slots: int, timeout_s: float = 1.0):
    """Controller side: yield (slot, FingerSummary) as complete summaries arrive on `bus`; stops
    when nothing arrives for `timeout_s`."""
    from ..contracts.can_frame import SummaryDecoder

    dec = SummaryDecoder(id_base, n_slots)
    while True:
        msg = bus.recv(timeout_s)
        if msg is None:
            return
        slot = dec.feed(msg.arbitration_id, msg.data)
        if slot is not None:
            yield slot, dec.fingers[slot]
