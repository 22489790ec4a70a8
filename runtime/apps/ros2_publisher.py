"""ROS 2 mode: publish standard ROS 2 messages straight onto Zenoh in rmw_zenoh's format, beside
our own `tensortouch/<id>/...` keys, so ROS 2 nodes using rmw_zenoh receive them with no bridge
(docs/wire.md "ROS 2").

Per sensor (`<ns>` = the namespace, `<s>` = the sensor id as a ROS token, `runtime.ros2_wire.name_token`):

| topic | type | rate | units |
|---|---|---|---|
| `<ns>/<s>/wrench` | geometry_msgs/WrenchStamped | every frame | N, N·m (ours ÷ 1000) |
| `<ns>/<s>/contacts` | sensor_msgs/PointCloud2 x y z fx fy fz force area id | every frame | m, N, m² |
| `<ns>/<s>/image/<channel>` | sensor_msgs/Image 32FC1 | with the fields | m (disp), Pa (stress) |
| `<ns>/<s>/surface` | sensor_msgs/PointCloud2 x y z + 15 channels | every `surface_every`-th fields frame | m, Pa |
| `/diagnostics` | diagnostic_msgs/DiagnosticArray | with the status | – |
| `/tf` | tf2_msgs/TFMessage `<parent_frame>` → `<s>_gel` | with the status | m |

Thin shell over contracts/ros2_cdr.py (message bytes) and contracts/ros2_wire.py (keys, tokens,
attachment). Like runtime/apps/publisher.py, the publish calls never raise and never block: failures
are counted and logged once, then every 1000th time.
"""
from __future__ import annotations

import argparse
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Self

import numpy as np

from ...contracts import ros2_cdr as cdr
from ...contracts import ros2_wire as rw
from ...contracts.fields import CHANNEL_UNITS, CHANNELS
from .zenoh_session import release

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)

ROUTER_ENDPOINT = "tcp/127.0.0.1:7447"          # rmw_zenohd's default listen endpoint
AUTO = "auto"            # router: connect to a router at the meeting point if one is there, else listen there
STAMPS = ("wall", "frame")
SI_SCALE = {"mm": 1e-3, "MPa": 1e6}              # house unit -> SI (m, Pa)
ERROR_FLAGS = frozenset({"camera_stalled", "camera_lost", "frame_black", "camera_frozen",
                         "calibration_invalid", "model_invalid"})

WRENCH, IMAGE, CLOUD = "geometry_msgs/msg/WrenchStamped", "sensor_msgs/msg/Image", "sensor_msgs/msg/PointCloud2"
DIAG, TF = "diagnostic_msgs/msg/DiagnosticArray", "tf2_msgs/msg/TFMessage"

CONTACT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("fx", "<f4"), ("fy", "<f4"),
                          ("fz", "<f4"), ("force", "<f4"), ("area", "<f4"), ("id", "<u4")])
SURFACE_DTYPE = np.dtype([(n, "<f4") for n in ("x", "y", "z") + CHANNELS])


def _default_domain() -> int:
    return rw.check_domain(os.environ.get("ROS_DOMAIN_ID", "0") or 0)


