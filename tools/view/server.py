"""Shell of `tensortouch view`: a Zenoh subscriber + a small HTTP server on 127.0.0.1.

The page (page.html, plain canvas, no JS libraries) polls `/api/frame` and draws the chosen field
channel as a colour map with its unit and range, the contacts on the image, and a 3D view of the
gel surface coloured by the same channel and deformed by the displacement field. Gel geometry
comes from the sensor's info queryable (`gel_surface`, published by `tensortouch hand`); a
sensor that does not publish it is drawn on the nominal dome (said on the page).

Routes: `/` page, `/api/sensors`, `/api/frame?sensor=ID&channel=NAME`, `/api/geometry?sensor=ID`,
`/api/lut`. Everything is JSON; the colour map image travels as base64 PNG inside it.

What sensors send is untrusted: the page puts every string into the DOM as text (never markup) and
is served with a Content-Security-Policy that lets only its own script run. The view keeps at most
`max_sensors` sensors and forgets one not heard from for `forget_after_s`. It bounds what it holds by
what a real sensor publishes: field images of at most FIELDS_MAX_SHAPE (larger ones are dropped before
they are converted), an info reply of at most INFO_MAX_BYTES, a gel surface grid of at most
SURFACE_GRID_MAX_SIDE per side (else the nominal dome is drawn and the page says why), so one kept
frame is at most 15*256*256*4 B = 3.9 MB and the kept frames of all sensors at most `max_sensors` times
that. A channel a sensor does not publish is answered with what it does publish. HTTP: at most
MAX_CONNECTIONS at once, idle connections closed after HTTP_IDLE_S, and each request must arrive and
be answered within REQUEST_DEADLINE_S, however slowly the client sends or reads.
"""
from __future__ import annotations

import base64
import hashlib
import json
import logging
import re
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np

from ...contracts.fields import CHANNELS
from ...runtime.stages.geometry import SURFACE_GRID_MAX_SIDE
from .render import ChannelAbsent, available, checked_surface, frame_view, lut_json

log = logging.getLogger(__name__)

PAGE = Path(__file__).with_name("page.html")
NOMINAL_GRID = 24
NOMINAL_THETA_EDGE_RAD = np.deg2rad(100.0)
HTTP_IDLE_S = 10.0                # an HTTP connection that sends nothing for this long is closed
REQUEST_DEADLINE_S = 10.0         # from waiting for a request to having sent its answer, whatever the pace
MAX_CONNECTIONS = 32              # HTTP connections served at once; more are closed on arrival
# What a real sensor publishes: the 15 wire channels at its model's size (128x128 for the shipped model);
# the view accepts up to twice that side, and an info reply (gel surface <= 32x32, model, finger) of 1 MB.
FIELDS_MAX_SHAPE = (len(CHANNELS), 256, 256)
INFO_MAX_BYTES = 1 << 20
STATUS_KEYS = ("state", "flags", "fps", "calibration_version", "model", "finger", "hand")


