"""Shell of `tensortouch view`: a Zenoh subscriber + a small HTTP server on 127.0.0.1.

The page (page.html, plain canvas, no JS libraries) polls `/api/frame` and draws the chosen field
channel as a colour map with its unit and range, the contacts on the image, and a 3D view of the
gel surface coloured by the same channel and deformed by the displacement field. Gel geometry
comes from the sensor's info queryable (`gel_surface`, published by `tensortouch hand`); a
sensor that does not publish it is drawn on the nominal dome (said on the page).

Routes: `/` page, `/api/sensors`, `/api/frame?sensor=ID&channel=NAME`, `/api/geometry?sensor=ID`,
`/api/lut`. Everything is JSON; the colour map image travels as base64 PNG inside it.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np

from tools.view.render import frame_view, lut_json

log = logging.getLogger(__name__)

PAGE = Path(__file__).with_name("page.html")
NOMINAL_GRID = 24
NOMINAL_THETA_EDGE_RAD = np.deg2rad(100.0)


def nominal_surface(grid: int = NOMINAL_GRID) -> dict:
    """Ideal equidistant fisheye onto the default dome (runtime.geometry), for sensors without info."""
    from runtime.geometry import DomeProfile, equidistant_theta_phi, surface_tables

    theta, phi = equidistant_theta_phi((grid, grid), NOMINAL_THETA_EDGE_RAD)
    t = surface_tables(theta, phi, DomeProfile())
    xyz = np.nan_to_num(t["surface_xyz"])
    return {"grid": [grid, grid], "xyz_mm": np.round(xyz, 3).ravel().tolist(),
            "mask": [bool(v) for v in np.asarray(t["mask"]).ravel()], "nominal": True}


class ViewState:
    """Latest fields / contacts / status per sensor, fed by a runtime Subscriber."""

    def __init__(self, session, sensor: str = "*"):
        from runtime.subscriber import Subscriber

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
            with self.lock:
                store[sid] = msg
                self.received[sid] = time.monotonic()
        return cb

    def sensors(self) -> list[dict]:
        with self.lock:
            ids = sorted(set(self.fields) | set(self.status) | set(self.contacts))
            now = time.monotonic()
            return [{"sensor_id": s, "has_fields": s in self.fields,
                     "age_s": round(now - self.received.get(s, now), 2),
                     "status": {k: self.status[s].get(k) for k in ("state", "flags", "fps", "calibration_version",
                                                                  "model", "finger", "hand")} if s in self.status else None}
                    for s in ids]

    def geometry(self, sensor: str) -> dict:
        if sensor in self._geometry:
            return self._geometry[sensor]
        from runtime.errors import TensorTouchError
        from runtime.subscriber import query_info

        try:
            info = query_info(self.session, sensor, timeout=1.0)
        except TensorTouchError as exc:
            log.info("no info from %s (%s): nominal dome", sensor, exc)
            return nominal_surface()
        geo = info.get("gel_surface") or nominal_surface()
        geo = {**geo, "finger": info.get("finger"), "model": info.get("model")}
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
        out["status"] = status
        return out

    def close(self) -> None:
        self.sub.close()


def make_handler(state: ViewState):
    class Handler(BaseHTTPRequestHandler):
        def log_message(self, fmt, *args):          # quiet: one line per request is too much at 15 Hz
            log.debug(fmt, *args)

        def _send(self, code: int, body: bytes, ctype: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _json(self, obj, code: int = 200) -> None:
            self._send(code, json.dumps(obj, allow_nan=False, default=_plain).encode(), "application/json")

        def do_GET(self):  # noqa: N802 - http.server API
            url = urlparse(self.path)
            q = {k: v[0] for k, v in parse_qs(url.query).items()}
            try:
                if url.path in ("/", "/index.html"):
                    self._send(200, PAGE.read_bytes(), "text/html; charset=utf-8")
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