@dataclass(frozen=True)
class Ros2Config:
    """ROS 2 mode settings (`tensortouch run --ros2 ...`, or `[ros2]` in a hand config)."""
    distro: str = "jazzy"                    # jazzy | kilted | rolling | humble (type hash placeholder)
    domain_id: int = field(default_factory=_default_domain)   # ROS_DOMAIN_ID, default from the env
    namespace: str = "/tensortouch"
    node: str = "tensortouch"                # ROS node name of this process
    reliability: str = "reliable"            # reliable | best_effort
    depth: int = rw.DEFAULT_DEPTH            # keep last N
    router: str = AUTO                       # Zenoh router to connect to; "auto": see resolve_router; "" = none
    images: tuple[str, ...] = ("disp_z", "fn_z")   # field channels published as 32FC1 images
    surface_every: int = 10                  # gel surface cloud on every N-th fields frame (0 = never)
    surface_step: int = 2                    # surface cloud: every n-th row and column of the grid
    parent_frame: str = "tensortouch_mount"  # tf parent of each sensor's `<s>_gel` frame
    mount_xyz_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mount_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    # header stamps: "wall" = the frame time moved onto the system clock by one constant offset taken at
    # the first message (live cameras stamp frames with a monotonic clock, replays with the recording's);
    # "frame" = the frame time as it is, the same `t` as on our own keys
    stamp: str = "wall"

    def __post_init__(self):
        rw.check_distro(self.distro)
        if self.stamp not in STAMPS:
            raise rw.Ros2Error(f"ROS 2 stamp {self.stamp!r}: expected one of {', '.join(STAMPS)}")
        rw.check_domain(self.domain_id)
        rw.check_name(self.namespace, "namespace")
        if rw.name_token(self.node) != self.node:
            raise rw.Ros2Error(f"ROS 2 node name {self.node!r}: expected letters, digits and _, "
                               "not starting with a digit")
        rw.Qos(self.reliability, int(self.depth))              # validates reliability and depth
        bad = [c for c in self.images if c not in CHANNELS]
        if bad:
            raise rw.Ros2Error(f"ROS 2 images {bad}: expected field channels from {', '.join(CHANNELS)}")
        if self.surface_every < 0 or self.surface_step < 1:
            raise rw.Ros2Error("ROS 2 surface_every must be >= 0 and surface_step >= 1")
        if len(self.mount_xyz_m) != 3 or len(self.mount_xyzw) != 4:
            raise rw.Ros2Error("ROS 2 mount_xyz_m needs 3 numbers and mount_xyzw 4 (x, y, z, w)")
        if abs(float(np.linalg.norm(self.mount_xyzw)) - 1.0) > 1e-3:
            raise rw.Ros2Error(f"ROS 2 mount_xyzw {list(self.mount_xyzw)}: expected a unit quaternion")

    @property
    def qos(self) -> rw.Qos:
        return rw.Qos(self.reliability, int(self.depth))


# --------------------------------------------------------------------------- CLI options

def add_ros2_arguments(parser: argparse.ArgumentParser) -> None:
    """The `--ros2*` options of `tensortouch run` (one argument group)."""
    g = parser.add_argument_group("ROS 2 (rmw_zenoh wire format, docs/wire.md \"ROS 2\")")
    d = Ros2Config.__dataclass_fields__
    g.add_argument("--ros2", action="store_true",
                   help="also publish ROS 2 messages (WrenchStamped, Image, PointCloud2, diagnostics, tf)")
    g.add_argument("--ros2-distro", choices=rw.DISTROS, default=d["distro"].default, help="ROS 2 distribution whose type hashes are published (humble has none)")
    g.add_argument("--ros2-domain", type=int, metavar="ID", help="ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or 0)")
    g.add_argument("--ros2-namespace", default=d["namespace"].default, metavar="NS", help="topic namespace: topics become /NS/<sensor>/…")
    g.add_argument("--ros2-router", default=AUTO, metavar="ENDPOINT",
                   help="connect to this Zenoh router, e.g. rmw_zenohd at " + ROUTER_ENDPOINT + "; 'auto' (default): "
                        "connect to a router at the meeting point when one runs there, else listen there "
                        "(ROS 2 nodes and `listen` connect to it); 'none': no router")
    g.add_argument("--ros2-qos", choices=tuple(rw.RELIABILITY), default=d["reliability"].default, help="QoS reliability announced in the liveliness tokens")
    g.add_argument("--ros2-depth", type=int, default=d["depth"].default, metavar="N", help="QoS history depth (KEEP_LAST N)")
    g.add_argument("--ros2-stamp", choices=STAMPS, default=d["stamp"].default,
                   help="header stamps: frame time moved onto the system clock (wall) or as it is (frame)")
    g.add_argument("--ros2-images", default=",".join(d["images"].default), metavar="CH,CH",
                   help="field channels published as 32FC1 images ('' for none)")


def ros2_config_from_args(args, node: str = "tensortouch") -> Ros2Config | None:
    """The `--ros2*` options as a Ros2Config (None without `--ros2`); `node` names the ROS node."""
    if not getattr(args, "ros2", False):
        return None
    kw: dict[str, Any] = {"node": rw.name_token(node), "distro": args.ros2_distro, "namespace": args.ros2_namespace,
                              "reliability": args.ros2_qos, "depth": args.ros2_depth, "stamp": args.ros2_stamp,
                              "router": "" if args.ros2_router in ("", "none") else args.ros2_router,
                              "images": tuple(c.strip() for c in args.ros2_images.split(",") if c.strip())}
    if args.ros2_domain is not None:
        kw["domain_id"] = args.ros2_domain
    return Ros2Config(**kw)


