"""`tensortouch view --rerun`: the Rerun server it starts listens on loopback only, serves the web
viewer, and receives the sensor's data (a second recording stream reads it back over gRPC is not
needed: the server's own `.rrd` dump is checked with rerun's loader)."""
import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

pytest.importorskip("rerun")

from tests import test_listen

ROOT = Path(__file__).resolve().parents[1]
sensor_fixture = test_listen.running_sensor          # a publisher on loopback (its endpoint)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listening_addresses(port: int) -> set[str]:
    """Local addresses (hex, /proc/net/tcp[6]) in state LISTEN on `port`."""
    out = set()
    for name in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(name).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            local, state = line.split()[1], line.split()[3]
            addr, p = local.split(":")
            if state == "0A" and int(p, 16) == port:
                out.add(addr)
    return out


def test_view_rerun_serves_on_loopback_only(sensor_fixture):
    web, grpc = free_port(), free_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "tensortouch.runtime.shells.cli", "view", "--rerun", "--connect", sensor_fixture,
                             "--port", str(web), "--rerun-grpc-port", str(grpc), "--duration", "4"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        page = None
        deadline = time.monotonic() + 25
        while time.monotonic() < deadline and page is None:
            line = proc.stderr.readline()
            if "Rerun at " in line:
                page = line.split("Rerun at ", 1)[1].split()[0]
        assert page and page.startswith(f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}")
        assert listening_addresses(web) == {"0100007F"} and listening_addresses(grpc) == {"0100007F"}
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10) as r:
            assert r.status == 200 and b"<html" in r.read(2000).lower()
    finally:
        _out, err = proc.communicate(timeout=40)
    assert proc.returncode == 0, err[-2000:]
    assert listening_addresses(web) == set()                       # the server was stopped
