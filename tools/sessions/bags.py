"""ROS1 / ROS2 bags (rosbags) and MCAP files (mcap) -> a session directory, by a topic mapping.

Mapping file (JSON or TOML), e.g.:

    sensor_id = "TT-0007"
    clock = "header"                 # "header" (msg.header.stamp) or "log" (bag receive time)
    frames_format = "png"            # png (lossless folder) | ffv1 | mjpg
    [units]                          # units of the bag; converted to mm, N, N*mm, degC
    length = "m"                     # m | mm
    torque = "N*m"                   # N*m | N*mm
    temperature = "degC"             # degC | K
    [ft_to_indenter]                 # p_indenter = R p_ft + t (docs/session.md)
    rotation_wxyz = [1, 0, 0, 0]
    translation_mm = [0, 0, 44]
    [frames]
    topic = "/tactile/image/compressed"          # sensor_msgs Image or CompressedImage
    [[poses]]
    topic = "/mocap/indenter0"                   # PoseStamped, TransformStamped or Pose
    indenter = 0
    base_topic = "/mocap/sensor"                 # optional: poses are made relative to this one
    [[wrench]]
    topic = "/ati0/wrench"                       # WrenchStamped or Wrench
    indenter = 0
    [temperature]
    topic = "/gel/temperature"                   # sensor_msgs Temperature or std_msgs Float64

Time zero is the first mapped message. MCAP messages are decoded by encoding: "cdr" (ROS 2,
with the rosbags typestore, registering the file's schema when the type is unknown), "ros1"
and "json" (fields as in the ROS message, e.g. {"header": {"stamp": {"sec":..,"nanosec":..}}, ...}).
"""
from __future__ import annotations

import json
import logging
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ...contracts.errors import SessionError
from ...contracts.names import NAME_PATTERN, is_name
from ...contracts.session import load_session
from ...contracts.units import accepted, to_house
from .writer import SessionWriter

log = logging.getLogger(__name__)
BAG_UNITS = {"length": "m", "torque": "N*m", "temperature": "degC"}   # ROS conventions (REP 103)


