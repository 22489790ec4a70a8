"""`tensortouch hand CONFIG`: the command-line shell around runtime.apps.hand.Hand (docs/hand.md)."""
from __future__ import annotations

import time

from ..apps.zenoh_session import add_zenoh_options, default_endpoint


def register_hand(sub) -> None:
    p = sub.add_parser("hand", help="run a whole hand: several fingertip sensors in one process",
                       description="Serve every sensor of a hand config (docs/hand.md) over one Zenoh "
                                   "session, with an optional CAN summary.")
    p.add_argument("config", help="hand config TOML")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--fast", action="store_true", help="replays: as fast as possible")
    p.add_argument("--loop", action="store_true", help="replays: start over at the end")
    add_zenoh_options(p, "sensor")      # given here, they override the config's [zenoh] table
    p.set_defaults(func=cmd_hand, handles_stop_signals=True)


def cmd_hand(args) -> int:
    """Runs until every finger's source ended, --duration passed, or SIGTERM/SIGINT: both stop the hand
    cleanly (fingers joined, publishers undeclared, Zenoh session closed) and exit 0, also when they
    arrive while the hand is still starting."""
    import signal
    import threading

    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *a: stop.set()) for s in (signal.SIGTERM, signal.SIGINT)}
    if getattr(args, "pending_signals", None):     # came while `tensortouch` was still starting
        stop.set()
    try:
        return _serve(args, stop)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _serve(args, stop) -> int:
    import dataclasses
    import sys

    from ..apps.hand import Hand
    from ..apps.hand_config import load_hand_config

    cfg = load_hand_config(args.config)
    cam = dict(cfg.camera_options)
    if args.fast:
        cam["realtime"] = False
    if args.loop:
        cam["loop"] = True
    changes = {"camera_options": cam}
    if args.listen:
        changes["listen"] = tuple(args.listen)
    if args.connect:
        changes["connect"] = tuple(args.connect)
    if args.zenoh_config:
        changes["zenoh_config"] = args.zenoh_config
    if args.multicast:
        changes["multicast"] = True
    cfg = dataclasses.replace(cfg, **changes)
    hand = Hand(cfg)
    hand.stop_event = stop          # a signal during start-up stops the fingers before they run
    print(f"tensortouch hand {cfg.name}: {len(hand.fingers)} finger(s), model {hand.package.name} "
          f"({cfg.precision}), Zenoh {' '.join(cfg.listen + cfg.connect) or 'listen ' + default_endpoint()}"
          f"{' config ' + cfg.zenoh_config if cfg.zenoh_config else ''}"
          f"{', CAN ' + cfg.can.interface + ':' + cfg.can.channel if cfg.can else ''}; Ctrl-C to stop",
          file=sys.stderr)
    t0 = time.monotonic()
    try:
        if not stop.is_set():
            hand.start()
        while not stop.is_set():
            if hand.wait(0.5):
                break
            if args.duration and time.monotonic() - t0 >= args.duration:
                break
    finally:
        summary = hand.summary()
        hand.stop()
    for name, s in summary.items():
        p50, p99 = s["p50_ms"] or 0.0, s["p99_ms"] or 0.0
        print(f"  {name:<8} {s['sensor_id']:<16} {s['state']:<11} {s['frames']:6d} frames  "
              f"p50 {p50:6.2f} ms  p99 {p99:6.2f} ms  reconnects {s['reconnects']}  flags {s['flags']}",
              file=sys.stderr)
    # fingers joined, publishers undeclared, Zenoh session and CAN closed: the `tensortouch` shell may
    # end the process now, before Zenoh's and OpenCV's native threads meet interpreter finalization
    args.exit_without_finalizing = True
    return 0
