"""No command listens beyond what it was given: the listening TCP sockets and bound UDP sockets of
real processes (`run`, `listen`, `view`, the Subscriber and Publisher libraries), read from /proc the
way `ss -ltnup` does. Real Zenoh on loopback.
"""
import os
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from tensortouch.tools.bench.models import write_difference_package

from tests.conftest import dome_calibration
from tests.test_e2e_runtime import (
    SENSOR,
    SIZE,
    H,
    W,
    free_port,
    stop,
    write_poke_session,
)

CLI = [sys.executable, "-m", "tensortouch.runtime.shells.cli"]
pytestmark = pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux /proc/net")


def _hexaddr(text: str) -> str:
    """'0100007F:1D27' (or the 32-hex-digit IPv6 form) -> '127.0.0.1:7463' / '[::1]:7463'."""
    addr, port = text.split(":")
    raw = bytes.fromhex(addr)
    if len(raw) == 4:
        host = socket.inet_ntop(socket.AF_INET, raw[::-1])
    else:
        host = "[" + socket.inet_ntop(socket.AF_INET6, b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4))) + "]"
    return f"{host}:{int(port, 16)}"


def sockets_of(pid: int) -> dict[str, set[str]]:
    """{'tcp_listen': {...}, 'udp': {...}} local addresses of the sockets process `pid` holds."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    out = {"tcp_listen": set(), "udp": set()}
    for table, kind in (("tcp", "tcp_listen"), ("tcp6", "tcp_listen"), ("udp", "udp"), ("udp6", "udp")):
        path = Path(f"/proc/{pid}/net/{table}")
        if not path.exists():
            continue
        for row in path.read_text().splitlines()[1:]:
            cols = row.split()
            if cols[9] not in inodes:
                continue
            if kind == "tcp_listen" and cols[3] != "0A":      # 0A = LISTEN
                continue
            out[kind].add(_hexaddr(cols[1]))
    return out


def _settle(proc: subprocess.Popen, seconds: float = 2.0) -> dict[str, set[str]]:
    time.sleep(seconds)
    assert proc.poll() is None, proc.communicate(timeout=5)
    return sockets_of(proc.pid)


def _env(endpoint: str) -> dict:
    return dict(os.environ, PYTHONUNBUFFERED="1", TENSORTOUCH_ENDPOINT=endpoint)


def _wait_stderr(proc: subprocess.Popen, needle: str, timeout: float = 120) -> str:
    text, t0 = "", time.monotonic()
    while time.monotonic() - t0 < timeout:
        line = proc.stderr.readline()
        if not line:
            break
        text += line
        if needle in line:
            return text
    raise AssertionError(f"{needle!r} never printed:\n{text[-2000:]}")


def test_run_listens_on_its_endpoint_only_and_listen_nowhere(tmp_path):
    session = write_poke_session(tmp_path / "session")
    write_difference_package(tmp_path / "models" / "difference-32", SIZE)
    dome_calibration(tmp_path / "calib", SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    port = free_port()
    env = _env(f"tcp/127.0.0.1:{port}")          # run and listen use the default meeting point
    env.update(TENSORTOUCH_CALIBRATION=str(tmp_path / "calib"), TENSORTOUCH_MODELS=str(tmp_path / "models"))
    run = subprocess.Popen(CLI + ["run", "--source", f"replay:{session}", "--loop"], env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    listen = None
    try:
        _wait_stderr(run, "Ctrl-C to stop")
        listen = subprocess.Popen(CLI + ["listen", "--timeout", "30"], env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        assert listen.stdout.readline().startswith("tensortouch/"), "listen received nothing"
        got_run, got_listen = sockets_of(run.pid), sockets_of(listen.pid)
    finally:
        if listen is not None:
            listen.kill()
            listen.wait(10)
        stop(run)
    assert got_run["tcp_listen"] == {f"127.0.0.1:{port}"}, got_run
    assert got_listen["tcp_listen"] == set(), got_listen
    for got in (got_run, got_listen):          # no multicast scouting socket (224.0.0.224:7446)
        assert not any(a.endswith(":7446") for a in got["udp"]), got


def test_view_listens_on_its_http_port_only(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    http = free_port()
    view = subprocess.Popen(CLI + ["view", "--port", str(http), "--duration", "30"], env=_env(endpoint),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _wait_stderr(view, "Ctrl-C to stop", 60)
        got = _settle(view)
    finally:
        view.kill()
        view.wait(10)
    assert got["tcp_listen"] == {f"127.0.0.1:{http}"}, got
    assert not any(a.endswith(":7446") for a in got["udp"]), got


@pytest.mark.parametrize("code, expected", [
    ("from tensortouch.runtime.apps.subscriber import Subscriber; s = Subscriber('*')", set()),
    ("from tensortouch.runtime.apps.subscriber import Subscriber; s = Subscriber('dome01', connect=['tcp/127.0.0.1:1'])", set()),
    ("from tensortouch.runtime.apps.publisher import Publisher; p = Publisher('dome01')", {"ENDPOINT"}),
    ("from tensortouch.runtime.apps.publisher import Publisher; p = Publisher('dome01', connect=['tcp/127.0.0.1:1'])", set()),
], ids=["subscriber-default", "subscriber-connect", "publisher-default", "publisher-connect"])
def test_library_sessions_listen_only_where_told(code, expected):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-c", textwrap.dedent(code) + "\nprint('up', flush=True)\n"
                             "import time; time.sleep(30)"], env=_env(endpoint),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline() == "up\n", proc.stderr.read() if proc.poll() is not None else ""
        got = _settle(proc, 1.5)
    finally:
        proc.kill()
        proc.wait(10)
    want = {f"127.0.0.1:{port}"} if expected else set()
    assert got["tcp_listen"] == want, got
    assert not any(a.endswith(":7446") for a in got["udp"]), got