@dataclass
class TopicMap:
    sensor_id: str
    frames: dict
    poses: list = field(default_factory=list)
    wrench: list = field(default_factory=list)
    temperature: dict | None = None
    units: dict = field(default_factory=dict)
    clock: str = "header"
    frames_format: str = "png"
    ft_to_indenter: dict = field(default_factory=lambda: {"rotation_wxyz": [1.0, 0.0, 0.0, 0.0],
                                                         "translation_mm": [0.0, 0.0, 0.0]})

    @classmethod
    def load(cls, path_or_dict) -> "TopicMap":
        if isinstance(path_or_dict, dict):
            data, where = path_or_dict, "topic map"
        else:
            p = Path(path_or_dict)
            where = str(p)
            try:
                text = p.read_bytes().decode("utf-8")
                data = tomllib.loads(text) if p.suffix == ".toml" else json.loads(text)
            except UnicodeDecodeError as exc:
                raise SessionError(f"{p}: topic map is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
            except (OSError, ValueError, RecursionError) as exc:
                raise SessionError(f"{p}: cannot read topic map ({str(exc)[:200]})") from None
        if not isinstance(data, dict):
            raise SessionError(f"{where}: expected a table/object of keys, got {type(data).__name__}")
        known = set(cls.__dataclass_fields__)
        unknown = set(data) - known
        if unknown:
            raise SessionError(f"{where}: unknown keys {sorted(unknown)} (known: {sorted(known)})")
        if "sensor_id" not in data or not isinstance(data.get("frames"), dict) or "topic" not in data["frames"]:
            raise SessionError(f"{where}: needs sensor_id and frames.topic")
        _check_map_types(data, where)
        m = cls(**data)
        if m.clock not in ("header", "log"):
            raise SessionError(f"{where}: clock must be 'header' or 'log', got {m.clock!r}")
        for key, default in BAG_UNITS.items():
            if to_house(key, m.units.get(key, default)) is None:
                raise SessionError(f"{where}: units.{key} {m.units[key]!r} not one of {accepted(key)}")
        return m

    def topics(self) -> dict[str, tuple]:
        """topic → (stream, indenter id); a topic mapped twice is an error."""
        out = {self.frames["topic"]: ("frames", None)}
        for p in self.poses:
            out[p["topic"]] = ("poses", int(p["indenter"]))
            if p.get("base_topic"):
                out[p["base_topic"]] = ("base", None)
        for w in self.wrench:
            out[w["topic"]] = ("wrench", int(w["indenter"]))
        if self.temperature:
            out[self.temperature["topic"]] = ("temperature", None)
        return out


def _check_map_types(data: dict, where: str) -> None:
    """Types of every topic-map field, each error naming the field and what was expected."""
    def fail(field_, want):
        raise SessionError(f"{where}: {field_} must be {want}")

    def topic_entry(entry, name, indenter):
        if not isinstance(entry, dict):
            fail(name, "a table/object with a topic")
        if not isinstance(entry.get("topic"), str) or not entry["topic"]:
            fail(f"{name}.topic", "a topic name string")
        if indenter:
            ind = entry.get("indenter")
            if ind is None:
                fail(f"{name}.indenter", "given (the indenter id, an integer >= 0)")
            if not isinstance(ind, int) or isinstance(ind, bool) or ind < 0:
                fail(f"{name}.indenter", f"an integer >= 0, not {ind!r}")
        if "base_topic" in entry and entry["base_topic"] is not None and not isinstance(entry["base_topic"], str):
            fail(f"{name}.base_topic", "a topic name string")

    if not is_name(data["sensor_id"]):      # it becomes a store folder and a Zenoh key chunk
        fail("sensor_id", f"a sensor id matching {NAME_PATTERN}, not {str(data['sensor_id'])[:80]!r}")
    topic_entry(data["frames"], "frames", False)
    for kind in ("poses", "wrench"):
        entries = data.get(kind, [])
        if not isinstance(entries, list):
            fail(kind, "a list of tables ([[poses]] in TOML) with topic and indenter")
        for i, e in enumerate(entries):
            topic_entry(e, f"{kind}[{i}]", True)
    if data.get("temperature") is not None:
        topic_entry(data["temperature"], "temperature", False)
    for key in ("clock", "frames_format"):
        if key in data and not isinstance(data[key], str):
            fail(key, "a string")
    units = data.get("units", {})
    if not isinstance(units, dict) or not all(isinstance(v, str) for v in units.values()):
        fail("units", "a table of unit strings, e.g. {length = \"m\"}")
    ft = data.get("ft_to_indenter")
    if ft is not None:
        nums = lambda v, n: (isinstance(v, list) and len(v) == n
                             and all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x)
                                     for x in v))
        if not isinstance(ft, dict) or not nums(ft.get("rotation_wxyz"), 4) or not nums(ft.get("translation_mm"), 3):
            fail("ft_to_indenter", "rotation_wxyz (4 numbers) and translation_mm (3 numbers)")


def _stamp(msg, log_ns: int, clock: str) -> float:
    if clock == "header" and hasattr(msg, "header"):
        st = msg.header.stamp
        return float(st.sec) + 1e-9 * float(getattr(st, "nanosec", getattr(st, "nsec", 0)))
    return log_ns * 1e-9


def _pose(msg) -> np.ndarray:
    if hasattr(msg, "transform"):
        p, q = msg.transform.translation, msg.transform.rotation
    else:
        pose = msg.pose if hasattr(msg, "pose") else msg
        p, q = pose.position, pose.orientation
    return np.array([p.x, p.y, p.z, q.w, q.x, q.y, q.z], dtype=np.float64)


