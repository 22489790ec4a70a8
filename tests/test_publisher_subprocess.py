"""A SEPARATE PROCESS publishes a sensor over real zenoh; this process's Subscriber decodes it."""
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
from tensortouch.contracts.fields import CHANNEL_UNITS, CHANNELS
from tensortouch.runtime.apps.subscriber import Subscriber, alive_sensors, query_info, watch_alive

# The child publishes frames whose content is a known function of (channel, seq, pixel), so the
# parent checks the values, not just the shapes. It stops when its stdin closes.
CHILD = textwrap.dedent("""
    import sys, threading, time
    import numpy as np
    from tensortouch.contracts import wire
    from tensortouch.runtime.apps.publisher import Publisher

    ep, sid = sys.argv[1], sys.argv[2]
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    info = {"model": {"name": "tiny-test", "hash": "sha256:0123"}, "calibration_version": 9,
            "bounds": {"fn_z": [-0.5, 0.0]}}
    yy, xx = np.mgrid[0:96, 0:96].astype(np.float32)
    pub = Publisher(sid, connect=[ep], info=lambda: info)
    seq = 0
    while not stop.is_set() and seq < 2000:
        t = time.time()
        f = np.stack([(c + 1) * 0.01 * (xx - yy) + seq * 1e-3 for c in range(15)])
        c1 = wire.Contact(id=5, uv_px=(40.0, 50.0), position_mm=(1.5, -2.0, 14.25),
                          normal=(0.1, -0.1, 0.99), area_mm2=4.0, force_n=(0.05, 0.0, -0.8),
                          force_mag_n=0.8015, perimeter_px=22.0, circularity=0.88,
                          priority=0.8, age_frames=seq)
        pub.publish_fields(f, seq, t)
        pub.publish_contacts([c1], seq, t)
        F, T = wire.wrench_from_contacts([c1])
        pub.publish_wrench(F, T, seq, t)
        pub.publish_status({"state": "contact", "flags": [], "fps": 20.0,
                            "timings_ms": {"capture": 0.5, "infer": 9.0, "publish": 0.3},
                            "model_hash": "sha256:0123", "calibration_version": 9}, seq, t)
        seq += 1
        time.sleep(0.05)
    pub.close()
""")


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def test_separate_process_publisher_is_received_and_decoded():
    ep = free_endpoint()
    events = []
    with Subscriber("proc01", listen=[ep]) as sub:
        watcher = watch_alive(sub, lambda sid, alive: events.append((sid, alive)))
        proc = subprocess.Popen([sys.executable, "-c", CHILD, ep, "proc01"],
                                stdin=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            fr = sub.wait_for("fields", timeout=30.0)
            assert fr.sensor_id == "proc01"
            assert fr.data.shape == (15, 96, 96) and fr.data.dtype == np.float32
            assert fr.channels == CHANNELS and fr.units == CHANNEL_UNITS
            assert fr.units[0] == "mm" and fr.units[11] == "MPa"
            yy, xx = np.mgrid[0:96, 0:96]
            for c in (0, 7, 14):
                want = (c + 1) * 0.01 * (xx - yy) + fr.seq * 1e-3
                np.testing.assert_allclose(fr.data[c], want, rtol=2e-3, atol=2e-3)
            assert abs(time.time() - fr.t) < 30

            cf = sub.wait_for("contacts", timeout=10.0)
            assert cf.sensor_id == "proc01" and len(cf.contacts) == 1
            c = cf.contacts[0]
            assert c.id == 5 and c.position_mm == (1.5, -2.0, 14.25) and c.force_n == (0.05, 0.0, -0.8)
            assert c.age_frames == cf.seq

            w = sub.wait_for("wrench", timeout=10.0)
            np.testing.assert_allclose(w.force_n, (0.05, 0.0, -0.8))
            np.testing.assert_allclose(w.torque_nmm, np.cross((1.5, -2.0, 14.25), (0.05, 0.0, -0.8)))

            st = sub.wait_for("status", timeout=10.0)
            assert st["sensor_id"] == "proc01" and st["state"] == "contact"
            assert st["timings_ms"]["infer"] == 9.0 and st["wire"]["errors"]["fields"] == 0

            assert alive_sensors(sub) == ["proc01"]
            info = query_info(sub, "proc01")
            assert info["model"]["hash"] == "sha256:0123" and info["calibration_version"] == 9
            assert info["units"] == list(CHANNEL_UNITS)
            assert sub.errors == 0

            proc.stdin.close()                     # child closes its publisher and exits
            assert proc.wait(timeout=20) == 0, proc.stderr.read()
            deadline = time.monotonic() + 10
            while ("proc01", False) not in events and time.monotonic() < deadline:
                time.sleep(0.05)
            assert ("proc01", True) in events and ("proc01", False) in events, events
            assert alive_sensors(sub) == []
        finally:
            watcher.undeclare()
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