def page_and_policy() -> tuple[bytes, str]:
    """The page and its Content-Security-Policy: only the page's own inline script (by hash) runs,
    data comes from this server, images from data: URLs."""
    page = PAGE.read_bytes()
    scripts = re.findall(rb"<script>(.*?)</script>", page, flags=re.S)
    hashes = " ".join("'sha256-" + base64.b64encode(hashlib.sha256(s).digest()).decode() + "'" for s in scripts)
    policy = (f"default-src 'none'; script-src {hashes}; style-src 'unsafe-inline'; img-src data:; "
              "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
    return page, policy


def _status_view(status: dict | None) -> dict | None:
    """The few status members the page shows (a status may carry anything a sender put in it)."""
    if status is None:
        return None
    return {k: status.get(k) for k in STATUS_KEYS}


def nominal_surface(grid: int = NOMINAL_GRID) -> dict:
    """Ideal equidistant fisheye onto the default dome (runtime.stages.geometry), for sensors without info."""
    from ...runtime.stages.geometry import DomeProfile, equidistant_theta_phi, surface_tables

    theta, phi = equidistant_theta_phi((grid, grid), NOMINAL_THETA_EDGE_RAD)
    t = surface_tables(theta, phi, DomeProfile())
    xyz = np.nan_to_num(t["surface_xyz"])
    return {"grid": [grid, grid], "xyz_mm": np.round(xyz, 3).ravel().tolist(),
            "mask": [bool(v) for v in np.asarray(t["mask"]).ravel()], "nominal": True}


class ViewState:
    """Latest fields / contacts / status per sensor, fed by a runtime Subscriber."""

    def __init__(self, session, sensor: str = "*", *, forget_after_s: float = 10.0, max_sensors: int = 32):
        from ...runtime.apps.subscriber import Subscriber

        self.forget_after_s = float(forget_after_s)
        self.max_sensors = max(1, int(max_sensors))
        self.session = session
        self.lock = threading.Lock()
        self.fields: dict = {}
        self.contacts: dict = {}
        self.status: dict = {}
        self.received: dict = {}
        self._geometry: dict = {}
        self.sub = Subscriber(sensor, session=session, on_fields=self._put("fields"),
                              on_contacts=self._put("contacts"), on_status=self._put("status"),
                              fields_max_shape=FIELDS_MAX_SHAPE)

    def _put(self, kind):
        store = getattr(self, kind)

        def cb(msg):
            sid = msg["sensor_id"] if isinstance(msg, dict) else msg.sensor_id
            now = time.monotonic()
            with self.lock:
                if sid not in self.received:
                    self._forget(now)
                    if len(self.received) >= self.max_sensors:     # full of live ids: drop the quietest
                        self._drop(min(self.received, key=self.received.get))
                store[sid] = msg
                self.received[sid] = now
        return cb

    def _drop(self, sid: str) -> None:
        for table in (self.fields, self.contacts, self.status, self.received, self._geometry):
            table.pop(sid, None)

    def _forget(self, now: float) -> None:
        """Drop sensors not heard from for forget_after_s (call with the lock held)."""
        for sid in [s for s, t in self.received.items() if now - t > self.forget_after_s]:
            self._drop(sid)

    def sensors(self) -> list[dict]:
        with self.lock:
            now = time.monotonic()
            self._forget(now)
            return [{"sensor_id": s, "has_fields": s in self.fields,
                     "age_s": round(now - self.received[s], 2),
                     "status": _status_view(self.status.get(s))}
                    for s in sorted(self.received)]

    def geometry(self, sensor: str) -> dict:
        with self.lock:
            known = sensor in self.received
            cached = self._geometry.get(sensor)
        if cached is not None:
            return cached
        if not known:
            return nominal_surface()
        from ...contracts.errors import TensorTouchError
        from ...runtime.apps.subscriber import query_info

        try:
            info = query_info(self.session, sensor, timeout=1.0, max_bytes=INFO_MAX_BYTES)
        except TensorTouchError as exc:
            log.info("no info from %s (%s): nominal dome", sensor, exc)
            return nominal_surface()
        if info.get("gel_surface") is None:
            geo = nominal_surface()
        else:
            try:
                geo = checked_surface(info["gel_surface"], SURFACE_GRID_MAX_SIDE)
            except ValueError as exc:
                log.warning("sensor %s: %s; drawing the nominal dome", sensor, exc)
                geo = {**nominal_surface(), "refused": str(exc)}
        geo = {**geo, "finger": _short(info.get("finger")), "model": _short(info.get("model"))}
        with self.lock:
            if sensor in self.received:
                self._geometry[sensor] = geo
        return geo

    def frame(self, sensor: str, channel: str) -> dict | None:
        with self.lock:
            fields = self.fields.get(sensor)
            contacts = self.contacts.get(sensor)
            status = self.status.get(sensor)
        if fields is None:
            return None
        grid = tuple(self.geometry(sensor)["grid"])
        try:
            out = frame_view(fields, contacts, channel, grid)
        except ChannelAbsent as exc:
            return {"error": str(exc), "absent": channel, "channels": available(fields.channels),
                    "sensor_id": sensor}
        out["status"] = _status_view(status)
        return out

    def close(self) -> None:
        self.sub.close()


def _short(value, depth: int = 0):
    """A sender's free-form info member cut to a size the page can show (strings 80 characters, at most
    8 members, 2 levels); anything else is dropped."""
    if isinstance(value, str):
        return value[:80]
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return value
    if isinstance(value, dict) and depth < 2:
        return {str(k)[:40]: _short(v, depth + 1) for k, v in list(value.items())[:8]}
    return None


def make_handler(state: ViewState):
    page, policy = page_and_policy()

    class Handler(BaseHTTPRequestHandler):
        timeout = HTTP_IDLE_S                       # socket timeout: idle keep-alive connections end

        def handle_one_request(self):
            self.server.arm(self.connection, REQUEST_DEADLINE_S)     # a slow sender is cut at the deadline
            super().handle_one_request()

        def log_message(self, fmt, *args):          # quiet: one line per request is too much at 15 Hz
            log.debug(fmt, *args)

        def _send(self, code: int, body: bytes, ctype: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("Content-Security-Policy", policy)
            self.end_headers()
            self.wfile.write(body)

        def _json(self, obj, code: int = 200) -> None:
            self._send(code, json.dumps(obj, allow_nan=False, default=_plain).encode(), "application/json")

        def do_GET(self):  # noqa: N802 - http.server API
            url = urlparse(self.path)
            q = {k: v[0] for k, v in parse_qs(url.query).items()}
            try:
                if url.path in ("/", "/index.html"):
                    self._send(200, page, "text/html; charset=utf-8")
                elif url.path == "/api/sensors":
                    self._json(state.sensors())
                elif url.path == "/api/lut":
                    self._json(lut_json())
                elif url.path == "/api/geometry":
                    self._json(state.geometry(q["sensor"]))
                elif url.path == "/api/frame":
                    out = state.frame(q["sensor"], q.get("channel", "fn_z"))
                    if out is None:
                        self._json({"error": f"no fields from {q['sensor'][:80]} yet"}, 404)
                    else:
                        self._json(out, 400 if "absent" in out else 200)     # 400: a channel it lacks
                else:
                    self._json({"error": f"no route {url.path[:80]}"}, 404)
            except KeyError as exc:
                self._json({"error": f"missing or unknown parameter: {str(exc)[:80]}"}, 400)
            except OSError:
                pass                                 # the client went away (or was cut at the deadline)
            except Exception as exc:  # noqa: BLE001 - one bad request must not end the connection's page
                log.exception("view: %s failed", url.path)
                self._json({"error": f"{type(exc).__name__} while answering {url.path[:80]}"}, 500)

    return Handler


def _plain(obj):
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")


class ViewHTTPServer(ThreadingHTTPServer):
    """ThreadingHTTPServer with at most MAX_CONNECTIONS connections and a per-request deadline: a watchdog
    thread shuts down the socket of a request not answered by its deadline (a client trickling bytes, or
    not reading the answer), which ends that connection's thread."""

    daemon_threads = True

    def __init__(self, address, handler):
        super().__init__(address, handler)
        self._deadlines: dict = {}               # open connection -> monotonic deadline
        self._guard = threading.Lock()
        self._stop = threading.Event()
        threading.Thread(target=self._watchdog, name="view-http-deadlines", daemon=True).start()

    def process_request(self, request, client_address):
        with self._guard:
            full = len(self._deadlines) >= MAX_CONNECTIONS
            if not full:
                self._deadlines[request] = time.monotonic() + REQUEST_DEADLINE_S
        if full:
            log.warning("view: %d HTTP connections open; closing a new one from %s", MAX_CONNECTIONS, client_address)
            super().shutdown_request(request)
            return
        super().process_request(request, client_address)

    def shutdown_request(self, request):
        with self._guard:
            self._deadlines.pop(request, None)
        super().shutdown_request(request)

    def arm(self, request, seconds: float) -> None:
        with self._guard:
            if request in self._deadlines:
                self._deadlines[request] = time.monotonic() + seconds

    def open_connections(self) -> int:
        with self._guard:
            return len(self._deadlines)

    def _watchdog(self) -> None:
        while not self._stop.wait(0.2):
            now = time.monotonic()
            with self._guard:
                late = [r for r, t in self._deadlines.items() if t < now]
                for r in late:
                    self._deadlines[r] = float("inf")        # shut down once
            for r in late:
                try:
                    r.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def handle_error(self, request, client_address):
        log.debug("view: connection from %s ended with an error", client_address, exc_info=True)

    def shutdown(self):
        self._stop.set()
        super().shutdown()


def serve(state: ViewState, host: str = "127.0.0.1", port: int = 8765) -> ViewHTTPServer:
    """Start the HTTP server in a daemon thread; returns it (`.server_address`, `.shutdown()`)."""
    httpd = ViewHTTPServer((host, port), make_handler(state))
    threading.Thread(target=httpd.serve_forever, name="view-http", daemon=True).start()
    return httpd
