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
`max_sensors` sensors and forgets one not heard from for `forget_after_s`; idle HTTP connections
are closed after `HTTP_IDLE_S`.
"""
from __future__ import annotations

import base64
import hashlib
import json
import logging
import re
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np

from .render import frame_view, lut_json

log = logging.getLogger(__name__)

PAGE = Path(__file__).with_name("page.html")
NOMINAL_GRID = 24
NOMINAL_THETA_EDGE_RAD = np.deg2rad(100.0)
HTTP_IDLE_S = 10.0                # an HTTP connection that sends nothing for this long is closed
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
                              on_contacts=self._put("contacts"), on_status=self._put("status"))

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
            info = query_info(self.session, sensor, timeout=1.0)
        except TensorTouchError as exc:
            log.info("no info from %s (%s): nominal dome", sensor, exc)
            return nominal_surface()
        geo = info.get("gel_surface") or nominal_surface()
        geo = {**geo, "finger": info.get("finger"), "model": info.get("model")}
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
        out = frame_view(fields, contacts, channel, grid)
        out["status"] = _status_view(status)
        return out

    def close(self) -> None:
        self.sub.close()


def make_handler(state: ViewState):
    page, policy = page_and_policy()

    class Handler(BaseHTTPRequestHandler):
        timeout = HTTP_IDLE_S                       # socket timeout: idle keep-alive connections end

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
                    self._json(out if out is not None else {"error": f"no fields from {q['sensor']} yet"},
                               200 if out is not None else 404)
                else:
                    self._json({"error": f"no route {url.path}"}, 404)
            except KeyError as exc:
                self._json({"error": f"missing or unknown parameter: {exc}"}, 400)
            except BrokenPipeError:
                pass

    return Handler


def _plain(obj):
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")


def serve(state: ViewState, host: str = "127.0.0.1", port: int = 8765) -> ThreadingHTTPServer:
    """Start the HTTP server in a daemon thread; returns it (`.server_address`, `.shutdown()`)."""
    httpd = ThreadingHTTPServer((host, port), make_handler(state))
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, name="view-http", daemon=True).start()
    return httpd