def _accepting(endpoint: str, timeout_s: float = 0.5) -> bool:
    """Whether something accepts TCP connections at a `tcp/HOST:PORT` endpoint (False for others)."""
    import socket

    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if proto != "tcp" or not host or not port.isdigit():
        return False
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return True
    except OSError:
        return False


def resolve_router(router: str, endpoints_given: bool) -> tuple[str | None, str]:
    """Where ROS 2 mode meets rmw_zenoh: (the endpoint to connect to, or None to keep the session's own
    endpoints) and the one line that says what happens and what to start.

    "auto" with no --listen/--connect/--zenoh-config: when something already listens at the meeting point
    (rmw_zenohd holds tcp/127.0.0.1:7447, the meeting point's default), connect to it; else listen
    there, as without ROS 2, so `tensortouch listen` and ROS 2 nodes on rmw_zenoh (which connect to
    tcp/localhost:7447 by default) reach this sensor directly. An explicit endpoint is connected to
    (instead of listening, when no --listen is given); "" connects to none."""
    from .zenoh_session import default_endpoint

    meet = default_endpoint()
    if router == AUTO:
        if endpoints_given:
            return None, "ROS 2: topics travel on this session's own endpoints (--ros2-router auto)"
        if _accepting(meet):
            return meet, (f"ROS 2: a Zenoh router listens at {meet} (rmw_zenohd?): connecting to it; "
                          f"`tensortouch listen` and ROS 2 nodes reach this sensor through it")
        return None, (f"ROS 2: no Zenoh router at {meet}: this sensor listens there itself; `tensortouch listen` "
                      f"and ROS 2 nodes on rmw_zenoh connect to it directly (rmw_zenohd not needed; started "
                      f"later it finds the port taken: start it first, or give --ros2-router ENDPOINT)")
    if not router:
        return None, "ROS 2: no router (--ros2-router none): topics travel on this session's own endpoints"
    return router, (f"ROS 2: connecting to the Zenoh router {router}; our own keys travel through it too: "
                    f"`tensortouch listen --connect {router}`")


# --------------------------------------------------------------------------- shell

class _Topic:
    """One ROS 2 publisher: a Zenoh publisher on the data key and its MP liveliness token."""

    def __init__(self, node: Ros2Node, topic: str, ros_type: str, priority, express: bool):
        import zenoh  # here, not at import: `tensortouch --help` builds this module's options

        cfg = node.config
        self.node, self.topic, self.ros_type = node, topic, ros_type
        self.token_key = rw.publisher_token(cfg.domain_id, node.zid, node.node_id, node.next_id(),
                                            cfg.namespace, cfg.node, topic, ros_type, cfg.distro, cfg.qos)
        self.key = rw.data_key(cfg.domain_id, topic, ros_type, cfg.distro)
        self.gid = rw.gid_of(self.token_key)
        self.seq = 0
        self.sent = 0
        self.errors = 0
        rel = zenoh.Reliability.RELIABLE if cfg.reliability == "reliable" else zenoh.Reliability.BEST_EFFORT
        self.pub = node.session.declare_publisher(self.key, congestion_control=zenoh.CongestionControl.DROP,
                                                  priority=priority, express=express, reliability=rel)
        self.token = node.session.liveliness().declare_token(self.token_key)

    def put(self, payload: bytes) -> None:
        self.seq += 1
        self.pub.put(payload, attachment=rw.attachment(self.seq, time.time_ns(), self.gid))
        self.sent += 1

    def close(self) -> None:
        for obj in (self.token, self.pub):
            release(obj.undeclare, f"ros2 undeclare {self.topic}", log)


