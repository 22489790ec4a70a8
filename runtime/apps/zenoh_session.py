"""Where TensorTouch processes meet on Zenoh, and how each command opens its session (docs/wire.md).

One meeting point: a sensor (`run`, `hand`, `Publisher`) listens on `default_endpoint()`,
a subscriber (`listen`, `view`, `Subscriber`) connects there. The default is loopback only,
`tcp/127.0.0.1:7447`; the `TENSORTOUCH_ENDPOINT` environment variable moves it.

Nothing listens where it was not told to: a session that is given no `listen` endpoint listens
nowhere (Zenoh's own default would be every interface on a random port), multicast and gossip
scouting are off unless asked for, and a subscriber opens a peer session that only connects out.
`--zenoh-config FILE` loads Zenoh's own JSON5 configuration (TLS, access control, ...); explicit
`--listen` / `--connect` then replace its endpoints.
"""
from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from ...contracts.errors import TensorTouchError

if TYPE_CHECKING:       # zenoh is imported where a session is configured, not when a parser is built
    import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
ENDPOINT_ENV = "TENSORTOUCH_ENDPOINT"
ROLES = ("sensor", "subscriber")


def default_endpoint() -> str:
    """The meeting point of run/hand (listen there) and listen/view (connect there)."""
    return os.environ.get(ENDPOINT_ENV) or DEFAULT_ENDPOINT


def zenoh_config(mode: str = "peer", listen: Sequence[str] = (), connect: Sequence[str] = (),
                 multicast: bool = False) -> zenoh.Config:
    """A zenoh.Config from plain arguments (endpoints like `tcp/127.0.0.1:7447`).

    It listens exactly on `listen` (nowhere when empty), connects to `connect`, and scouts
    (multicast and gossip) only when `multicast` is true."""
    import zenoh

    if mode not in ("peer", "client", "router"):
        raise TensorTouchError(f"zenoh mode {mode!r}: expected 'peer', 'client' or 'router'")
    cfg = zenoh.Config()
    try:
        cfg.insert_json5("mode", json.dumps(mode))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
        cfg.insert_json5("scouting/gossip/enabled", json.dumps(bool(multicast)))
        cfg.insert_json5("listen/endpoints", json.dumps([str(e) for e in listen]))
        cfg.insert_json5("connect/endpoints", json.dumps([str(e) for e in connect]))
    except zenoh.ZError as exc:
        raise TensorTouchError(f"zenoh config (listen={list(listen)}, connect={list(connect)}): "
                               f"{exc}") from None
    return cfg


def load_zenoh_config(path: str | os.PathLike, *, listen: Sequence[str] = (),
                      connect: Sequence[str] = ()) -> zenoh.Config:
    """Zenoh's own JSON5 config file; non-empty `listen` / `connect` replace its endpoints."""
    import zenoh

    path = Path(path)
    if not path.is_file():
        raise TensorTouchError(f"{path}: no such Zenoh config file (expected Zenoh's JSON5 configuration)")
    try:
        cfg = zenoh.Config.from_file(str(path))
        if listen:
            cfg.insert_json5("listen/endpoints", json.dumps([str(e) for e in listen]))
        if connect:
            cfg.insert_json5("connect/endpoints", json.dumps([str(e) for e in connect]))
    except zenoh.ZError as exc:
        raise TensorTouchError(f"{path}: not a valid Zenoh config ({_zerror(exc)})") from None
    return cfg


def session_config(role: str, *, listen: Sequence[str] = (), connect: Sequence[str] = (),
                   config_file: str | os.PathLike | None = None,
                   multicast: bool = False) -> zenoh.Config:
    """The config a `role` ('sensor' or 'subscriber') opens with.

    With a `config_file`, that file (endpoints replaced by non-empty `listen`/`connect`).
    Without one and with no endpoint, the meeting point: a sensor listens there, a subscriber
    connects there."""
    if role not in ROLES:
        raise ValueError(f"role {role!r}: expected one of {ROLES}")
    if config_file is not None:
        return load_zenoh_config(config_file, listen=listen, connect=connect)
    listen, connect = list(listen), list(connect)
    if not listen and not connect:
        (listen if role == "sensor" else connect).append(default_endpoint())
    return zenoh_config("peer", listen=listen, connect=connect, multicast=multicast)


