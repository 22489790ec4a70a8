"""Serial force gauge driver through pyserial's loop:// and a real pseudo-terminal (unplug = master closed)."""
import os
import select
import threading
import time

import pytest
from tensortouch.contracts.errors import CaptureError, DeviceNotFoundError
from tensortouch.drivers.gauge import ForceGauge, GaugeConfig, checksum, format_tt, parse_mark10, parse_tt


def test_tt_line_roundtrip_and_checksum():
    line = format_tt(2.315)
    assert line.startswith(b"F 2.3150*") and line.endswith(b"\n")
    assert parse_tt(line) == pytest.approx(2.315)
    assert parse_tt(format_tt(-0.5)) == pytest.approx(-0.5)
    body = b"F 2.3150"
    assert parse_tt(body + b"*%02X\n" % (checksum(body) ^ 1)) is None   # wrong checksum
    for junk in (b"", b"F", b"F abc*00", b"2.3150\n", b"\xff\xfe F 1.0*00", b"F 1.0"):
        assert parse_tt(junk) is None


def test_mark10_replies():
    assert parse_mark10(b"4.285 N\r\n") == pytest.approx(4.285)
    assert parse_mark10(b"-18.78 lbF") == pytest.approx(-18.78 * 4.4482216152605)
    assert parse_mark10(b"250 gF") == pytest.approx(0.25 * 9.80665)
    assert parse_mark10(b"1.5") == pytest.approx(1.5)
    for junk in (b"*10", b"4.2 furlongs", b"N 4.2", b""):
        assert parse_mark10(junk) is None


def test_loop_url_skips_garbage_and_partial_lines():
    g = ForceGauge(GaugeConfig("loop://", timeout_s=0.5)).open()
    try:
        g._port.write(b"\x00\xffnoise\n" + format_tt(1.25) + b"F 9.9*00\n" + format_tt(2.5)[:5])
        g._port.write(format_tt(2.5)[5:] + b"\r\n" + format_tt(-0.75))
        got = [g.read().force_n for _ in range(3)]
        assert got == pytest.approx([1.25, 2.5, -0.75])
        assert g.garbage == 0   # reset by the last valid line
    finally:
        g.close()


def test_loop_url_silent_gauge_times_out_with_clear_message():
    g = ForceGauge(GaugeConfig("loop://", timeout_s=0.3)).open()
    t0 = time.monotonic()
    with pytest.raises(DeviceNotFoundError, match="no valid reading for 0.3 s"):
        g.read()
    assert time.monotonic() - t0 < 2.0
    g.close()


def test_loop_url_wrong_protocol_is_reported():
    g = ForceGauge(GaugeConfig("loop://", timeout_s=2.0, max_garbage=5)).open()
    g._port.write(b"4.285 N\r\n" * 6)      # a Mark-10 talking while we expect 'tt'
    with pytest.raises(CaptureError, match="5 unreadable lines in a row.*'tt' protocol"):
        g.read()
    g.close()


def test_open_missing_device_says_so():
    with pytest.raises(DeviceNotFoundError, match="cannot open"):
        ForceGauge(GaugeConfig("/dev/ttyTT-does-not-exist")).open()


def _pty():
    master, slave = os.openpty()
    return master, os.ttyname(slave), slave


def test_pty_unplug_mid_stream_raises_disconnected():
    master, name, slave = _pty()
    g = ForceGauge(GaugeConfig(name, timeout_s=2.0)).open().start()
    try:
        for f in (0.5, 1.0, 1.5):
            os.write(master, format_tt(f))
        deadline = time.monotonic() + 2
        while len(g.readings) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert [r.force_n for r in g.readings] == pytest.approx([0.5, 1.0, 1.5])
        os.close(master)          # the gauge's cable is pulled
        os.close(slave)
        deadline = time.monotonic() + 3
        while g._error is None and time.monotonic() < deadline:
            time.sleep(0.01)
        with pytest.raises(DeviceNotFoundError, match="disconnected"):
            g.check()
    finally:
        g.close()


def test_pty_mark10_request_reply():
    master, name, slave = _pty()
    replies = iter([b"*10\r\n", b"4.285 N\r\n", b"-0.100 kgF\r\n"])
    stop = threading.Event()

    def gauge_side():     # answers each '?' like a Mark-10 Series 5
        buf = b""
        while not stop.is_set():
            if not select.select([master], [], [], 0.05)[0]:
                continue
            buf += os.read(master, 64)
            while b"?\r" in buf:
                buf = buf.split(b"?\r", 1)[1]
                os.write(master, next(replies, b"0.000 N\r\n"))

    th = threading.Thread(target=gauge_side, daemon=True)
    th.start()
    g = ForceGauge(GaugeConfig(name, protocol="mark10", baudrate=9600, poll_s=0.01, timeout_s=2)).open()
    try:
        assert g.read().force_n == pytest.approx(4.285)
        assert g.read().force_n == pytest.approx(-0.980665)
    finally:
        stop.set()
        th.join(timeout=2)
        g.close()
        os.close(master)
        os.close(slave)


