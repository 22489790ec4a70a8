"""`tensortouch view`: subscribe over Zenoh and serve a live page on http://127.0.0.1:PORT/."""
from __future__ import annotations

import logging
import sys
import time

from ...runtime.apps.zenoh_session import add_zenoh_options, describe, session_from_args

log = logging.getLogger(__name__)


def register(sub) -> None:
    p = sub.add_parser("view", help="live web view of published fields and contacts (127.0.0.1)",
                       description="Subscribe to sensors over Zenoh and serve a local page showing each "
                                   "field channel as a colour map with units, the contacts on the image "
                                   "and on a 3D gel view.")
    p.add_argument("sensor", nargs="?", default="*", help="sensor id, or * for every sensor (default)")
    add_zenoh_options(p, "subscriber")
    p.add_argument("--host", default="127.0.0.1", help="HTTP address (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=8765, help="HTTP port (default 8765; 0: any free port)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--rerun", action="store_true",
                   help="show the sensors in a Rerun web viewer (viewers extra) served on --host:--port "
                        "instead of the built-in page")
    p.add_argument("--rerun-grpc-port", type=int, default=9876, metavar="PORT",
                   help="gRPC port of the Rerun server, also bound to --host (default 9876)")
    p.set_defaults(func=cmd_view)


def cmd_view(args) -> int:
    from .server import ViewState, serve

    if getattr(args, "rerun", False):
        from ...contracts.extras import require

        require("viewers")
        from ..viewers.rerun_live import run_rerun_view

        return run_rerun_view(args)
    session = session_from_args(args, "subscriber")
    state = ViewState(session, args.sensor)
    httpd = serve(state, args.host, args.port)
    host, port = httpd.server_address[:2]
    print(f"tensortouch view: http://{host}:{port}/  (Zenoh {describe(args, 'subscriber')}, "
          f"sensor {args.sensor}); Ctrl-C to stop", file=sys.stderr)
    t0 = time.monotonic()
    try:
        while args.duration is None or time.monotonic() - t0 < args.duration:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        httpd.shutdown()
        state.close()
        session.close()
    return 0

