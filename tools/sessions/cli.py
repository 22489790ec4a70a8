"""`tensortouch session import|check` (entry point `session = "tensortouch.tools.sessions.cli:register"`).

    tensortouch session import BAG --map topics.toml --out DIR   # ROS1 .bag, ROS2 bag folder, .mcap
    tensortouch session check DIR                                # validate against the contract
    tensortouch record --source usb:SERIAL [--ft serial:URL] [--mocap URL] --out DIR   # a session, no ROS
"""
from __future__ import annotations

import logging
import sys

from ..command_group import add_commands, arg, command_group

log = logging.getLogger(__name__)


def _import(args) -> int:
    from .bags import TopicMap, convert

    print(convert(args.bag, TopicMap.load(args.map), args.out))
    return 0


def _check(args) -> int:
    from ...contracts.session import load_session

    s = load_session(args.session)
    rows = {name: len(s.table(name)) for name in s.streams}
    print(f"{args.session}: OK, sensor {s.sensor_id}, rows {rows}")
    return 0


def _record(args) -> int:
    import signal
    import threading

    from ...contracts.errors import TensorTouchError
    from ...drivers.camera import camera_from_uri
    from ...drivers.gauge import ForceGauge, GaugeConfig
    from ...drivers.mocap import MocapConfig, PoseStream
    from .record import RecordLimits, record

    if args.frames is not None and args.frames < 1 or args.duration is not None and args.duration <= 0:
        raise TensorTouchError("--frames / --duration: expected a positive number")
    sensor = args.sensor
    if sensor is None:
        if args.source.startswith("usb:"):
            sensor = args.source[4:].split("?")[0]
        else:
            raise TensorTouchError("--sensor is required unless --source is usb:SERIAL (the serial is the sensor id)")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    gauge = mocap = None
    try:
        if args.ft:
            url = args.ft.split(":", 1)[1] if args.ft.startswith("serial:") else args.ft
            baud = args.ft_baud or (9600 if args.ft_protocol == "mark10" else 115200)
            gauge = ForceGauge(GaugeConfig(url, protocol=args.ft_protocol, baudrate=baud, history=10_000_000)).open()
            gauge.start()
        if args.mocap:
            url = args.mocap.split(":", 1)[1] if args.mocap.startswith("serial:") else args.mocap
            mocap = PoseStream(MocapConfig(url, baudrate=args.mocap_baud)).open().start()
        with camera_from_uri(args.source) as cam:
            print(f"tensortouch record: {cam.name} -> {args.out}; Ctrl-C to stop", file=sys.stderr)
            record(cam, args.out, sensor, gauge, mocap, RecordLimits(args.frames, args.duration),
                   frame_format=args.format, ft_indenter=args.ft_indenter, stop=stop,
                   provenance={"ft": args.ft, "mocap": args.mocap}, say=lambda m: print(m, file=sys.stderr))
    finally:
        for dev in (gauge, mocap):
            if dev is not None:
                dev.close()
    return 0


def register_record(sub) -> None:
    r = sub.add_parser("record", help="record a session (camera frames, force gauge, mocap poses) without ROS",
                       description="Record camera frames, and the force gauge and mocap poses when given, into a "
                                   "session folder (docs/session.md) on one clock. Stops at the end of a replay, "
                                   "after --frames / --duration, or on Ctrl-C / SIGTERM (the session is finished either way).")
    r.add_argument("--source", required=True, help="usb:SERIAL | v4l2:/dev/videoN | replay:SESSION_DIR | file:VIDEO")
    r.add_argument("--sensor", help="sensor id written into the session (default: the USB serial of usb:SERIAL)")
    r.add_argument("--out", required=True, help="new session folder")
    r.add_argument("--ft", help="force gauge: serial:/dev/ttyUSB0 or any pyserial URL (socket://host:port, loop://)")
    r.add_argument("--ft-protocol", choices=("tt", "mark10"), default="tt", help="F/T line protocol: TensorTouch's (tt) or a Mark-10 gauge")
    r.add_argument("--ft-baud", type=int, help="gauge baud rate (default 115200 tt, 9600 mark10)")
    r.add_argument("--ft-indenter", type=int, default=0, help="indenter id the gauge is mounted on (default 0)")
    r.add_argument("--mocap", help="mocap pose stream: pyserial URL (socket://host:port, /dev/ttyACM0), "
                                   "lines 'P <indenter> x y z qw qx qy qz' in mm, sensor frame")
    r.add_argument("--mocap-baud", type=int, default=115200, help="mocap serial baud rate")
    r.add_argument("--frames", type=int, help="stop after N frames")
    r.add_argument("--duration", type=float, help="stop after this many seconds")
    r.add_argument("--format", choices=("ffv1", "png", "mjpg"), default="ffv1",
                   help="frame storage (ffv1 and png are lossless; default ffv1)")
    r.set_defaults(func=_record)


COMMANDS = (
    ("import", "ROS1 .bag, ROS2 bag folder or .mcap -> session (topic map file)", _import, (
        arg("bag", help="ROS 1 bag, ROS 2 bag folder or MCAP file"),
        arg("--map", required=True, help="topic map (JSON or TOML), see docs/session.md"),
        arg("--out", required=True, help="session folder to write"))),
    ("check", "validate a session directory (names the first problem)", _check, (
        arg("session", help="session folder to check"),)),
)


def register(sub) -> None:
    add_commands(command_group(sub, "session", "import ROS/MCAP recordings as sessions; validate sessions",
                               "session_command", "SESSION_COMMAND"), COMMANDS)
    register_record(sub)
