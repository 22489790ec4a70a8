"""The mocap pose stream (drivers/mocap.py): the line protocol by hand, and the reader on pyserial's loop://
skipping garbage, normalizing quaternions and giving up on a stream that never speaks the protocol."""
import time

import pytest

serial = pytest.importorskip("serial")

from tensortouch.contracts.errors import CaptureError  # noqa: E402
from tensortouch.drivers.mocap import MocapConfig, PoseStream, format_pose, parse_pose  # noqa: E402


def test_pose_lines_by_hand():
    assert format_pose(2, (1.5, -2, 14.25), (1, 0, 0, 0)) == b"P 2 1.5 -2 14.25 1 0 0 0\n"
    assert parse_pose(b"P 2 1.5 -2 14.25 1 0 0 0\r\n") == (2, (1.5, -2.0, 14.25), (1.0, 0.0, 0.0, 0.0))
    ind, xyz, q = parse_pose(b"P 0 0 0 0 0 0.6 0.8 0.001")    # norm 1.0000005: normalized
    assert q == pytest.approx((0.0, 0.6, 0.8, 0.001), abs=1e-6) and sum(v * v for v in q) == pytest.approx(1.0)
    for bad in (b"P 0 1 2 3 1 0 0", b"Q 0 1 2 3 1 0 0 0", b"P -1 1 2 3 1 0 0 0", b"P 0 x 2 3 1 0 0 0",
                b"P 0 1 2 3 0.5 0 0 0", b"P 0 1e10 2 3 1 0 0 0", b"P 0 nan 2 3 1 0 0 0"):
        assert parse_pose(bad) is None, bad


def _wait(cond, timeout=3.0):
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.01)
    return cond()


def _failed(stream):
    try:
        stream.check()
    except CaptureError:
        return True
    return False


def test_stream_on_loop_url_keeps_poses_and_skips_garbage():
    port = serial.serial_for_url("loop://", timeout=0.05)
    port.write(b"garbage\n" + format_pose(0, (1, 2, 3), (1, 0, 0, 0)) + b"\n" + format_pose(1, (4, 5, 6), (0, 1, 0, 0)))
    with PoseStream(MocapConfig("loop://"), port) as s:
        s.start()
        assert _wait(lambda: len(s.poses()) == 2)
        a, b = s.poses()
        assert (a.indenter, a.xyz_mm, b.indenter, b.q_wxyz) == (0, (1.0, 2.0, 3.0), 1, (0.0, 1.0, 0.0, 0.0))
        assert a.t <= b.t and s.garbage == 0
        s.check()


def test_a_stream_that_never_speaks_the_protocol_is_one_clear_error():
    port = serial.serial_for_url("loop://", timeout=0.05)
    port.write(b"hello\nworld\n$GPGGA,1\n")
    with PoseStream(MocapConfig("loop://", max_garbage=3), port) as s:
        s.start()
        assert _wait(lambda: _failed(s))                    # the reader stops at the third bad line
        with pytest.raises(CaptureError, match=r"mocap stream loop://: 3 unreadable lines in a row \(expected 'P <indenter>"):
            s.check()