def _wrench(msg) -> np.ndarray:
    w = msg.wrench if hasattr(msg, "wrench") else msg
    return np.array([w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z], dtype=np.float64)


def _image(msg) -> np.ndarray:
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if hasattr(msg, "format"):  # CompressedImage
        img = cv2.imdecode(data, cv2.IMREAD_COLOR)
        if img is None:
            raise SessionError(f"compressed image ({msg.format}) could not be decoded")
        return img
    enc = str(msg.encoding).lower()
    h, w = int(msg.height), int(msg.width)
    if enc in ("bgr8", "rgb8"):
        img = data.reshape(h, int(msg.step))[:, :w * 3].reshape(h, w, 3)
        return img[..., ::-1].copy() if enc == "rgb8" else img.copy()
    if enc in ("mono8", "8uc1"):
        return cv2.cvtColor(data.reshape(h, int(msg.step))[:, :w].copy(), cv2.COLOR_GRAY2BGR)
    raise SessionError(f"image encoding {msg.encoding!r} not supported (bgr8, rgb8, mono8)")


def _temperature(msg) -> float:
    return float(msg.temperature if hasattr(msg, "temperature") else msg.data)


def _ns(obj):
    """JSON dict -> attribute access like a deserialized ROS message."""
    if isinstance(obj, dict):
        return SimpleNamespace(**{k: _ns(v) for k, v in obj.items()})
    if isinstance(obj, list) and obj and isinstance(obj[0], dict):
        return [_ns(v) for v in obj]
    return obj


