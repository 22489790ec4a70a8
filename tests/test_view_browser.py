"""`tensortouch view` in headless Chromium while a hostile publisher puts script into every string field
it can (status members, flags, field channel names, units, clipped list, sensor ids). Real Zenoh on
loopback, the real view server, real Chromium. No injected code may run: it would change
`document.title` and call a local "canary" HTTP server; the page must still show the genuine sensor.
A control page that does use innerHTML on the same payload proves the payload and the canary work.
"""
import json
import shutil
import subprocess
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest
import zenoh
from tensortouch.contracts import wire
from tensortouch.runtime.apps.publisher import Publisher
from tensortouch.runtime.apps.zenoh_session import open_session, zenoh_config

from tests.test_listen import CONTACT, free_endpoint

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (Debian package `chromium`)")


class Canary:
    """A local HTTP server that counts every request injected code makes to it."""

    def __init__(self):
        self.hits: list[str] = []
        canary = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_GET(self):  # noqa: N802 - http.server API
                canary.hits.append(self.path)
                if self.path.startswith("/control"):
                    body = CONTROL_PAGE.replace("PAYLOAD", json.dumps(canary.payload).replace("</", "<\\/")).encode()
                    self.send_response(200)
                    self.send_header("Content-Type", "text/html")
                else:
                    body = b"{}"
                    self.send_response(200)
                    self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.httpd.server_address[1]
        self.payload = payload(self.port)
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def injected_hits(self) -> list[str]:
        return [h for h in self.hits if h.startswith("/hit")]


def payload(port: int) -> str:
    js = f"document.title='PWNED';fetch('http://127.0.0.1:{port}/hit');window.pwned=1"
    return (f"<img src=x onerror=\"{js}\"><script>{js}</script>"
            f"<svg onload=\"{js}\"></svg>\"'><iframe srcdoc=\"<script>parent.{js}</script>\"></iframe>")


CONTROL_PAGE = """<!doctype html><html><head><title>control</title></head><body><div id=d></div>
<script>document.getElementById("d").innerHTML = PAYLOAD;</script></body></html>"""


def chromium_dom(url: str, tmp_path, budget_ms: int = 6000) -> str:
    profile = tmp_path / f"chromium-{time.monotonic_ns()}"
    r = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                        "--disable-component-update", "--no-first-run", f"--user-data-dir={profile}",
                        f"--virtual-time-budget={budget_ms}", "--timeout=30000", "--dump-dom", url],
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


def _hostile(session: zenoh.Session, evil: str, stop: threading.Event) -> None:
    """Publishes under valid ids with script in every string, and under ids that are script."""
    sid = "aaa-hostile"                                   # sorts first: the page shows it by default
    channels = ["fn_z"] + [f"{evil}{i}" for i in range(14)]
    units = [evil] * 15
    data = np.linspace(-1, 1, 15 * 8 * 8).astype(np.float16).reshape(15, 8, 8)
    enc = {k: zenoh.Encoding(v) for k, v in wire.ENCODINGS.items()}
    seq = 0
    while not stop.is_set():
        for key_id in (sid, evil[:40].replace("/", ""), "x<script>y"):
            head = {"schema": wire.SCHEMAS["fields"], "sensor_id": key_id, "seq": seq,
                    "t": 0.5, "shape": [15, 8, 8], "dtype": wire.FIELDS_DTYPE, "channels": channels, "units": units,
                    "clipped": [evil]}
            status = {"schema": wire.SCHEMAS["status"], "sensor_id": key_id, "seq": seq, "t": 0.5, "state": evil,
                      "flags": [evil, evil], "timings_ms": {evil: 1.0}, "fps": evil, "finger": evil, "hand": evil,
                      "calibration_version": evil, "model": evil}
            contacts = {"schema": wire.SCHEMAS["contacts"], "sensor_id": key_id, "seq": seq, "t": 0.5,
                        "contacts": [{**CONTACT.to_dict(), "id": 7}]}
            try:
                session.put(f"tensortouch/{key_id}/fields", data.tobytes(), encoding=enc["fields"],
                            attachment=json.dumps(head))
                session.put(f"tensortouch/{key_id}/status", json.dumps(status), encoding=enc["status"])
                session.put(f"tensortouch/{key_id}/contacts", json.dumps(contacts), encoding=enc["contacts"])
            except zenoh.ZError:
                pass                                       # zenoh itself refuses some keys: fine
        seq += 1
        time.sleep(0.05)


