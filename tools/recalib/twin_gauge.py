"""Twin force gauge on a serial port: plays a recording's force stream as `tt` protocol lines.

    tensortouch twin gauge SESSION_DIR --port /dev/pts/5 [--speed 1] [--rate 50]

Lets the serial path of `tensortouch recalibrate --gauge serial:...` run against twin (or any
recorded) force truth: each line is `format_tt(|F|)` of the strongest indenter at that time, sent
at `rate` Hz on the recording's clock (scaled by `speed`). Pure part: `gauge_lines`.
"""
from __future__ import annotations

import argparse
import logging
import sys
import time

import numpy as np

from ...drivers.gauge import format_tt

log = logging.getLogger(__name__)


def gauge_lines(t: np.ndarray, indenter: np.ndarray, force: np.ndarray, rate_hz: float = 50.0):
    """(t_s, line bytes) at `rate_hz`: the strongest indenter's |F| (N) sampled on a uniform clock."""
    t, indenter = np.asarray(t, float), np.asarray(indenter, float)
    mag = np.linalg.norm(np.asarray(force, float).reshape(len(t), -1), axis=1)
    grid = np.arange(t.min(), t.max(), 1.0 / rate_hz)
    per = [np.interp(grid, t[indenter == k], mag[indenter == k], left=0.0, right=0.0) for k in np.unique(indenter)]
    best = np.max(per, axis=0)
    return [(float(tg), format_tt(float(f))) for tg, f in zip(grid, best)]


def play(lines, write, speed: float = 1.0, sleep=time.sleep, clock=time.monotonic) -> int:
    """Write each line at its time (scaled by `speed`); returns the number written."""
    if not lines:
        return 0
    t0, c0 = lines[0][0], clock()
    for t, line in lines:
        wait = (t - t0) / speed - (clock() - c0)
        if wait > 0:
            sleep(wait)
        write(line)
    return len(lines)


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("session", help="session folder whose force stream is played")
    ap.add_argument("--port", required=True, help="pyserial URL to write to (e.g. a pty, socket://...)")
    ap.add_argument("--speed", type=float, default=1.0, help="playback speed (1 = the recording's clock)")
    ap.add_argument("--rate", type=float, default=50.0, help="gauge lines per second")


def run(a: argparse.Namespace) -> int:
    import serial

    from ...contracts.session import load_session

    w = load_session(a.session).table("wrench")
    lines = gauge_lines(w[:, 0], w[:, 1], w[:, 2:5], a.rate)
    with serial.serial_for_url(a.port, baudrate=115200) as port:
        n = play(lines, port.write, a.speed)
    print(f"{n} gauge lines sent to {a.port}", file=sys.stderr)
    return 0

