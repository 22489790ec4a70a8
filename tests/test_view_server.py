"""`tensortouch view` server (tools/view/server.py): the page's JSON API fed by a real hand over real
Zenoh."""
import base64
import json
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from tests.hand_util import free_endpoint, hand_cfg, make_package, make_store, make_video, wait_until


def _get(url):
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return r.status, r.headers.get("Content-Type"), r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers.get("Content-Type"), exc.read()


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    from tensortouch.runtime.apps.hand import Hand
    from tensortouch.runtime.apps.publisher import open_session
    from tensortouch.tools.view.server import ViewState, serve

    tmp = tmp_path_factory.mktemp("view")
    pkg = make_package(tmp / "models" / "difference-32")
    make_store(tmp / "store", ["TT-A", "TT-B"])
    cfg = hand_cfg(tmp, pkg, {"TT-A": f"file:{make_video(tmp / 'a.avi')}",
                              "TT-B": f"file:{make_video(tmp / 'b.avi', seed=1, dx=-20)}"})
    hand = Hand(cfg).start()
    session = open_session(connect=list(cfg.listen))
    state = ViewState(session)
    httpd = serve(state, "127.0.0.1", 0)
    base = "http://127.0.0.1:%d" % httpd.server_address[1]
    try:
        yield base, state, hand
    finally:
        httpd.shutdown()
        state.close()
        session.close()
        hand.stop()


def test_page_and_sensor_list(live):
    base, state, hand = live
    code, ctype, body = _get(base + "/")
    assert code == 200 and ctype.startswith("text/html") and b"<canvas" in body
    assert wait_until(lambda: {s["sensor_id"] for s in json.loads(_get(base + "/api/sensors")[2])
                               if s["has_fields"]} == {"TT-A", "TT-B"}, 15)
    sensors = json.loads(_get(base + "/api/sensors")[2])
    assert all(s["status"]["state"] for s in sensors)
    # every status names its finger from the hand config (TT-A is f0, TT-B is f1)
    assert wait_until(lambda: {s["sensor_id"]: (s["status"] or {}).get("finger")
                               for s in json.loads(_get(base + "/api/sensors")[2])} == {"TT-A": "f0", "TT-B": "f1"}, 5)
    assert all(s["status"]["hand"] == "test-hand" for s in json.loads(_get(base + "/api/sensors")[2]))
    assert b"st.finger" in body                                          # the page shows it


def test_frame_api_colour_map_contacts_and_geometry(live):
    base, state, hand = live
    assert wait_until(lambda: state.contacts.get("TT-A") is not None and state.contacts["TT-A"].contacts, 20)
    code, _, body = _get(base + "/api/frame?sensor=TT-A&channel=fn_z")
    assert code == 200
    f = json.loads(body)
    img = cv2.imdecode(np.frombuffer(base64.b64decode(f["png"]), np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (32, 32, 3)
    assert f["unit"] == "MPa" and f["signed"] and f["vmin"] == -f["vmax"] and f["vmax"] > 0
    assert "traction_mag" in f["channels"] and "disp_z" in f["channels"]
    geo = json.loads(_get(base + "/api/geometry?sensor=TT-A")[2])
    assert not geo.get("nominal") and geo["finger"] == "f0"
    gh, gw = geo["grid"]
    assert len(geo["xyz_mm"]) == 3 * gh * gw and len(f["grid_values"]) == gh * gw
    z = np.array([v if v is not None else np.nan for v in geo["xyz_mm"]]).reshape(gh, gw, 3)[..., 2]
    assert np.nanmax(z) == pytest.approx(16.0, abs=0.5)                  # the dome's apex, mm
    code, _, body = _get(base + "/api/frame?sensor=TT-A&channel=disp_mag")
    assert code == 200 and json.loads(body)["unit"] == "mm"


def test_frame_api_errors(live):
    base, state, hand = live
    assert _get(base + "/api/frame?sensor=TT-A&channel=bogus")[0] == 400
    assert _get(base + "/api/frame?sensor=NOBODY&channel=fn_z")[0] == 404
    assert _get(base + "/api/frame")[0] == 400
    assert _get(base + "/nothing")[0] == 404


def test_sensor_without_geometry_gets_nominal_dome():
    from tensortouch.runtime.apps.publisher import Publisher, open_session
    from tensortouch.tools.view.server import ViewState

    ep = free_endpoint()
    with Publisher("plain-1", listen=[ep]) as pub:
        session = open_session(connect=[ep])
        state = ViewState(session)
        try:
            pub.publish_fields(np.zeros((15, 32, 32), np.float32), 1, 0.0)
            geo = state.geometry("plain-1")
            assert geo["nominal"] and geo["grid"] == [24, 24]
        finally:
            state.close()
            session.close()


def test_cli_registers_view():
    import argparse

    from tensortouch.tools.view.cli import register

    p = argparse.ArgumentParser()
    register(p.add_subparsers())
    a = p.parse_args(["view", "TT-A", "--port", "0", "--duration", "0.1"])
    assert a.host == "127.0.0.1" and a.sensor == "TT-A" and callable(a.func)


def test_view_command_serves_then_stops():
    import subprocess
    import sys
    from pathlib import Path

    from tests.hand_util import free_endpoint

    ep = free_endpoint()
    r = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", "view", "--connect", ep, "--port", "0", "--duration", "1"],
                       capture_output=True, text=True, timeout=60, cwd=Path(__file__).parents[1])
    assert r.returncode == 0, r.stderr
    assert "tensortouch view: http://127.0.0.1:" in r.stderr
