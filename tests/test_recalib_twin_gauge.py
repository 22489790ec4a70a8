"""The twin gauge (tools/recalib/twin_gauge.py) played through a pty and read back by the gauge driver."""
import os
import time

from tensortouch.drivers.gauge import ForceGauge, GaugeConfig


def _pty():
    master, slave = os.openpty()
    return master, os.ttyname(slave), slave


def test_twin_gauge_lines_through_a_pty_are_read_back():
    """tools.recalib.twin_gauge plays a force stream as tt lines; the driver reads the same |F|."""
    import numpy as np
    from tensortouch.tools.recalib.twin_gauge import gauge_lines, play

    t = np.arange(0, 1.0, 0.01)
    fz = np.where((t > 0.2) & (t < 0.8), -2.0, 0.0)
    force = np.stack([0.3 * fz, np.zeros_like(t), fz], 1)
    lines = gauge_lines(t, np.zeros_like(t), force, rate_hz=50)
    assert len(lines) == 50
    master, name, slave = _pty()
    g = ForceGauge(GaugeConfig(name, timeout_s=2.0)).open().start()
    try:
        assert play(lines, lambda b: os.write(master, b), speed=10.0) == 50
        deadline = time.monotonic() + 2
        while len(g.readings) < 50 and time.monotonic() < deadline:
            time.sleep(0.01)
        got = np.array([r.force_n for r in g.readings])
        expect = np.interp([x for x, _ in lines], t, np.hypot(0.3 * fz, fz))
        assert np.allclose(got, expect, atol=1e-4)
    finally:
        g.close()
        os.close(master)
        os.close(slave)
