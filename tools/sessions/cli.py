"""`tensortouch session import|check` (entry point `session = "tools.sessions.cli:register"`).

    tensortouch session import BAG --map topics.toml --out DIR   # ROS1 .bag, ROS2 bag folder, .mcap
    tensortouch session check DIR                                # validate against the contract
"""
from __future__ import annotations

import logging

log = logging.getLogger(__name__)


def _import(args) -> int:
    from tools.sessions.bags import TopicMap, convert

    print(convert(args.bag, TopicMap.load(args.map), args.out))
    return 0


def _check(args) -> int:
    from runtime.session import load_session

    s = load_session(args.session)
    rows = {name: len(s.table(name)) for name in s.streams}
    print(f"{args.session}: OK, sensor {s.sensor_id}, rows {rows}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("session", help="import ROS/MCAP recordings as sessions; validate sessions")
    ssub = p.add_subparsers(dest="session_command", metavar="SESSION_COMMAND")
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
    i = ssub.add_parser("import", help="ROS1 .bag, ROS2 bag folder or .mcap -> session (topic map file)")
    i.add_argument("bag")
    i.add_argument("--map", required=True, help="topic map (JSON or TOML), see docs/session.md")
    i.add_argument("--out", required=True)
    i.set_defaults(func=_import)
    c = ssub.add_parser("check", help="validate a session directory (names the first problem)")
    c.add_argument("session")
    c.set_defaults(func=_check)

