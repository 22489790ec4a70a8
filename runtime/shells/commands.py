"""Deploy-side subcommands of `tensortouch`: run, listen, calib. Thin shells over runtime/ cores."""
from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import sys
from pathlib import Path

from ..apps.zenoh_session import add_zenoh_options, config_from_args, describe

log = logging.getLogger(__name__)

def register(sub) -> None:
    """Add the deploy subcommands to the `tensortouch` parser."""
    p = sub.add_parser("run", help="run one sensor: capture → fields → contacts → Zenoh",
                       description="Run the runtime on a camera or a recording and publish over Zenoh. "
                                   "With no --source it replays the shipped demo recording.")
    p.add_argument("--source", help="replay:SESSION_DIR | file:VIDEO | v4l2:/dev/videoN | usb:SERIAL "
                                    "(default: the shipped demo recording)")
    p.add_argument("--sensor", help="sensor id = calibration store folder (default: the session's sensor_id)")
    p.add_argument("--model", help="model package name in exported_models/ or a path (default: newest installed)")
    p.add_argument("--precision", choices=("int8", "fp32"), default="int8", help="network precision: the int8 graph (default) or the package's fp32 graph")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads")
    add_zenoh_options(p, "sensor")
    p.add_argument("--frames", type=int, help="stop after N frames")
    p.add_argument("--fast", action="store_true", help="replay as fast as possible (default: recorded clock)")
    p.add_argument("--loop", action=argparse.BooleanOptionalAction, default=None,
                   help="replay the recording in a loop (default: on for the shipped demo, off otherwise)")
    p.add_argument("--no-fields", action="store_true", help="publish contacts/wrench/status only")
    p.add_argument("--fields-every", type=int, default=1, metavar="N",
                   help="publish the dense fields on every N-th frame (contacts/wrench/status every frame)")
    from ..apps.ros2_publisher import add_ros2_arguments

    add_ros2_arguments(p)
    p.set_defaults(func=cmd_run)

    from .listen import add_listen_parser

    add_listen_parser(sub)

    c = sub.add_parser("calib", help="calibration store: list / show / rollback")
    csub = c.add_subparsers(dest="calib_cmd", metavar="ACTION", required=True)
    cl = csub.add_parser("list", help="sensors and their versions")
    cl.set_defaults(func=cmd_calib_list)
    cs = csub.add_parser("show", help="one sensor's active calibration")
    cs.add_argument("sensor", help="sensor id (e.g. TWIN-DEMO)")
    cs.add_argument("--version", help="show this version (e.g. v0002) instead of the current one")
    cs.set_defaults(func=cmd_calib_show)
    cr = csub.add_parser("rollback", help="reactivate the previous (or a named) version")
    cr.add_argument("sensor", help="sensor id whose CURRENT version moves back")
    cr.add_argument("--to", dest="version", help="version to make current (default: the one before the current)")
    cr.set_defaults(func=cmd_calib_rollback)
    ci = csub.add_parser("init", help="a new sensor's first calibration: gel rim + nominal θ/φ from a lens model",
                         description="Find the gel rim and centre in rest frames of the camera (gel untouched, lit) "
                                     "and store nominal θ/φ tables from an equidistant fisheye model as the "
                                     "sensor's first calibration version. Refine with `tensortouch recalibrate "
                                     "--geometry` (pokes). docs/bringup.md")
    ci.add_argument("--source", required=True, help="usb:SERIAL | v4l2:/dev/videoN | replay:SESSION_DIR | file:VIDEO")
    ci.add_argument("--sensor", required=True, help="sensor id = calibration store folder (e.g. the USB serial)")
    ci.add_argument("--rest-frames", type=int, default=10, help="frames averaged to find the rim (default 10)")
    ci.add_argument("--model", help="model package whose input size the tables use (default: newest installed)")
    ci.add_argument("--fov-deg", type=float, help="lens field of view (default 220)")
    ci.add_argument("--camera-z-mm", type=float,
                    help="optical centre below the gel base, mm (default -1)")
    ci.add_argument("--gel", default=None, metavar="BASE,CAP,SKIRT",
                    help="gel base radius, cap height, skirt height in mm (default 12,6,2)")
    ci.add_argument("--force", action="store_true", help="add a nominal version even if the sensor has calibrations")
    ci.set_defaults(func=cmd_calib_init)
    for q in (cl, cs, cr, ci):
        q.add_argument("--store", help="calibration store folder (default: calibration_store/)")

    f = sub.add_parser("find", help="list connected cameras: USB serial, vendor/product, /dev/video nodes, capture node",
                       description="List USB cameras with their serial number, vendor and product, every /dev/video "
                                   "node (UVC cameras usually have two: capture and metadata) and which one captures "
                                   "(VIDIOC_QUERYCAP). The serial is what --source usb:SERIAL takes. docs/bringup.md")
    f.add_argument("--json", action="store_true", help="one JSON object per camera")
    f.add_argument("--all", action="store_true", help="every USB device, not only cameras")
    f.set_defaults(func=cmd_find)

    from .hand_cli import register_hand

    register_hand(sub)