class Ros2Node:
    """One ROS 2 node on an open Zenoh session: its NN token, `/diagnostics`, `/tf`, and the
    per-sensor publishers made by `sensor()`. Not the owner of the session."""

    def __init__(self, session: zenoh.Session, config: Ros2Config | None = None):
        import zenoh  # here, not at import: `tensortouch --help` builds this module's options

        self.session = session
        self.config = config or Ros2Config()
        self.zid = str(session.info.zid())
        self.node_id = 0
        self._ids = 0
        self._lock = threading.Lock()
        self._closed = False
        self.sensors: list[Ros2Sensor] = []
        self._token = session.liveliness().declare_token(rw.node_token(
            self.config.domain_id, self.zid, self.node_id, self.config.namespace, self.config.node))
        low = zenoh.Priority.DATA_LOW
        self.diagnostics = _Topic(self, "/diagnostics", DIAG, low, False)
        self.tf = _Topic(self, "/tf", TF, low, False)
        log.info("ROS 2 node %s%s (domain %d, %s) on Zenoh session %s", rw.join(self.config.namespace, ""),
                 self.config.node, self.config.domain_id, self.config.distro, self.zid)

    def next_id(self) -> int:
        with self._lock:
            self._ids += 1
            return self.node_id + self._ids

    def sensor(self, sensor_id: str, calibration: Callable[[], Any] | None = None) -> Ros2Sensor:
        s = Ros2Sensor(self, sensor_id, calibration)
        self.sensors.append(s)
        return s

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for s in self.sensors:
            s.close()
        for t in (self.diagnostics, self.tf):
            t.close()
        release(self._token.undeclare, "ros2 node token", log)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Ros2Sensor:
    """One sensor's ROS 2 topics. Same calls as runtime.apps.publisher.Publisher, house units in
    (mm, N, N·mm, MPa), SI out. `calibration()` returns the active Calibration (for the surface)."""

    def __init__(self, node: Ros2Node, sensor_id: str, calibration: Callable[[], Any] | None = None):
        import zenoh  # here, not at import: `tensortouch --help` builds this module's options

        cfg = node.config
        self.node, self.sensor_id, self.calibration = node, sensor_id, calibration
        self.name = rw.name_token(sensor_id)
        self.frame_id = f"{self.name}_gel"
        base = rw.join(cfg.namespace, self.name)
        hi, data = zenoh.Priority.INTERACTIVE_HIGH, zenoh.Priority.DATA
        self.topics: dict[str, _Topic] = {}
        self._closed = False
        self._fields_frames = 0
        self._log_every = 1000
        self._offset: float | None = None      # wall clock - frame clock ("wall" stamps)
        try:
            self.topics["wrench"] = _Topic(node, f"{base}/wrench", WRENCH, hi, True)
            self.topics["contacts"] = _Topic(node, f"{base}/contacts", CLOUD, hi, True)
            for ch in cfg.images:
                self.topics[f"image/{ch}"] = _Topic(node, f"{base}/image/{ch}", IMAGE, data, False)
            if cfg.surface_every:
                self.topics["surface"] = _Topic(node, f"{base}/surface", CLOUD, zenoh.Priority.DATA_LOW, False)
        except Exception:
            self.close()
            raise

    def stamp(self, t: float) -> float:
        """Header stamp (s) of a message with frame time `t` (Ros2Config.stamp)."""
        if self.node.config.stamp == "frame":
            return float(t)
        if self._offset is None:
            self._offset = time.time() - float(t)
        return float(t) + self._offset

    # ---------------------------------------------------------------- frame-loop API (never raises)

    def publish_wrench(self, force_n: Sequence[float], torque_nmm: Sequence[float], seq: int, t: float) -> bool:
        return self._send("wrench", lambda: cdr.wrench_stamped(
            self.stamp(t), self.frame_id, [float(v) for v in force_n], [float(v) * 1e-3 for v in torque_nmm]))

    def publish_contacts(self, contacts: Iterable[Any], seq: int, t: float) -> bool:
        def build():
            items = [c.to_dict() if hasattr(c, "to_dict") else c for c in contacts]
            pts = np.zeros(len(items), CONTACT_DTYPE)
            for i, c in enumerate(items):
                (pts["x"][i], pts["y"][i], pts["z"][i]) = (float(v) * 1e-3 for v in c["position_mm"])
                (pts["fx"][i], pts["fy"][i], pts["fz"][i]) = (float(v) for v in c["force_n"])
                pts["force"][i] = float(c["force_mag_n"])
                pts["area"][i] = float(c["area_mm2"]) * 1e-6
                pts["id"][i] = int(c["id"])
            return cdr.point_cloud2(self.stamp(t), self.frame_id, pts)
        return self._send("contacts", build)

    def publish_fields(self, fields: np.ndarray, seq: int, t: float) -> bool:
        """Images of the chosen channels; the surface cloud on every `surface_every`-th call."""
        cfg = self.node.config
        ok = True
        for ch in cfg.images:
            i = CHANNELS.index(ch)
            ok &= self._send(f"image/{ch}", lambda i=i: cdr.image_32fc1(
                self.stamp(t), self.frame_id, np.asarray(fields[i], np.float32) * SI_SCALE[CHANNEL_UNITS[i]]))
        if cfg.surface_every and self._fields_frames % cfg.surface_every == 0:
            ok &= self._send("surface", lambda: cdr.point_cloud2(self.stamp(t), self.frame_id,
                                                                 self.surface_points(fields)))
        self._fields_frames += 1
        return bool(ok)

    def surface_points(self, fields: np.ndarray) -> np.ndarray:
        """Gel surface points (m) inside the calibrated mask with every field channel in SI."""
        cal = self.calibration() if self.calibration is not None else None
        if cal is None:
            raise rw.Ros2Error("surface cloud needs the calibration (surface_xyz, mask)")
        step = self.node.config.surface_step
        xyz = np.asarray(cal.surface_xyz)[::step, ::step]
        mask = np.asarray(cal.mask, bool)[::step, ::step]
        f = np.asarray(fields)[:, ::step, ::step]
        if f.shape[1:] != mask.shape:
            raise rw.Ros2Error(f"surface cloud: fields {np.asarray(fields).shape} do not match the "
                               f"calibration's model size {tuple(np.asarray(cal.mask).shape)}")
        pts = np.zeros(int(mask.sum()), SURFACE_DTYPE)
        for k, axis in enumerate("xyz"):
            pts[axis] = xyz[..., k][mask] * 1e-3
        for i, ch in enumerate(CHANNELS):
            pts[ch] = f[i][mask] * SI_SCALE[CHANNEL_UNITS[i]]
        return pts

    def publish_status(self, status: dict, seq: int | None = None, t: float | None = None) -> bool:
        """A DiagnosticArray with this sensor's status, and the sensor frame on /tf."""
        t = time.time() if t is None else self.stamp(t)
        cfg = self.node.config

        def diag():
            flags = sorted(str(f) for f in (status.get("flags") or ()))
            level = (cdr.DIAG_ERROR if ERROR_FLAGS.intersection(flags)
                     else cdr.DIAG_WARN if flags else cdr.DIAG_OK)
            state = str(status.get("state") or "")
            values = [("sensor_id", self.sensor_id), ("state", state), ("flags", ",".join(flags))]
            for k in ("fps", "frames", "finger", "hand", "model", "model_hash", "calibration_version"):
                if status.get(k) is not None:
                    values.append((k, str(status[k])))
            values += [(f"timing_ms/{k}", f"{v:.3f}") for k, v in (status.get("timings_ms") or {}).items()
                       if isinstance(v, (int, float))]
            message = state + (f" ({', '.join(flags)})" if flags else "")
            return cdr.diagnostic_array(t, [cdr.DiagnosticStatus(
                level, f"tensortouch/{self.sensor_id}", message, self.sensor_id, tuple(values))])

        a = self._send("diagnostics", diag, self.node.diagnostics)
        b = self._send("tf", lambda: cdr.tf_message([cdr.Transform(
            t, cfg.parent_frame, self.frame_id, tuple(cfg.mount_xyz_m), tuple(cfg.mount_xyzw))]), self.node.tf)
        return a and b

    def _send(self, name: str, build: Callable[[], bytes], topic: _Topic | None = None) -> bool:
        topic = topic or self.topics.get(name)
        if topic is None:
            return False
        try:
            if self._closed:
                raise rw.Ros2Error("ROS 2 publisher is closed")
            topic.put(build())
            return True
        except Exception as exc:  # noqa: BLE001 - the frame loop must go on
            topic.errors += 1
            if topic.errors == 1 or topic.errors % self._log_every == 0:
                log.warning("sensor %s: ROS 2 %s not published (%d so far): %s", self.sensor_id,
                            topic.topic, topic.errors, exc)
            return False

    def stats(self) -> dict:
        return {t.topic: {"sent": t.sent, "errors": t.errors} for t in self.topics.values()}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for t in self.topics.values():
            t.close()
