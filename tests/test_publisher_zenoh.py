"""Publisher + Subscriber over a REAL zenoh session pair on loopback (peer mode, tcp, no multicast)."""
import json
import math
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest
from tensortouch.contracts import wire
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.contracts.fields import CHANNEL_UNITS, CHANNELS
from tensortouch.runtime.apps.publisher import Publisher, open_session, zenoh_config
from tensortouch.runtime.apps.subscriber import Subscriber, alive_sensors, query_info, watch_alive

from tests.hand_util import free_endpoint
from tests.hand_util import wait_until as _wait_until


def wait_until(pred, timeout=5.0, step=0.02):
    return _wait_until(pred, timeout, step)


def make_contact(i, f, p):
    return wire.Contact(id=i, uv_px=(10.0 + i, 20.0), position_mm=p, normal=(0.0, 0.0, 1.0),
                        area_mm2=2.0 * i, force_n=f, force_mag_n=float(np.linalg.norm(f)),
                        perimeter_px=12.0, circularity=0.9, priority=float(np.linalg.norm(f)),
                        age_frames=3)


INFO = {"model": {"name": "tiny", "hash": "sha256:feed"}, "calibration_version": 4,
        "bounds": {name: [-1.0, 1.0] for name in CHANNELS}}


@pytest.fixture
def pair():
    """A publisher session (listening) and a subscriber session connected to it."""
    ep = free_endpoint()
    pub = Publisher("dome01", listen=[ep], info=lambda: INFO)
    sub = Subscriber("*", connect=[ep])
    try:
        assert wait_until(lambda: "dome01" in alive_sensors(sub, timeout=0.5), 5.0)
        # warm-up: once one status got through, the subscription is known to the publisher
        publish_until(lambda: pub.publish_status({"state": "warmup"}, 0, 0.0), sub, "status")
        yield pub, sub, ep
    finally:
        sub.close()
        pub.close()


def publish_until(pub_fn, sub, kind, timeout=5.0):
    """Publish repeatedly from a thread until `sub` receives `kind` (first puts may race the
    subscriber declaration reaching the publisher)."""
    stop = threading.Event()

    def loop():
        while not stop.is_set():
            pub_fn()
            time.sleep(0.02)

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    try:
        return sub.wait_for(kind, timeout=timeout)
    finally:
        stop.set()
        th.join(2.0)


def test_zenoh_config_builder():
    cfg = zenoh_config(listen=["tcp/127.0.0.1:7999"], connect=["tcp/127.0.0.1:7998"])
    assert '"peer"' in cfg.get_json("mode")
    assert cfg.get_json("scouting/multicast/enabled") == "false"
    assert "7999" in cfg.get_json("listen/endpoints") and "7998" in cfg.get_json("connect/endpoints")
    with pytest.raises(TensorTouchError, match="mode"):
        zenoh_config(mode="satellite")


def test_round_trip_every_payload(pair):
    pub, sub, _ = pair
    rng = np.random.default_rng(1)
    fields = rng.normal(size=(15, 128, 128)).astype(np.float32)
    fr = publish_until(lambda: pub.publish_fields(fields, 11, 1.5), sub, "fields")
    assert fr.sensor_id == "dome01" and fr.seq == 11 and fr.t == 1.5
    assert fr.data.shape == (15, 128, 128) and fr.data.dtype == np.float32
    assert fr.channels == CHANNELS and fr.units == CHANNEL_UNITS
    np.testing.assert_array_equal(fr.data, fields.astype(np.float16).astype(np.float32))

    cs = [make_contact(1, (0.0, 0.1, -1.2), (1.0, -2.0, 14.5)),
          make_contact(2, (0.3, 0.0, -0.2), (-4.0, 0.0, 12.0))]
    cf = publish_until(lambda: pub.publish_contacts(cs, 12, 1.6), sub, "contacts")
    assert cf.contacts == cs and cf.seq == 12 and cf.sensor_id == "dome01"

    force, torque = wire.wrench_from_contacts(cs)
    w = publish_until(lambda: pub.publish_wrench(force, torque, 13, 1.7), sub, "wrench")
    np.testing.assert_allclose(w.force_n, force)
    np.testing.assert_allclose(w.torque_nmm, torque)

    st = publish_until(lambda: pub.publish_status(
        {"state": "contact", "flags": ["model_fallback"], "fps": 99.5,
         "timings_ms": {"capture": 1.0, "infer": 8.5}, "model_hash": "sha256:feed",
         "calibration_version": 4}, 14, 1.8), sub, "status")
    assert st["state"] == "contact" and "model_fallback" in st["flags"]
    assert st["timings_ms"] == {"capture": 1.0, "infer": 8.5} and st["sensor_id"] == "dome01"
    assert st["wire"]["sent"]["fields"] >= 1 and st["wire"]["errors"]["fields"] == 0
    assert sub.errors == 0