def _open_source(args):
    from ...contracts import paths
    from ...contracts.errors import CaptureError
    from ...contracts.session import load_session
    from ...drivers.camera import config_from_uri, make_camera
    from ...drivers.camera.replay import ReplayCameraConfig

    source = args.source
    loop = bool(args.loop)
    if not source:
        demo = paths.demo_dir()
        if not (demo / "session.json").is_file():
            raise CaptureError(f"no --source given and no demo recording at {demo}; "
                               "record one with `tensortouch twin record ... --out runtime/demo`")
        source = f"replay:{demo}"
        if args.loop is None:
            loop = True
            print(f"tensortouch run: replaying the demo recording {demo} in a loop (--no-loop: play it once)",
                  file=sys.stderr)
    config = config_from_uri(source)
    session_sensor = None
    if isinstance(config, ReplayCameraConfig):
        config = config_from_uri(source, realtime=not args.fast, loop=loop or config.loop)
        if not Path(config.path).exists():
            raise CaptureError(f"{config.path}: no such recording (expected a session folder or a video file)")
        if Path(config.path).is_dir():
            session_sensor = load_session(config.path).sensor_id
    return make_camera(config), session_sensor


def _temperature_source(args, cam):
    """A replayed session's own temperature stream (for temperature-dependent effects), else None."""
    from ..stages.temperature import TemperatureTrack

    path = getattr(getattr(cam, "config", None), "path", None)
    if path is None or not Path(path).is_dir():
        return None
    track = TemperatureTrack.from_session(path)
    if track is None:
        return None
    fold = getattr(cam, "recording_time", lambda t: t)
    return lambda t: track(fold(t))


def cmd_run(args) -> int:
    import cv2

    from ...contracts.errors import TensorTouchError
    from ...contracts.store import CalibrationStore
    from ...contracts.wire import check_sensor_id
    from ..apps.loop import LoopConfig, SensorLoop
    from ..apps.publisher import Publisher
    from ..apps.ros2_publisher import Ros2Node, resolve_router, ros2_config_from_args
    from ..pipeline import open_pipeline
    from ..stages.model import find_package

    cv2.setNumThreads(1)                        # leave the cores to onnxruntime and other sensors
    package = find_package(args.model)          # clear message when no trained model is installed
    cam, session_sensor = _open_source(args)
    sensor = args.sensor or session_sensor
    if not sensor:
        raise TensorTouchError("--sensor is required unless --source is a session folder "
                               "(it names the calibration store folder of this sensor)")
    check_sensor_id(sensor)                     # before it names a folder or a Zenoh key
    store = CalibrationStore()
    cal = store.load(sensor)
    pipeline = open_pipeline(package, cal, precision=args.precision, threads=args.threads, sensor_id=sensor)
    ros2 = ros2_config_from_args(args, node=f"tensortouch_{sensor}")
    if ros2 is not None:
        router, note = resolve_router(ros2.router, bool(args.listen or args.connect or args.zenoh_config))
        print(f"tensortouch run: {note}", file=sys.stderr)
        if router:      # a router (rmw_zenohd) holds the port: connect to it instead of listening
            args.connect = list(args.connect) + [router]
    loop = None
    with contextlib.ExitStack() as stack:
        pub = stack.enter_context(Publisher(sensor, zenoh_config=config_from_args(args, "sensor"),
                                            info=lambda: loop.info() if loop else {}))
        ros2_sensor = None
        if ros2 is not None:
            node = stack.enter_context(Ros2Node(pub.session, ros2))
            ros2_sensor = node.sensor(sensor, calibration=lambda: pipeline.cal)
        loop = SensorLoop(cam, pipeline, pub, LoopConfig(publish_fields=not args.no_fields,
                                                          fields_every=max(1, args.fields_every)),
                          store=store, temperature=_temperature_source(args, cam), ros2=ros2_sensor)
        signal.signal(signal.SIGTERM, lambda *a: loop.stop())
        print(f"tensortouch run: sensor {sensor}, model {package.name} ({args.precision}), "
              f"calibration {cal.version}, Zenoh {describe(args, 'sensor')}"
              + (f", ROS 2 {ros2.distro} domain {ros2.domain_id} under {ros2.namespace}" if ros2 else "")
              + "; Ctrl-C to stop", file=sys.stderr)
        try:
            with cam:
                n = loop.run(max_frames=args.frames)
        except KeyboardInterrupt:
            n = loop.frames
        summ = loop.latency.summary()
    tot = summ.get("total", {})
    print(f"tensortouch run: {n} frames, end-to-end p50 {tot.get('p50', 0):.2f} ms, "
          f"p99 {tot.get('p99', 0):.2f} ms", file=sys.stderr)
    return 0


def _store(args):
    from ...contracts.store import CalibrationStore

    return CalibrationStore(args.store) if args.store else CalibrationStore()


def cmd_calib_list(args) -> int:
    store = _store(args)
    sensors = store.sensors()
    if not sensors:
        print(f"no calibrations in {store.root}")
    for s in sensors:
        for row in store.history(s):
            mark = "*" if row["active"] else " "
            print(f"{mark} {s} {row['version']} {row['created']} {row['provenance'].get('method', '')}")
    return 0