def open_session(config: zenoh.Config | None = None, *, listen: Sequence[str] = (),
                 connect: Sequence[str] = (), role: str = "sensor",
                 config_file: str | os.PathLike | None = None,
                 multicast: bool = False) -> zenoh.Session:
    """Open a zenoh session from a Config, a config file or endpoints, with a one-line error."""
    import zenoh

    if config is None:
        config = session_config(role, listen=listen, connect=connect, config_file=config_file,
                                multicast=multicast)
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        where = f"config {config_file}, " if config_file else ""
        raise TensorTouchError(f"cannot open zenoh session ({where}listen={_endpoints(config, 'listen')}, "
                               f"connect={_endpoints(config, 'connect')}): {_zerror(exc)}") from None


def release(step: Callable[[], object], what: str, log: logging.Logger) -> None:
    """One step of letting go of Zenoh at shutdown (an undeclare, a session close). A session or
    peer that is already gone may refuse it; that is logged at debug level as `what: error`."""
    try:
        step()
    except Exception as exc:  # noqa: BLE001 - nothing left to do for an entity that is gone
        log.debug("%s: %s", what, exc)


def _zerror(exc: Exception) -> str:
    """A Zenoh error on one line, without the Rust source location it carries."""
    text = " ".join(str(exc).split())
    return re.sub(r"\s+at /\S+\.rs:\d+\.?", "", text).strip()


def _endpoints(config: zenoh.Config, which: str) -> str:
    try:
        return config.get_json(f"{which}/endpoints")
    except Exception:  # noqa: BLE001 - only for an error message
        return "?"


def add_zenoh_options(parser, role: str) -> None:
    """--listen / --connect / --zenoh-config / --multicast, the same on every command."""
    if role not in ROLES:
        raise ValueError(f"role {role!r}: expected one of {ROLES}")
    meet = f"{DEFAULT_ENDPOINT}, or ${ENDPOINT_ENV}"
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help="Zenoh endpoint to listen on, repeatable" +
                             (f" (default: {meet})" if role == "sensor" else " (default: none)"))
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        help="Zenoh endpoint to connect to, repeatable" +
                             (f" (default: {meet})" if role == "subscriber" else " (default: none)"))
    parser.add_argument("--zenoh-config", metavar="FILE",
                        help="Zenoh's own JSON5 config (TLS, access control; docs/wire.md#security); "
                             "--listen/--connect replace its endpoints")
    parser.add_argument("--multicast", action="store_true",
                        help="find peers by multicast and gossip scouting (default: off)")


def config_from_args(args, role: str) -> zenoh.Config:
    """The config a command's add_zenoh_options arguments describe."""
    return session_config(role, listen=args.listen, connect=args.connect,
                          config_file=args.zenoh_config, multicast=args.multicast)


def session_from_args(args, role: str) -> zenoh.Session:
    """Open the session a command's add_zenoh_options arguments describe."""
    return open_session(listen=args.listen, connect=args.connect, role=role,
                        config_file=args.zenoh_config, multicast=args.multicast)


def describe(args, role: str) -> str:
    """Where a command's session listens/connects, for its start-up line."""
    if args.zenoh_config:
        extra = " ".join(args.listen + args.connect)
        return f"config {args.zenoh_config}" + (f" {extra}" if extra else "")
    if not args.listen and not args.connect:
        verb = "listen" if role == "sensor" else "connect"
        return f"{verb} {default_endpoint()}"
    parts = [f"listen {e}" for e in args.listen] + [f"connect {e}" for e in args.connect]
    return ", ".join(parts)