def test_subscriber_counts_malformed_and_skips_unknown_streams(pair):
    """Raw puts from a foreign publisher: a bad schema is counted, a new stream is ignored."""
    pub, sub, _ = pair
    n = sub.counts["status"]
    pub.session.put("tensortouch/dome01/status", b'{"schema":"tensortouch.status.v9"}',
                    encoding="application/json;tensortouch.status.v9")
    pub.session.put("tensortouch/dome01/pressure", b"future stream")
    assert wait_until(lambda: sub.errors == 1, 5.0), (sub.errors, sub.last_error)
    assert "tensortouch.status.v9" in sub.last_error and sub.counts["status"] == n
    pub.publish_status({"state": "stable"}, 5, 0.5)       # the stream keeps working
    assert sub.wait_for("status", timeout=5.0, since=n)["seq"] == 5
    assert sub.errors == 1


def test_non_finite_messages_are_dropped_and_counted_never_handed_to_a_callback():
    """A forger on the real session puts contacts, wrenches and fields holding NaN/Infinity between
    genuine ones: the callbacks see only the genuine messages, `non_finite` counts every forged one."""
    ep = free_endpoint()
    pub = Publisher("dome01", listen=[ep])
    got = {"contacts": [], "wrench": [], "fields": []}
    sub = Subscriber("dome01", connect=[ep], on_contacts=got["contacts"].append,
                     on_wrench=got["wrench"].append, on_fields=got["fields"].append)
    try:
        assert wait_until(lambda: "dome01" in alive_sensors(sub, timeout=0.5), 5.0)
        publish_until(lambda: pub.publish_status({"state": "warmup"}, 0, 0.0), sub, "status")
        c = make_contact(1, (0.0, 0.1, -1.2), (1.0, -2.0, 14.5)).to_dict()
        head = json.loads(wire.encode_fields(np.zeros((15, 4, 4), np.float32), 1, 0.0, "dome01")[1])
        nan_fields = np.zeros((15, 4, 4), np.float16)
        nan_fields[12, 2, 2] = np.nan
        for i in range(20):
            body = {"schema": "tensortouch.contacts.v1", "sensor_id": "dome01", "seq": i, "t": 1.0,
                    "contacts": [{**c, "force_n": [float("nan"), 0.0, -1.0], "force_mag_n": float("nan")}]}
            pub.session.put(wire.key("dome01", "contacts"), json.dumps(body).encode(),
                            encoding=wire.ENCODINGS["contacts"])
            pub.session.put(wire.key("dome01", "wrench"),
                            ('{"schema":"tensortouch.wrench.v1","sensor_id":"dome01","seq":%d,"t":1.0,'
                             '"frame":"gel","force_n":[Infinity,0,0],"torque_nmm":[0,0,0]}' % i).encode(),
                            encoding=wire.ENCODINGS["wrench"])
            if i < 5:
                pub.session.put(wire.key("dome01", "fields"), nan_fields.tobytes(), encoding=wire.ENCODINGS["fields"],
                                attachment=json.dumps(head).encode())
        assert wait_until(lambda: sub.non_finite == 45, 10.0), (sub.non_finite, sub.last_error)
        assert sub.errors == 45 and got == {"contacts": [], "wrench": [], "fields": []}
        pub.publish_contacts([make_contact(2, (0.0, 0.0, -0.5), (0.0, 0.0, 14.0))], 30, 2.0)
        pub.publish_wrench((0.0, 0.0, -0.5), (0.0, 0.0, 0.0), 30, 2.0)
        assert wait_until(lambda: got["contacts"] and got["wrench"], 5.0)
        assert got["contacts"][0].seq == 30 and got["wrench"][0].force_n == (0.0, 0.0, -0.5)
        assert all(math.isfinite(v) for f in got["contacts"] for ct in f.contacts for v in ct.force_n)
    finally:
        sub.close()
        pub.close()


