"""`tensortouch view` under many fake ids and idle connections: it keeps at most `max_sensors`, forgets
the ones it no longer hears, and closes HTTP connections that send nothing. Real Zenoh on loopback."""
import json
import socket
import time

import zenoh

from tensortouch.contracts import wire
from tensortouch.runtime.apps.zenoh_session import open_session, zenoh_config
from tests.test_listen import free_endpoint


def _status(sid: str) -> str:
    return json.dumps({"schema": wire.SCHEMAS["status"], "sensor_id": sid, "seq": 1, "t": 0.0,
                       "state": "stable", "flags": [], "timings_ms": {}})


def test_view_keeps_a_bounded_set_of_sensors_and_forgets_silent_ones():
    from tensortouch.tools.view.server import ViewState

    ep = free_endpoint()
    session = open_session(listen=[ep])
    flood = zenoh.open(zenoh_config(connect=[ep]))
    state = ViewState(session, forget_after_s=1.0, max_sensors=8)
    enc = zenoh.Encoding(wire.ENCODINGS["status"])
    try:
        time.sleep(0.5)
        seen = 0
        for i in range(300):
            flood.put(f"tensortouch/fake{i:03d}/status", _status(f"fake{i:03d}"), encoding=enc)
            seen = max(seen, len(state.sensors()))
            time.sleep(0.002)
        time.sleep(0.3)
        ids = [s["sensor_id"] for s in state.sensors()]
        assert 0 < len(ids) <= 8 and seen <= 8, (ids, seen)
        assert "fake299" in ids                           # the newest are kept
        time.sleep(1.3)
        assert state.sensors() == []                       # silent for > forget_after_s: forgotten
        with state.lock:
            assert not (state.status or state.received or state.fields or state.contacts)
    finally:
        state.close()
        flood.close()
        session.close()


def test_idle_http_connections_are_closed(monkeypatch):
    import tensortouch.tools.view.server as server

    monkeypatch.setattr(server, "HTTP_IDLE_S", 1.0)
    session = open_session(listen=[free_endpoint()])
    state = server.ViewState(session)
    httpd = server.serve(state, "127.0.0.1", 0)
    try:
        with socket.create_connection(httpd.server_address[:2], timeout=5) as s:
            t0 = time.monotonic()
            assert s.recv(1) == b""                         # the server hung up on a silent client
            assert time.monotonic() - t0 < 4.0
        with socket.create_connection(httpd.server_address[:2], timeout=5) as s:
            s.sendall(b"GET /api/sensors HTTP/1.1\r\nHost: x\r\n\r\n")
            assert s.recv(12).startswith(b"HTTP/1.")
    finally:
        httpd.shutdown()
        state.close()
        session.close()