def iter_rosbag(path: Path, topics: set[str]):
    """(topic, log_ns, msg) from a ROS1 .bag or a ROS2 bag folder (rosbags AnyReader)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, t, raw in reader.messages(connections=conns):
            yield conn.topic, t, reader.deserialize(raw, conn.msgtype)


def iter_mcap(path: Path, topics: set[str]):
    """(topic, log_ns, msg) from an MCAP file (cdr / ros1 / json message encodings)."""
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages(topics=sorted(topics)):
            enc = channel.message_encoding
            if enc == "json":
                msg = _ns(json.loads(message.data))
            elif enc in ("cdr", "ros1"):
                name = schema.name if "/msg/" in schema.name else schema.name.replace("/", "/msg/", 1)
                if name not in ts.types:
                    ts.register(get_types_from_msg(schema.data.decode(), name))
                msg = ts.deserialize_cdr(message.data, name) if enc == "cdr" else ts.deserialize_ros1(message.data, name)
            else:
                raise SessionError(f"{path}: channel {channel.topic} has message encoding {enc!r} "
                                   "(supported: cdr, ros1, json)")
            yield channel.topic, message.log_time, msg


def _relative(pose: np.ndarray, t: np.ndarray, base: np.ndarray | None) -> np.ndarray:
    """Poses (n,7) made relative to the base pose (nearest earlier-or-equal base sample)."""
    if base is None or not len(base):
        return pose
    idx = np.clip(np.searchsorted(base[:, 0], t, side="right") - 1, 0, len(base) - 1)
    b = base[idx, 1:]
    Rb = Rotation.from_quat(b[:, [4, 5, 6, 3]])
    Rp = Rotation.from_quat(pose[:, [4, 5, 6, 3]])
    p = Rb.inv().apply(pose[:, :3] - b[:, :3])
    q = (Rb.inv() * Rp).as_quat()[:, [3, 0, 1, 2]]
    return np.column_stack([p, q])


def convert(bag: str | Path, mapping: TopicMap, out: str | Path) -> Path:
    """Read a ROS1 .bag, ROS2 bag folder or .mcap file and write a session with `mapping`."""
    bag = Path(bag)
    if not bag.exists():
        raise SessionError(f"{bag}: bag not found")
    topics = mapping.topics()
    out = Path(out)
    try:
        _convert(bag, mapping, topics, out)
    except SessionError:
        raise
    except Exception as exc:  # noqa: BLE001 - bag/MCAP/CDR decoders raise their own types on corrupt input
        what = "MCAP file" if bag.suffix == ".mcap" else "ROS bag"
        raise SessionError(f"{bag}: cannot read as a {what} with this topic map ({type(exc).__name__}: "
                           f"{_first_line(exc)})") from None
    try:                                   # the same check as `tensortouch session check`
        load_session(out)
    except SessionError as exc:
        (out / "session.json").unlink(missing_ok=True)
        raise SessionError(f"{bag}: the converted recording fails the session check, so {out} was not "
                           f"made a session: {exc}") from None
    return out


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else "no detail"


def _convert(bag: Path, mapping: TopicMap, topics: dict, out: Path) -> None:
    it = iter_mcap(bag, set(topics)) if bag.suffix == ".mcap" else iter_rosbag(bag, set(topics))
    (L, _), (TQ, _), (TS, T0) = (to_house(k, mapping.units.get(k, d)) for k, d in BAG_UNITS.items())
    rows: dict = {"poses": [], "wrench": [], "temperature": [], "base": [], "frames": []}
    writer = SessionWriter(out, mapping.sensor_id, mapping.frames_format)
    seen = set()
    for topic, log_ns, msg in it:
        kind, ind = topics[topic]
        seen.add(topic)
        t = _stamp(msg, log_ns, mapping.clock)
        if kind in ("poses", "base"):
            v = _pose(msg)
            v[:3] *= L
            rows[kind].append((t, -1 if ind is None else ind, *v))
        elif kind == "wrench":
            v = _wrench(msg)
            v[3:] *= TQ
            rows[kind].append((t, ind, *v))
        elif kind == "temperature":
            c = _temperature(msg)
            rows[kind].append((t, c * TS + T0))
        else:
            writer.frame(len(rows["frames"]), _image(msg))
            rows["frames"].append(t)
    missing = sorted(set(topics) - seen)
    if missing:
        raise SessionError(f"{bag}: mapped topic(s) {missing} have no messages (missing stream)")
    t0 = min(min(r[0] for r in v) if kind != "frames" else min(v) for kind, v in rows.items() if v)
    base = np.array(rows["base"], dtype=np.float64).reshape(-1, 9)[:, [0, 2, 3, 4, 5, 6, 7, 8]] if rows["base"] else None
    if base is not None:
        base[:, 0] -= t0
        base = base[np.argsort(base[:, 0], kind="stable")]
    ft = np.array(rows["frames"]) - t0
    order = np.argsort(ft, kind="stable")
    if np.any(order != np.arange(len(ft))):
        raise SessionError(f"{bag}: image messages are out of time order (non-monotonic clock)")
    for name in ("poses", "wrench"):
        if rows[name]:
            a = np.array(rows[name], dtype=np.float64)
            a[:, 0] -= t0
            a = a[np.lexsort((a[:, 1], a[:, 0]))]
            if name == "poses" and base is not None:
                a[:, 2:] = _relative(a[:, 2:], a[:, 0], base)
            info = {"source_topics": sorted(t for t, (k, _) in topics.items() if k == name)}
            if name == "wrench":
                info.update(frame="ft", ft_to_indenter=mapping.ft_to_indenter)
            writer.table(name, a, **info)
    if rows["temperature"]:
        a = np.array(rows["temperature"], dtype=np.float64)
        a[:, 0] -= t0
        writer.table("temperature", a[np.argsort(a[:, 0], kind="stable")])
    fps = (len(ft) - 1) / (ft[-1] - ft[0]) if len(ft) > 1 and ft[-1] > ft[0] else 30.0
    writer.finish_frames(ft, fps)
    writer.finish({"source": "bag", "bag": str(bag), "topics": sorted(topics)},
                  {"source": mapping.clock, "t0_unix_s": t0, "unit": "s"})