def test_queryable_answers_and_errors(pair):
    pub, sub, _ = pair
    info = query_info(sub, "dome01")
    assert info["model"]["hash"] == "sha256:feed" and info["calibration_version"] == 4
    assert info["channels"] == list(CHANNELS) and info["units"] == list(CHANNEL_UNITS)
    assert info["sensor_id"] == "dome01" and info["keys"]["alive"] == "tensortouch/dome01/alive"
    assert pub.stats.info_queries == 1
    with pytest.raises(TensorTouchError, match="did not answer"):
        query_info(sub, "nosuchsensor", timeout=0.5)

    def broken():
        raise RuntimeError("calibration store unreadable")

    bad = Publisher("dome02", session=pub.session, info=broken)
    try:
        assert wait_until(lambda: "dome02" in alive_sensors(sub, timeout=0.5), 5.0)
        with pytest.raises(TensorTouchError, match="calibration store unreadable"):
            query_info(sub, "dome02", timeout=2.0)
    finally:
        bad.close()


def test_liveliness_appears_and_disappears():
    ep = free_endpoint()
    sub = Subscriber("*", connect=[ep])
    events = []
    watcher = watch_alive(sub, lambda sid, alive: events.append((sid, alive)))
    try:
        pub = Publisher("dome07", listen=[ep])
        try:
            assert wait_until(lambda: ("dome07", True) in events, 5.0), events
            assert alive_sensors(sub) == ["dome07"]
        finally:
            pub.close()
        assert wait_until(lambda: ("dome07", False) in events, 5.0), events
        assert alive_sensors(sub) == []
    finally:
        watcher.undeclare()
        sub.close()


def test_several_sensors_share_one_session():
    ep = free_endpoint()
    session = open_session(listen=[ep])
    pubs = [Publisher(sid, session=session, info=lambda sid=sid: {"model": {"name": sid}})
            for sid in ("left", "right")]
    only_right = Subscriber("right", connect=[ep])
    try:
        assert wait_until(lambda: alive_sensors(only_right) == ["left", "right"], 5.0)
        assert query_info(only_right, "left")["model"]["name"] == "left"
        st = publish_until(lambda: [p.publish_status({"state": "stable"}, 1, 0.0) for p in pubs],
                           only_right, "status")
        assert st["sensor_id"] == "right"
        pubs[0].close()                       # does not close the shared session
        assert not session.is_closed()
        assert wait_until(lambda: alive_sensors(only_right) == ["right"], 5.0)
        assert pubs[1].publish_status({"state": "stable"}, 2, 0.1)
    finally:
        only_right.close()
        for p in pubs:
            p.close()
        session.close()


def test_subscriber_going_away_does_not_break_publisher(pair):
    pub, sub, ep = pair
    fields = np.zeros((15, 128, 128), np.float32)
    publish_until(lambda: pub.publish_fields(fields, 0, 0.0), sub, "fields")
    sub.close()                               # the only subscriber disappears mid-stream
    worst = 0.0
    for seq in range(1, 201):
        t0 = time.perf_counter()
        ok = pub.publish_fields(fields, seq, seq * 0.01)
        pub.publish_contacts([], seq, seq * 0.01)
        worst = max(worst, time.perf_counter() - t0)
        assert ok
    assert sum(pub.stats.errors.values()) == 0 and pub.stats.sent["fields"] >= 201
    assert worst < 0.5, f"a publish call blocked for {worst:.3f} s"