def test_view_escapes_everything_a_hostile_publisher_sends(tmp_path):
    from tensortouch.tools.view.server import ViewState, serve

    canary = Canary()
    evil = canary.payload
    # the control: the same payload through innerHTML does run in this Chromium, and the canary sees it
    control = chromium_dom(f"http://127.0.0.1:{canary.port}/control", tmp_path, 3000)
    assert canary.injected_hits() and "<title>PWNED</title>" in control, "control payload did not run"
    canary.hits.clear()

    ep = free_endpoint()
    stop = threading.Event()
    genuine = Publisher("genuine-1", listen=[ep], info=lambda: {"model": "tiny"})
    hostile = zenoh.open(zenoh_config("client", connect=[ep]))     # the sensor relays a client's puts
    fields = np.linspace(-1, 1, 15 * 16 * 16, dtype=np.float32).reshape(15, 16, 16)

    def genuine_loop():
        seq = 0
        while not stop.is_set():
            genuine.publish_fields(fields, seq, 0.1 * seq)
            genuine.publish_contacts([CONTACT], seq, 0.1 * seq)
            genuine.publish_status({"state": "stable", "fps": 20.0, "timings_ms": {}}, seq, 0.1 * seq)
            seq += 1
            time.sleep(0.05)

    threads = [threading.Thread(target=genuine_loop, daemon=True),
               threading.Thread(target=_hostile, args=(hostile, evil, stop), daemon=True)]
    for th in threads:
        th.start()
    session = open_session(connect=[ep], role="subscriber")
    state = ViewState(session)
    httpd = serve(state, "127.0.0.1", 0)
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and {"aaa-hostile", "genuine-1"} - {s["sensor_id"] for s in state.sensors()}:
            time.sleep(0.1)
        assert {s["sensor_id"] for s in state.sensors()} == {"aaa-hostile", "genuine-1"}, state.sensors()
        dom = chromium_dom(f"http://127.0.0.1:{httpd.server_address[1]}/", tmp_path)
    finally:
        stop.set()
        for th in threads:
            th.join(5)
        httpd.shutdown()
        state.close()
        session.close()
        hostile.close()
        genuine.close()
    assert canary.injected_hits() == [], canary.hits
    assert "<title>TensorTouch view</title>" in dom and "PWNED" not in dom.split("</title>")[0]
    assert '<option value="genuine-1">genuine-1</option>' in dom, dom[:3000]
    # the hostile strings are on the page, as text only
    assert "&lt;img src=x onerror=" in dom and "<img src=\"x\"" not in dom and "<svg" not in dom
    assert "<iframe" not in dom


def test_3d_view_is_right_handed_and_arrows_point_along_the_force(tmp_path):
    """The page's own `project` in Chromium: sensor x, y, z map to a right-handed screen frame
    (right, up, toward the viewer), so the gel is not drawn mirrored, and a force arrow (tail at
    p - s·F, head at p) points along F on screen."""
    from tensortouch.tools.view.server import PAGE

    probe = """<script>
    const J = [[1,0,0],[0,1,0],[0,0,1]].map(e => { const a = project(e, 460), o = project([0,0,0], 460);
      return [a[0] - o[0], -(a[1] - o[1]), a[2] - o[2]]; });          // screen right, up, toward
    const det = J[0][0]*(J[1][1]*J[2][2]-J[1][2]*J[2][1]) - J[0][1]*(J[1][0]*J[2][2]-J[1][2]*J[2][0])
              + J[0][2]*(J[1][0]*J[2][1]-J[1][1]*J[2][0]);
    const p = [3, 0, 14], F = [1, 0, -2], s = 8, tail = project(p.map((v, j) => v - s * F[j]), 460),
          head = project(p, 460), px = project([4, 0, 14], 460), pz = project([3, 0, 13], 460), o = head;
    const dot = (a, b) => (a[0] - o[0]) * b[0] + (a[1] - o[1]) * b[1];
    const along = [head[0] - tail[0], head[1] - tail[1]];
    document.title = JSON.stringify({det: det, alongX: dot(px, along) > 0, alongMinusZ: dot(pz, along) > 0});
    </script></body>"""
    page = tmp_path / "probe.html"
    page.write_text(PAGE.read_text().replace("</body>", probe))
    dom = chromium_dom(page.as_uri(), tmp_path, 2000)
    got = json.loads(dom.split("<title>")[1].split("</title>")[0].replace("&quot;", '"'))
    assert got["det"] > 0, got                        # right-handed (a mirrored projection gives < 0)
    assert got["alongX"] and got["alongMinusZ"], got
