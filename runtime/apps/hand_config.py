"""Hand configuration (TOML): which sensors one runtime process serves (docs/hand.md).

    [hand]
    name = "left"                     # used in log lines and the hand summary
    model = "tt-hiera-128"            # package name in exported_models/ or a path (default: newest)
    precision = "int8"
    share_model = false               # true: one onnxruntime session for every finger
    opencv_threads = 1                # OpenCV's threads for the whole process (the fingers are the parallelism)
    fields_every = 1                  # dense fields on every N-th frame per finger (contacts and wrench: every frame)
    inference_workers = 2             # fingers running inference at the same time (0: no limit)
    calibration_store = "calibration_store"   # relative paths are relative to this file

    [zenoh]
    listen = ["tcp/127.0.0.1:7447"]   # default: the meeting point (runtime/apps/zenoh_session.py)
    connect = []
    config = "sensor.json5"           # optional: Zenoh's own JSON5 config (TLS, access control)

    [ros2]                            # optional: ROS 2 topics in rmw_zenoh's format (docs/wire.md)
    distro = "jazzy"                  # jazzy | kilted | rolling | humble
    domain_id = 0                     # default: $ROS_DOMAIN_ID or 0
    router = "auto"                   # default: connect to a router (rmw_zenohd) at the meeting point when
                                      # one runs there, else listen there; an endpoint: connect to it
                                      # (instead of listening, with no [zenoh] listen); "" = none

    [can]                             # optional: compact summary on CAN (python-can)
    interface = "socketcan"
    channel = "can0"
    id_base = 0x300
    rate_hz = 100

    [[finger]]
    name = "index"
    serial = "TT-0001"                # sensor serial = sensor id on the wire
    source = "usb:TT-0001"            # default: usb:<serial>
    calibration = "TT-0001"           # calibration store folder (default: serial)
    can_slot = 0                      # default: position in the list

Unknown keys are errors (a typo must not silently fall back to a default). Every value is checked by
the type of its dataclass field and its range in LIMITS before anything starts: one line, exit 2.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ...contracts import wire
from ...contracts.errors import TensorTouchError
from ...contracts.ros2_wire import name_token as rw_name_token
from ...contracts.schema import Range, SchemaError, check_depth, check_fields, check_value
from ...drivers.can_bus import CanConfig
from .ros2_publisher import Ros2Config, resolve_router

log = logging.getLogger(__name__)


class HandConfigError(TensorTouchError):
    """The hand configuration file is missing, malformed or inconsistent."""


@dataclass(frozen=True)
class FingerConfig:
    name: str
    serial: str                        # sensor id: wire key chunk and default calibration folder
    source: str = ""                   # camera source string (drivers.camera); "" -> usb:<serial>
    calibration: str = ""              # calibration store folder; "" -> serial
    can_slot: int = -1                 # -1 -> position in the finger list
    enabled: bool = True

    @property
    def source_uri(self) -> str:
        return self.source or f"usb:{self.serial}"

    @property
    def calibration_id(self) -> str:
        return self.calibration or self.serial


@dataclass(frozen=True)
class HandConfig:
    fingers: tuple[FingerConfig, ...]
    name: str = "hand"
    model: str | None = None
    precision: str = "int8"
    threads: int = 1                   # onnxruntime intra-op threads per session
    opencv_threads: int = 1            # OpenCV's worker threads for the whole process (cv2.setNumThreads), set when the
                                       # hand starts: the fingers' threads are the parallelism; OpenCV's pool beside
                                       # them cost ~12 % more CPU in a 5-finger soak (docs/hand.md)
    share_model: bool = False          # measured: no consistent speed difference; shared saves ~7 MB/finger
    inference_workers: int = field(default_factory=lambda: os.cpu_count() or 2)
    calibration_store: str | None = None
    publish_fields: bool = True
    fields_every: int = 1              # dense fields on every N-th frame of each finger; contacts, wrench and status
                                       # every frame (LoopConfig.fields_every, `run --fields-every`)
    listen: tuple[str, ...] = ()       # listen and connect both empty: listen on the meeting point
    connect: tuple[str, ...] = ()
    zenoh_config: str | None = None    # Zenoh's JSON5 config file; listen/connect replace its endpoints
    multicast: bool = False            # multicast + gossip scouting
    can: CanConfig | None = None
    # camera faults: SensorLoop gives up after max_camera_failures reads; the hand then
    # reconnects every reconnect_s and drops the sensor's liveliness token after offline_after_s
    max_camera_failures: int = 20
    reconnect_s: float = 0.5
    offline_after_s: float = 5.0
    status_every_s: float = 0.5
    model_poll_s: float = 1.0          # how often model files are checked for replacement
    camera_options: dict = field(default_factory=dict)   # extra camera config (e.g. realtime, loop)
    ros2: Ros2Config | None = None     # [ros2]: also publish ROS 2 topics (runtime/apps/ros2_publisher.py)

    def slots(self) -> dict[str, int]:
        return {f.name: (f.can_slot if f.can_slot >= 0 else i) for i, f in enumerate(self.fingers)}


# The declared range of every numeric field of each table (contracts/schema.py Range, inclusive); the
# field types come from the dataclasses themselves (FingerConfig, HandConfig, CanConfig, Ros2Config).
LIMITS = {
    FingerConfig: {"can_slot": Range(-1, 255)},
    HandConfig: {"threads": Range(1, 256), "opencv_threads": Range(1, 256), "inference_workers": Range(0, 256),
                 "fields_every": Range(1, 1_000_000),
                 "max_camera_failures": Range(1, 1_000_000), "reconnect_s": Range(0, 3600, lo_open=True),
                 "offline_after_s": Range(0, 86_400), "status_every_s": Range(0, 3600, lo_open=True),
                 "model_poll_s": Range(0, 3600, lo_open=True), "precision": ("int8", "fp32")},
    CanConfig: {"bitrate": Range(1, 10_000_000), "id_base": Range(0, 0x1FFFFFFF), "rate_hz": Range(0, 10_000, lo_open=True),
                "send_timeout_s": Range(0, 60), "reopen_after_errors": Range(1, 1_000_000),
                "reopen_wait_s": Range(0, 60), "stale_after_s": Range(0, 60, lo_open=True)},
    Ros2Config: {"domain_id": Range(0, 232), "depth": Range(1, 10_000), "surface_every": Range(0, 1_000_000),
                 "surface_step": Range(1, 4096), "mount_xyz_m": Range(-100, 100), "mount_xyzw": Range(-1, 1)},
}
# [camera] options for every finger's camera (drivers.camera configs): each number in its range here,
# others in CAMERA_RANGE
CAMERA_LIMITS = {"speed": Range(0, 1000, lo_open=True), "fps": Range(0, 10_000, lo_open=True),
                 "width": Range(1, 16384), "height": Range(1, 16384), "exposure_s": Range(0, 10, lo_open=True),
                 "read_timeout_s": Range(0, 3600, lo_open=True), "connect_timeout_s": Range(0, 3600, lo_open=True)}
CAMERA_RANGE = Range(0, 1_000_000)


def _take(table, cls, where: str, renames: dict | None = None) -> dict:
    """The keys of one table as fields of `cls`, each checked by its type and declared range."""
    if not isinstance(table, dict):
        raise HandConfigError(f"{where}: expected a table of {cls.__name__} fields, got {_show(table)}")
    names = {f.name for f in dataclasses.fields(cls)}
    out = {}
    for key, value in table.items():
        k = (renames or {}).get(key, key)
        if k not in names:
            raise HandConfigError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(names))})")
        out[k] = value
    try:
        check_fields(cls, out, "", LIMITS.get(cls))
    except SchemaError as exc:
        raise HandConfigError(f"{where}: {exc}") from None
    return out


def _show(v) -> str:
    return f"{type(v).__name__} {v!r}"[:80]


def _camera_options(table, where: str) -> dict:
    """[camera]: fields of the replay or the live camera config, by their types and CAMERA_LIMITS."""
    import typing

    from ...drivers.camera.opencv import OpenCVCameraConfig
    from ...drivers.camera.replay import ReplayCameraConfig

    if not isinstance(table, dict):
        raise HandConfigError(f"{where}: expected a table of camera options, got {_show(table)}")
    for key, value in table.items():
        cls = next((c for c in (ReplayCameraConfig, OpenCVCameraConfig)
                    if key in {f.name for f in dataclasses.fields(c)} and key not in ("path", "device", "serial")), None)
        if cls is None:
            known = sorted({f.name for c in (ReplayCameraConfig, OpenCVCameraConfig) for f in dataclasses.fields(c)}
                           - {"path", "device", "serial"})
            raise HandConfigError(f"{where}: unknown camera option {key!r} (known: {', '.join(known)})")
        try:
            check_value(value, typing.get_type_hints(cls)[key], key, CAMERA_LIMITS.get(key, CAMERA_RANGE))
        except SchemaError as exc:
            raise HandConfigError(f"{where}: {exc}") from None
    return dict(table)


def _check(cfg: HandConfig, where: str) -> None:
    if not cfg.fingers:
        raise HandConfigError(f"{where}: no [[finger]] entries (a hand needs at least one sensor)")
    for what in ("name", "serial"):
        seen = [getattr(f, what) for f in cfg.fingers]
        dup = sorted({v for v in seen if seen.count(v) > 1})
        if dup:
            raise HandConfigError(f"{where}: finger {what} {dup} used more than once")
    for f in cfg.fingers:
        try:
            wire.check_sensor_id(f.serial)
        except wire.WireError as exc:
            raise HandConfigError(f"{where}: finger {f.name!r}: {exc}") from None
    slots = list(cfg.slots().values())
    if len(set(slots)) != len(slots):
        raise HandConfigError(f"{where}: can_slot values {slots} collide")
    if cfg.precision not in ("int8", "fp32"):
        raise HandConfigError(f"{where}: hand.precision {cfg.precision!r}, expected 'int8' or 'fp32'")
    if cfg.inference_workers < 0 or cfg.threads < 1:
        raise HandConfigError(f"{where}: hand.inference_workers must be >= 0 (0: no limit) and "
                              "hand.threads >= 1")
    if cfg.can is not None:
        from ...contracts.can_frame import check_id_range

        try:
            check_id_range(cfg.can.id_base, max(slots) + 1, cfg.can.extended_id)
        except ValueError as exc:
            raise HandConfigError(f"{where}: [can] {exc}") from None


def parse_hand_config(data: dict, where: str = "hand config", base_dir: Path | None = None) -> HandConfig:
    """A parsed TOML document -> validated HandConfig."""
    unknown = set(data) - {"hand", "zenoh", "can", "finger", "camera", "ros2"}
    if unknown:
        raise HandConfigError(f"{where}: unknown table(s) {sorted(unknown)} "
                              "(expected [hand], [zenoh], [can], [camera], [ros2], [[finger]])")
    try:
        check_depth(data, where)
    except SchemaError as exc:
        raise HandConfigError(str(exc)) from None
    fingers_raw = data.get("finger", [])
    if not isinstance(fingers_raw, list):
        raise HandConfigError(f"{where}: 'finger' must be an array of tables ([[finger]])")
    fingers = []
    for i, fr in enumerate(fingers_raw):
        kw = _take(fr, FingerConfig, f"{where}: finger #{i + 1}")
        for req in ("name", "serial"):
            if not kw.get(req):
                raise HandConfigError(f"{where}: finger #{i + 1} needs '{req}'")
        fingers.append(FingerConfig(**kw))
    hand = _take(data.get("hand", {}), HandConfig, f"{where}: [hand]")
    for bad in ("fingers", "listen", "connect", "zenoh_config", "multicast", "can", "camera_options", "ros2"):
        if bad in data.get("hand", {}):
            raise HandConfigError(f"{where}: [hand] {bad} belongs in its own table")
    zen = data.get("zenoh", {})
    if not isinstance(zen, dict):
        raise HandConfigError(f"{where}: [zenoh] expected a table, got {_show(zen)}")
    extra = set(zen) - {"listen", "connect", "config", "multicast"}
    if extra:
        raise HandConfigError(f"{where}: [zenoh] unknown key(s) {sorted(extra)} "
                              "(known: listen, connect, config, multicast)")
    for key in ("listen", "connect"):
        if key in zen and not (isinstance(zen[key], list) and all(isinstance(e, str) for e in zen[key])):
            raise HandConfigError(f"{where}: [zenoh] {key} is {_show(zen[key])}, expected a list of endpoints "
                                  "such as [\"tcp/127.0.0.1:7447\"]")
    if "config" in zen:
        if not isinstance(zen["config"], str):
            raise HandConfigError(f"{where}: [zenoh] config is {_show(zen['config'])}, expected a file path")
        zpath = Path(str(zen["config"]))
        if base_dir is not None and not zpath.is_absolute():
            zpath = base_dir / zpath
        hand["zenoh_config"] = str(zpath)
    if "multicast" in zen:
        if not isinstance(zen["multicast"], bool):
            raise HandConfigError(f"{where}: [zenoh] multicast must be true or false")
        hand["multicast"] = zen["multicast"]
    if "listen" in zen:
        hand["listen"] = tuple(zen["listen"])
    if "connect" in zen:
        hand["connect"] = tuple(zen["connect"])
    if "can" in data:
        try:
            hand["can"] = CanConfig(**_take(data["can"], CanConfig, f"{where}: [can]"))
        except (TypeError, ValueError) as exc:
            raise HandConfigError(f"{where}: [can] {exc}") from None
    if "camera" in data:
        hand["camera_options"] = _camera_options(data["camera"], f"{where}: [camera]")
    if "ros2" in data:
        kw = _take(data["ros2"], Ros2Config, f"{where}: [ros2]")
        kw.setdefault("node", rw_name_token(f"tensortouch_{hand.get('name', 'hand')}"))
        for k in ("images", "mount_xyz_m", "mount_xyzw"):
            if k in kw:
                kw[k] = tuple(kw[k])
        try:
            hand["ros2"] = Ros2Config(**kw)
        except (TypeError, ValueError, TensorTouchError) as exc:
            raise HandConfigError(f"{where}: [ros2] {exc}") from None
        router, note = resolve_router(hand["ros2"].router, bool(set(zen) & {"listen", "connect", "config"}))
        log.info("hand %s: %s", hand.get("name", "hand"), note)
        if router:
            hand["connect"] = tuple(hand.get("connect", ())) + (router,)
            if "listen" not in zen:           # the router (rmw_zenohd) holds the port: connect, not listen
                hand["listen"] = ()
    store = hand.get("calibration_store")
    if store and base_dir is not None and not Path(store).is_absolute():
        hand["calibration_store"] = str(base_dir / store)
    try:
        cfg = HandConfig(fingers=tuple(fingers), **hand)
    except TypeError as exc:
        raise HandConfigError(f"{where}: {exc}") from None
    _check(cfg, where)
    return cfg


def load_hand_config(path: str | Path) -> HandConfig:
    path = Path(path)
    if not path.is_file():
        raise HandConfigError(f"{path}: hand config file not found")
    try:
        data = tomllib.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise HandConfigError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); expected TOML") from None
    except tomllib.TOMLDecodeError as exc:
        raise HandConfigError(f"{path}: not valid TOML ({exc})") from None
    return parse_hand_config(data, str(path), path.parent)