def test_killed_subscriber_process_does_not_break_publisher():
    """A subscriber in another process is SIGKILLed while fields flood: puts never raise or block."""
    ep = free_endpoint()
    code = textwrap.dedent(f"""
        import sys, time
        from tensortouch.runtime.apps.subscriber import Subscriber
        sub = Subscriber("*", connect=["{ep}"])
        sub.wait_for("fields", timeout=20)
        print("got", flush=True)
        time.sleep(60)
    """)
    with Publisher("dome01", listen=[ep]) as pub:
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
        try:
            fields = np.ones((15, 128, 128), np.float32)
            got = []
            reader = threading.Thread(target=lambda: got.append(proc.stdout.readline()), daemon=True)
            reader.start()
            seq, deadline = 0, time.monotonic() + 30
            while not got and time.monotonic() < deadline:
                pub.publish_fields(fields, seq, 0.0)
                seq += 1
                time.sleep(0.005)
            assert got == ["got\n"], "subscriber process never received fields"
            proc.kill()
            worst, n_ok = 0.0, 0
            for i in range(300):
                t0 = time.perf_counter()
                n_ok += pub.publish_fields(fields, seq + i, 0.0)
                worst = max(worst, time.perf_counter() - t0)
            assert n_ok == 300 and worst < 0.5, (n_ok, worst)
            assert pub.publish_status({"state": "stable"}, 1, 0.0)
        finally:
            proc.kill()
            proc.wait(10)


def test_closed_publisher_counts_errors_instead_of_raising():
    pub = Publisher("dome01", listen=[free_endpoint()])
    pub.close()
    assert pub.publish_fields(np.zeros((15, 4, 4), np.float32), 1, 0.0) is False
    assert pub.publish_contacts([], 1, 0.0) is False
    assert pub.stats.errors["fields"] == 1 and "closed" in pub.stats.last_error
    # bad input is counted too, never raised into the frame loop
    pub2 = Publisher("dome02", listen=[free_endpoint()])
    try:
        assert pub2.publish_fields(np.zeros((3, 4, 4)), 1, 0.0) is False
        assert pub2.stats.errors["fields"] == 1 and "expected shape" in pub2.stats.last_error
    finally:
        pub2.close()


def test_status_reports_publish_errors_and_clipping(pair):
    pub, sub, _ = pair
    pub.publish_fields(np.zeros((2, 4, 4)), 1, 0.0)           # counted error
    big = np.full((15, 4, 4), 1e9, np.float32)
    pub.publish_fields(big, 2, 0.0)                            # clipped + flagged
    n = sub.counts["status"]
    assert pub.publish_status({"state": "stable", "flags": ["frame_black"]}, 3, 0.1)
    st = sub.wait_for("status", timeout=5.0, since=n)
    assert st["wire"]["errors"]["fields"] == 1 and st["wire"]["clipped_frames"] == 1
    assert st["flags"] == ["fields_clipped", "frame_black", "publish_errors"]
    n = sub.counts["status"]
    assert pub.publish_status({"state": "stable"}, 4, 0.2)   # nothing new since: no flags
    assert sub.wait_for("status", timeout=5.0, since=n)["flags"] == []


def test_control_congestion_block_delivers_every_contact_frame_and_bad_values_are_refused():
    """A step-locked simulation publishes contacts with BLOCK: a burst of frames all arrive, in order."""
    from tensortouch.runtime.apps.publisher import PublisherConfig

    with pytest.raises(TensorTouchError, match="control_congestion"):
        Publisher("dome01", listen=[free_endpoint()], config=PublisherConfig(control_congestion="LATER"))
    ep = free_endpoint()
    pub = Publisher("dome01", listen=[ep], config=PublisherConfig(control_congestion="BLOCK"))
    seqs = []
    sub = Subscriber("dome01", connect=[ep], on_contacts=lambda fr: seqs.append(fr.seq))
    try:
        publish_until(lambda: pub.publish_status({"state": "warmup"}, 0, 0.0), sub, "status")
        for k in range(1, 201):
            assert pub.publish_contacts([make_contact(1, (0.0, 0.0, -1.0), (0.0, 0.0, 8.0))], k, 0.01 * k)
        assert wait_until(lambda: len(seqs) >= 200, 10.0)
        assert seqs == list(range(1, 201))
    finally:
        sub.close()
        pub.close()
