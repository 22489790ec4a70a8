"""`tensortouch view --rerun`: stream every sensor's messages into a Rerun web viewer on this machine.

Starts rerun-sdk's own server (`rerun --serve-web`) bound to the view's `--host` (127.0.0.1 by default:
Rerun itself would listen on every interface), subscribes over Zenoh and logs what arrives through
tools/viewers/rerun_saver.py. The page is `http://<host>:<port>/?url=rerun+http://<host>:<grpc>/proxy`.
"""
from __future__ import annotations

import logging
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import time
from urllib.parse import quote

from ...contracts.errors import TensorTouchError

log = logging.getLogger(__name__)

KINDS = ("fields", "contacts", "wrench", "status")
FIELDS_MIN_INTERVAL_S = 0.1            # live view: at most 10 field tensors per second and sensor


def start_server(host: str, grpc_port: int, web_port: int, timeout: float = 20.0):
    """A `rerun --serve-web` process bound to `host`; returns (process, gRPC url, web page url)."""
    exe = shutil.which("rerun")
    cmd = ([exe] if exe else [sys.executable, "-m", "rerun"]) + [
        "--serve-web", "--bind", host, "--port", str(grpc_port), "--web-viewer-port", str(web_port),
        "--server-memory-limit", "512MiB"]
    # its own process group: the `rerun` launcher runs the viewer binary as a child, and both must stop
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise TensorTouchError(f"rerun server exited ({proc.returncode}): {proc.stderr.read()[-500:]}")
        try:
            with socket.create_connection((host, grpc_port), timeout=0.5), \
                    socket.create_connection((host, web_port), timeout=0.5):
                break
        except OSError:
            time.sleep(0.2)
    else:
        stop_server(proc)
        raise TensorTouchError(f"rerun server did not open {host}:{grpc_port} and {host}:{web_port} "
                               f"within {timeout:.0f} s")
    grpc_url = f"rerun+http://{host}:{grpc_port}/proxy"
    return proc, grpc_url, f"http://{host}:{web_port}/?url={quote(grpc_url, safe='')}"


def stop_server(proc) -> None:
    """Stop the server's process group (the launcher and the binary it started)."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        proc.poll()                             # reap the launcher
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def run_rerun_view(args) -> int:
    from ...runtime.apps.subscriber import Subscriber, query_info, queued_callbacks
    from ...runtime.apps.zenoh_session import config_from_args, describe
    from .rerun_saver import RerunSaver

    def stop_on_sigterm(*_):
        raise KeyboardInterrupt              # so the server started below is stopped too

    previous = signal.signal(signal.SIGTERM, stop_on_sigterm)
    proc, grpc_url, page = start_server(args.host, args.rerun_grpc_port, args.port)
    inbox, callbacks = queued_callbacks(KINDS)     # the logger may fall behind: drop, never stall zenoh
    saver = RerunSaver(grpc_url=grpc_url, fields_min_interval_s=FIELDS_MIN_INTERVAL_S)
    described: set[str] = set()
    print(f"tensortouch view: Rerun at {page}  (Zenoh {describe(args, 'subscriber')}, "
          f"sensor {args.sensor}); Ctrl-C to stop", file=sys.stderr, flush=True)
    t0 = time.monotonic()
    try:
        with Subscriber(args.sensor, zenoh_config=config_from_args(args, "subscriber"),
                        **callbacks) as sub:
            while args.duration is None or time.monotonic() - t0 < args.duration:
                try:
                    kind, msg = inbox.get(timeout=0.2)
                except queue.Empty:
                    continue
                sid = msg["sensor_id"] if isinstance(msg, dict) else msg.sensor_id
                if sid not in described:
                    described.add(sid)
                    try:
                        saver.on_info(query_info(sub, sid))
                    except TensorTouchError as exc:
                        log.warning("sensor %s: no info (no dome in the view): %s", sid, exc)
                saver.save(kind, msg)
    except KeyboardInterrupt:
        pass
    finally:
        saver.close()
        stop_server(proc)
        signal.signal(signal.SIGTERM, previous)
    return 0
