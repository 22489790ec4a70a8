"""Zenoh wire benchmark (slow): encode/decode cost and publish->callback latency on loopback.

Run:  /work/venv/bin/python tests/test_wire_bench.py [--duration 5] [--rate 100]
  or  /work/venv/bin/pytest -m slow tests/test_wire_bench.py -s
Prints one JSON object (last line). Results are recorded in docs/BENCHMARKS.md "## Zenoh wire".
"""
import argparse
import json
import socket
import subprocess
import sys
import textwrap
import time
import timeit
from pathlib import Path

import numpy as np
import pytest
from tensortouch.contracts import wire
from tensortouch.runtime.apps.publisher import Publisher
from tensortouch.runtime.apps.subscriber import Subscriber

SHAPE = (15, 128, 128)

# Publisher process: publish_fields at `rate` Hz for `duration` s; t = wall clock just before the
# call, so the measured latency includes encode + transport + decode + dispatch.
CHILD = textwrap.dedent("""
    import sys
    import numpy as np
    sys.path.insert(0, sys.argv[4])
    from tensortouch.runtime.apps.publisher import Publisher
    from tests.test_wire_bench import publish_paced
    ep, rate, duration = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
    rng = np.random.default_rng(0)
    fields = rng.normal(size=(15, 128, 128)).astype(np.float32)
    pub = Publisher("bench01", connect=[ep])
    sys.stdin.readline()                       # parent says: subscriber ready
    publish_paced(pub, fields, rate, duration)
    print(pub.stats.sent["fields"], flush=True)
    pub.close()
""")
ROOT = Path(__file__).resolve().parents[1]


def publish_paced(pub, fields, rate: float, duration: float) -> int:
    """Publish `fields` at `rate` Hz for `duration` s (seq 0, 1, ...), then give the last frames
    0.5 s to arrive; returns how many were published."""
    period, n = 1.0 / rate, int(rate * duration)
    start = time.perf_counter()
    for seq in range(n):
        delay = start + seq * period - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        pub.publish_fields(fields, seq, time.time())
    time.sleep(0.5)
    return n


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _us(fn, number):
    return min(timeit.repeat(fn, number=number, repeat=5)) / number * 1e6


def codec_costs() -> dict:
    rng = np.random.default_rng(0)
    f = rng.normal(size=SHAPE).astype(np.float32)
    payload, att, _ = wire.encode_fields(f, 1, 0.0, "bench01")
    over = f.copy()
    over[5, :4, :4] = 1e6
    contacts = [wire.Contact(id=i, uv_px=(10.0, 20.0), position_mm=(1.0, 2.0, 14.0),
                             normal=(0.0, 0.0, 1.0), area_mm2=3.0, force_n=(0.1, 0.0, -1.0),
                             force_mag_n=1.005, perimeter_px=20.0, circularity=0.9, priority=1.0,
                             age_frames=4) for i in range(5)]
    cpay = wire.encode_contacts(contacts, 1, 0.0, "bench01")
    status = {"state": "contact", "flags": [], "fps": 120.0,
              "timings_ms": {k: 1.0 for k in ("capture", "preprocess", "infer", "contacts", "publish")}}
    spay = wire.encode_status(status, 1, 0.0, "bench01")
    return {
        "fields_bytes": len(payload), "fields_attachment_bytes": len(att),
        "encode_fields_us": _us(lambda: wire.encode_fields(f, 1, 0.0, "bench01"), 200),
        "encode_fields_clipping_us": _us(lambda: wire.encode_fields(over, 1, 0.0, "bench01"), 200),
        "decode_fields_us": _us(lambda: wire.decode_fields(payload, att), 200),
        "encode_contacts5_us": _us(lambda: wire.encode_contacts(contacts, 1, 0.0, "bench01"), 2000),
        "decode_contacts5_us": _us(lambda: wire.decode_contacts(cpay), 2000),
        "encode_status_us": _us(lambda: wire.encode_status(status, 1, 0.0, "bench01"), 2000),
        "decode_status_us": _us(lambda: wire.decode_status(spay), 2000),
    }


def _stats(lat_ms: list, sent: int) -> dict:
    a = np.asarray(lat_ms)
    return {"sent": sent, "received": int(a.size),
            "p50_ms": float(np.percentile(a, 50)) if a.size else None,
            "p99_ms": float(np.percentile(a, 99)) if a.size else None,
            "max_ms": float(a.max()) if a.size else None}


def latency_cross_process(rate: float, duration: float) -> dict:
    ep = free_endpoint()
    lat = []
    with Subscriber("bench01", listen=[ep],
                    on_fields=lambda fr: lat.append((time.time() - fr.t) * 1e3)) as sub:
        proc = subprocess.Popen([sys.executable, "-c", CHILD, ep, str(rate), str(duration), str(ROOT)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 30
            while not _alive(sub) and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.3)                       # let the subscription reach the publisher
            proc.stdin.write("go\n")
            proc.stdin.flush()
            sent = int(proc.stdout.readline() or 0)
            proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    return _stats(lat, sent)


def _alive(sub) -> bool:
    from tensortouch.runtime.apps.subscriber import alive_sensors

    return "bench01" in alive_sensors(sub, timeout=0.5)


def latency_same_process(rate: float, duration: float) -> dict:
    ep = free_endpoint()
    lat = []
    rng = np.random.default_rng(0)
    fields = rng.normal(size=SHAPE).astype(np.float32)
    with Publisher("bench01", listen=[ep]) as pub, \
            Subscriber("bench01", connect=[ep],
                       on_fields=lambda fr: lat.append((time.time() - fr.t) * 1e3)) as sub:
        deadline = time.monotonic() + 10
        while not lat and time.monotonic() < deadline:   # warm-up until frames flow
            pub.publish_fields(fields, -1, time.time())
            time.sleep(0.05)
        lat.clear()
        n = publish_paced(pub, fields, rate, duration)
        assert sub.errors == 0
    return _stats(lat, n)


def run(rate: float = 100.0, duration: float = 5.0) -> dict:
    return {"shape": list(SHAPE), "rate_hz": rate, "duration_s": duration,
            "codec": codec_costs(),
            "cross_process": latency_cross_process(rate, duration),
            "same_process": latency_same_process(rate, duration)}


@pytest.mark.slow
def test_wire_bench():
    res = run(100.0, 5.0)
    print(json.dumps(res))
    for name in ("cross_process", "same_process"):
        r = res[name]
        assert r["received"] >= 0.95 * r["sent"], r       # loopback: essentially nothing lost
        assert r["p50_ms"] < 20.0, r                       # loose: a shared 2-core machine
    assert res["codec"]["decode_fields_us"] < 20000


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--duration", type=float, default=5.0)
    a = ap.parse_args()
    print(json.dumps(run(a.rate, a.duration)))
