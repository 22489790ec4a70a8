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


def _rss_mb(pid: int) -> float:
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def _get_json(url: str, timeout: float = 10.0):
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            body = r.read()
            return r.status, json.loads(body), len(body)
    except urllib.error.HTTPError as exc:
        body = exc.read()
        return exc.code, json.loads(body), len(body)


def test_hostile_publishers_and_slow_clients_leave_the_view_serving_the_genuine_sensor(tmp_path):
    """`tensortouch view` in its own process beside a genuine sensor (15x128x128 fields, a 4x4 gel surface)
    and hostile publishers on a client session: an info grid of [1500, 1500] and of [0, 0], fields without
    fn_x/fs_x, 15x1024x1024 fields, and eight HTTP clients trickling one byte a second. The view keeps
    answering the genuine sensor, every answer stays small, its memory stays bounded, the slow clients are
    cut at the request deadline, and the page's API says which channel is absent."""
    import subprocess
    import sys
    import threading

    import numpy as np
    from tensortouch.contracts.fields import CHANNEL_UNITS, CHANNELS
    from tensortouch.runtime.apps.publisher import Publisher
    from tensortouch.tools.view import server

    ep = free_endpoint()
    grid = {"grid": [4, 4], "xyz_mm": [float(v) for v in np.linspace(-5, 5, 48)], "mask": [True] * 16}
    genuine = Publisher("dome01", listen=[ep], info=lambda: {"gel_surface": grid, "finger": "index"})
    hostile = zenoh.open(zenoh_config(mode="client", connect=[ep]))    # a peer routes what its clients put
    answers = []
    for sid, surface in (("evil", {"grid": [1500, 1500], "xyz_mm": [0.0, 0.0, 0.0], "mask": [True]}),
                         ("evil0", {"grid": [0, 0], "xyz_mm": [], "mask": []})):
        def answer(query, sid=sid, surface=surface):
            query.reply(wire.info_key(sid), wire.encode_info({"gel_surface": surface}, sid, "9"),
                        encoding=zenoh.Encoding(wire.ENCODINGS["info"]))
        answers.append(hostile.declare_queryable(wire.info_key(sid), answer))
    stop = threading.Event()
    fields = np.linspace(-1, 1, 15 * 128 * 128, dtype=np.float32).reshape(15, 128, 128)
    keep = [i for i, c in enumerate(CHANNELS) if c not in ("fn_x", "fs_x")]
    lacking = wire.encode_fields(fields[keep], 1, 0.0, "evil", [CHANNELS[i] for i in keep],
                                 [CHANNEL_UNITS[i] for i in keep])
    huge = wire.encode_fields(np.ones((15, 1024, 1024), np.float32), 1, 0.0, "big")
    enc = zenoh.Encoding(wire.ENCODINGS["fields"])

    def publish():
        seq = 0
        while not stop.is_set():
            genuine.publish_fields(fields, seq, time.time())
            for sid, (payload, att, _) in (("evil", lacking), ("evil0", lacking), ("big", huge)):
                hostile.put(wire.key(sid, "fields"), payload, encoding=enc,
                            attachment=att.replace(b'"sensor_id":"evil"', f'"sensor_id":"{sid}"'.encode()))
            seq += 1
            time.sleep(0.05)

    view = subprocess.Popen([sys.executable, "-m", "tensortouch.runtime.shells.cli", "view", "--connect", ep,
                             "--port", "0"], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    th = threading.Thread(target=publish, daemon=True)
    slow = []
    try:
        line = view.stderr.readline()
        base = line.split()[2].rstrip("/")
        assert base.startswith("http://127.0.0.1:"), line
        th.start()
        deadline = time.monotonic() + 30
        while _get_json(base + "/api/frame?sensor=dome01")[0] != 200:
            assert time.monotonic() < deadline, "the genuine sensor never reached the view"
            time.sleep(0.2)
        code, geo, _ = _get_json(base + "/api/geometry?sensor=dome01")
        assert code == 200 and geo["grid"] == [4, 4] and not geo["nominal"] and geo["finger"] == "index"
        for sid, why in (("evil", "grid [1500, 1500]"), ("evil0", "grid [0, 0]")):
            while _get_json(base + f"/api/frame?sensor={sid}&channel=fn_z")[0] == 404:
                assert time.monotonic() < deadline, f"{sid}'s fields never reached the view"
                time.sleep(0.2)
            code, geo, _ = _get_json(base + f"/api/geometry?sensor={sid}")
            assert code == 200 and geo["nominal"] and why in geo["refused"], geo
            code, frame, size = _get_json(base + f"/api/frame?sensor={sid}&channel=fn_z")
            assert code == 200 and size < 200_000 and len(frame["grid_values"]) == server.NOMINAL_GRID ** 2
            code, frame, _ = _get_json(base + f"/api/frame?sensor={sid}&channel=traction_mag")
            assert code == 400 and "absent" in frame["error"] and "fn_x" in frame["error"], frame
            assert "traction_mag" not in frame["channels"] and "fn_y" in frame["channels"]
        assert _get_json(base + "/api/frame?sensor=big&channel=fn_z")[0] == 404     # too large: never kept
        rss0 = _rss_mb(view.pid)           # every route warmed up; the hostile streams go on from here
        host, port = base.split("//")[1].split(":")
        slow = [socket.create_connection((host, int(port)), timeout=30) for _ in range(8)]
        t0 = time.monotonic()
        cut = {}
        while len(cut) < len(slow) and time.monotonic() - t0 < server.REQUEST_DEADLINE_S + 10:
            for i, s in enumerate(slow):
                if i in cut:
                    continue
                try:
                    s.sendall(b"G")
                    s.setblocking(False)
                    try:
                        if s.recv(1) == b"":
                            cut[i] = time.monotonic() - t0
                    except BlockingIOError:
                        pass
                    finally:
                        s.setblocking(True)
                except OSError:
                    cut[i] = time.monotonic() - t0
            t_get = time.monotonic()
            code, frame, size = _get_json(base + "/api/frame?sensor=dome01&channel=traction_mag")
            assert code == 200 and frame["width"] == 128 and size < 1_000_000
            assert time.monotonic() - t_get < 3.0                 # the genuine sensor is served meanwhile
            for sid in ("evil", "evil0"):
                assert _get_json(base + f"/api/frame?sensor={sid}&channel=fn_z")[2] < 200_000
            time.sleep(1.0)
        assert len(cut) == len(slow), f"slow clients still connected after {time.monotonic() - t0:.0f} s: {cut}"
        assert max(cut.values()) < server.REQUEST_DEADLINE_S + 3, cut
        rss1 = _rss_mb(view.pid)
        print(f"view RSS {rss0:.0f} -> {rss1:.0f} MB; slow clients cut after {sorted(round(v, 1) for v in cut.values())} s")
        assert rss1 < rss0 + 50, (rss0, rss1)        # a 1500x1500 grid alone used to add 490 MB per request
        assert view.poll() is None
    finally:
        stop.set()
        for s in slow:
            s.close()
        view.terminate()
        view.wait(10)
        if th.is_alive():
            th.join(5)
        for q in answers:
            q.undeclare()
        hostile.close()
        genuine.close()