def cmd_calib_show(args) -> int:
    import json

    cal = _store(args).load(args.sensor, args.version)
    meta = {k: v for k, v in cal.meta.items() if k != "files"}
    print(json.dumps(meta, indent=2))
    return 0


def cmd_calib_rollback(args) -> int:
    v = _store(args).rollback(args.sensor, args.version)
    print(f"{args.sensor}: active calibration is now {v}")
    return 0



def cmd_calib_init(args) -> int:
    from dataclasses import fields

    from ...contracts.errors import CalibrationError, TensorTouchError
    from ...contracts.store import ANY
    from ...drivers.camera import camera_from_uri
    from ...drivers.camera.camera import EndOfStream
    from ..calib.bringup import GelShape, LensModel, init_calibration
    from ..stages.model import find_package

    store = _store(args)
    if args.sensor in store.sensors() and not args.force:
        raise CalibrationError(f"sensor {args.sensor} already has calibration {store.current(args.sensor)} in "
                               f"{store.root}; use --force to add a nominal version on top")
    gel = GelShape()
    if args.gel:
        try:
            values = [float(v) for v in args.gel.split(",")]
        except ValueError:
            values = []
        if len(values) != 3 or min(values) < 0 or values[0] <= 0 or values[1] <= 0:
            raise TensorTouchError(f"--gel {args.gel!r}: expected BASE,CAP,SKIRT in mm (e.g. 12,6,2)")
        gel = GelShape(*values)
    if args.fov_deg is None:
        args.fov_deg = LensModel.fov_deg
    if args.camera_z_mm is None:
        args.camera_z_mm = LensModel.camera_z_mm
    if not 0 < args.fov_deg <= 360:
        raise TensorTouchError(f"--fov-deg {args.fov_deg}: expected a field of view in (0, 360]")
    if args.rest_frames < 1:
        raise TensorTouchError(f"--rest-frames {args.rest_frames}: expected at least 1")
    package = find_package(args.model)
    lens = LensModel(fov_deg=args.fov_deg, camera_z_mm=args.camera_z_mm)
    frames = []
    with camera_from_uri(args.source) as cam:
        try:
            for _ in range(args.rest_frames):
                frames.append(cam.read().image)
        except EndOfStream:
            pass
    if not frames:
        raise TensorTouchError(f"--source {args.source}: no frames")
    version, fit = init_calibration(store, args.sensor, frames, tuple(package.size), lens, gel,
                                    provenance={"source": args.source, "model": package.name,
                                                "gel_shape": {f.name: getattr(gel, f.name) for f in fields(gel)}},
                                    base_version=ANY if args.force else None)  # no second first version
    print(f"{args.sensor}: gel centre ({fit.center[0]:.1f}, {fit.center[1]:.1f}) px, radius {fit.radius:.1f} px "
          f"(rim rms {fit.rms_px:.2f} px on {fit.points} rays); nominal calibration {version} stored in {store.root}")
    print(f"next: poke it with `tensortouch recalibrate --sensor {args.sensor} --geometry ...` (docs/bringup.md)")
    return 0


def format_camera(cam) -> str:
    """One `tensortouch find` entry (drivers.usb.CameraInfo) as text."""
    d = cam.device
    label = f" ({d.name})" if d.name else ""
    names = " ".join(x for x in (cam.manufacturer, cam.product) if x) or "?"
    lines = [f"{d.serial or '(no readable serial)'}  {d.vid_pid}{label}  {names}  bus {d.bus:03d} address {d.address:03d}"]
    for n in cam.nodes:
        mark = "  <- capture node" if n.path == cam.capture_node else ""
        lines.append(f"    {n.path}  {n.kind}{f'  {n.card}' if n.card else ''}{mark}")
    if cam.stable_name:
        lines.append(f"    {cam.stable_name}  (udev rule: drivers/udev/99-tensortouch.rules)")
    if d.serial and cam.capture_node:
        lines.append(f"    tensortouch run --source usb:{d.serial} --sensor {d.serial}")
    elif cam.capture_node:
        lines.append(f"    tensortouch run --source v4l2:{cam.capture_node} --sensor ID")
    return "\n".join(lines)


def cmd_find(args, backend=None, sysfs_root=None, dev_root=None, query=None) -> int:
    import json

    from ...drivers import usb

    cams = usb.list_cameras(backend=backend, sysfs_root=sysfs_root or usb.SYSFS_ROOT,
                            dev_root=dev_root or usb.DEV_ROOT, query=query, include_all=args.all)
    if args.json:
        for cam in cams:
            print(json.dumps(cam.to_dict(), sort_keys=True))
        return 0 if cams else 1          # the same rule as the text form: 1 = found nothing
    if not cams:
        print("no USB cameras found (is the sensor plugged in? in a container, are /dev and /sys mapped?)")
        return 1
    for cam in cams:
        print(format_camera(cam))
    return 0
