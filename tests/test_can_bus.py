"""CAN summary sender and receiver (drivers/can_bus.py) on python-can's virtual bus."""
import time
import uuid

import pytest

can = pytest.importorskip("can")

from tensortouch.contracts.can_frame import (  # noqa: E402
    FingerSummary,
    SummaryDecoder,
    decode_frames,
)
from tensortouch.drivers.can_bus import CanConfig, CanSummarySender, receive_summaries  # noqa: E402


def _channel():
    return f"tt-{uuid.uuid4().hex[:8]}"


def test_sender_on_virtual_bus_rate_and_decode():
    ch = _channel()
    cfg = CanConfig(interface="virtual", channel=ch, id_base=0x400, rate_hz=100.0)
    rx = can.Bus(interface="virtual", channel=ch)
    try:
        with CanSummarySender(cfg, 2) as tx:
            tx.update(0, FingerSummary(1, (1, 2, 3), (0, 0, 0.5), 0.5, {"alive", "contact"}))
            tx.update(1, FingerSummary(0, status={"alive"}))
            dec = SummaryDecoder(0x400, 2)
            t0 = time.monotonic()
            while time.monotonic() - t0 < 0.5:
                m = rx.recv(0.1)
                if m is not None:
                    dec.feed(m.arbitration_id, m.data)
            elapsed = time.monotonic() - t0
        assert dec.fingers[0].position_mm == pytest.approx((1, 2, 3))
        assert dec.fingers[0].force_n[2] == pytest.approx(0.5)
        assert dec.fingers[1].count == 0
        # 100 Hz for 0.5 s -> ~50 summaries per finger (loose bounds: shared 2-core machine)
        assert 20 <= dec.updated[0] <= 100 * elapsed + 5
    finally:
        rx.shutdown()


def test_sender_marks_stale_summaries():
    ch = _channel()
    cfg = CanConfig(interface="virtual", channel=ch, stale_after_s=0.05)
    tx = CanSummarySender(cfg, 1)                          # not started: frames built by hand
    try:
        tx.update(0, FingerSummary(0, status={"alive"}))
        fresh = decode_frames(tx.frames_now(), cfg.id_base, 1)[0]
        time.sleep(0.1)
        old = decode_frames(tx.frames_now(), cfg.id_base, 1)[0]
    finally:
        tx.stop()
    assert not fresh.has("stale") and old.has("stale")
    assert old.counter == (fresh.counter + 1) % 16


def test_bus_off_is_recovered_by_reopening():
    """A closed virtual bus raises CanOperationError on send (as a bus-off interface does)."""
    ch = _channel()
    cfg = CanConfig(interface="virtual", channel=ch, rate_hz=200, reopen_after_errors=4, reopen_wait_s=0.05)
    rx = can.Bus(interface="virtual", channel=ch)
    try:
        with CanSummarySender(cfg, 1) as tx:
            tx.update(0, FingerSummary(0, status={"alive"}))
            time.sleep(0.1)
            tx.bus.shutdown()                              # the interface goes away under the sender
            deadline = time.monotonic() + 3.0
            while tx.stats.reopens == 0 and time.monotonic() < deadline:
                time.sleep(0.02)
            assert tx.stats.errors >= 4 and tx.stats.reopens >= 1
            assert "can_errors" in tx.flags()
            sent = tx.stats.sent
            while rx.recv(0.0) is not None:
                pass
            time.sleep(0.2)
            assert tx.stats.sent > sent                    # sending again after recovery
            assert rx.recv(0.5) is not None
            tx.flags()
            assert tx.flags() == set()                     # errors cleared once reported
    finally:
        rx.shutdown()


class _SlowBus:
    """Injected fault (no hardware to make a real interface hang): every send blocks 50 ms."""

    def __init__(self):
        self.calls = 0

    def send(self, msg, timeout=None):
        self.calls += 1
        time.sleep(0.05)
        raise can.CanOperationError("Transmit buffer full (injected)")

    def shutdown(self):
        pass


def test_injected_blocking_bus_does_not_stall_updates():
    bus = _SlowBus()
    with CanSummarySender(CanConfig(interface="virtual", channel="unused"), 4, bus=bus) as tx:
        t0 = time.perf_counter()
        for k in range(2000):
            tx.update(k % 4, FingerSummary(1, status={"alive"}))
        per_update = (time.perf_counter() - t0) / 2000
        time.sleep(0.2)
    assert per_update < 1e-3          # the frame loop's side stays O(microseconds)
    assert bus.calls >= 2 and tx.stats.errors == bus.calls


def test_receive_summaries_generator_on_virtual_bus():
    ch = _channel()
    rx = can.Bus(interface="virtual", channel=ch)
    try:
        with CanSummarySender(CanConfig(interface="virtual", channel=ch, id_base=0x500, rate_hz=50), 3) as tx:
            tx.update(2, FingerSummary(2, (0.5, 0.25, 14.0), (0, 0.01, -0.75), 0.8, {"alive", "contact"}))
            got = []
            for slot, s in receive_summaries(rx, 0x500, 3, timeout_s=1.0):
                got.append((slot, s))
                if len(got) >= 5:
                    break
        assert {slot for slot, _ in got} == {2}
        s = got[-1][1]
        assert s.count == 2 and s.position_mm[2] == pytest.approx(14.0) and s.force_n[2] == pytest.approx(-0.75)
        counters = [g[1].counter for g in got]
        assert all((b - a) % 16 == 1 for a, b in zip(counters, counters[1:]))   # no round lost
    finally:
        rx.shutdown()
