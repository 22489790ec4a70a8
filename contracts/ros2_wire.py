"""rmw_zenoh's wire conventions, pure (docs/wire.md "ROS 2"): data keys, liveliness tokens, QoS
strings, the per-message attachment, ROS names and the type hashes of the published types.

No zenoh import: runtime/apps/ros2_publisher.py declares what these functions name.

- data key: `<domain>/<topic without leading slash>/<DDS type>/<type hash>`;
- liveliness token of a node:
  `@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>`;
- of a publisher: `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP/<enclave>/<namespace>/<node>/
  <topic>/<DDS type>/<type hash>/<qos>`, where `/` inside a name is written `%` (the root namespace
  and enclave `/` become `%`);
- attachment of every message (33 bytes): int64 LE sequence number, int64 LE source time in ns,
  the GID length as one LEB128 byte (16) and the 16-byte GID.
"""
from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass

from .errors import TensorTouchError

ADMIN_SPACE = "@ros2_lv"
DISTROS = ("humble", "jazzy", "kilted", "rolling")
HUMBLE_HASH = "TypeHashNotSupported"     # rmw_zenoh on humble: no type description hashes
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE

# RIHS01 hashes of the published types. The same for jazzy, kilted and rolling (checked against
# rosbags' hash computation for each in tests/test_ros2_cdr.py).
TYPES = {
    "geometry_msgs/msg/WrenchStamped":
        "RIHS01_8dc3deaf06b2ab281f9f9a742a8961c328ca7cec16e3fd6586d3a5c83fa78f77",
    "sensor_msgs/msg/Image":
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/PointCloud2":
        "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5",
    "diagnostic_msgs/msg/DiagnosticArray":
        "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
    "tf2_msgs/msg/TFMessage":
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
}

# rmw QoS enum values as rmw_zenoh writes them in tokens (empty = the rmw default)
RELIABILITY = {"reliable": 1, "best_effort": 2}
DEFAULT_DEPTH = 10

_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class Ros2Error(TensorTouchError):
    """A ROS 2 option (distro, domain, namespace, topic, QoS) is not valid."""


def check_distro(distro: str) -> str:
    if distro not in DISTROS:
        raise Ros2Error(f"ROS 2 distro {distro!r}: expected one of {', '.join(DISTROS)}")
    return distro


def check_domain(domain) -> int:
    try:
        d = int(domain)
    except (TypeError, ValueError):
        raise Ros2Error(f"ROS_DOMAIN_ID {domain!r}: expected an integer 0-232") from None
    if not 0 <= d <= 232:
        raise Ros2Error(f"ROS_DOMAIN_ID {d}: expected 0-232")
    return d


def check_name(name: str, what: str = "topic") -> str:
    """An absolute ROS name (`/a/b_c`): tokens of letters, digits, `_`, not starting with a digit."""
    if name == "/" and what == "namespace":
        return name
    parts = name.split("/") if isinstance(name, str) else [""]
    if not name.startswith("/") or name.endswith("/") or not all(_TOKEN.match(p) for p in parts[1:]):
        raise Ros2Error(f"ROS {what} {name!r}: expected an absolute name like /tensortouch/left "
                        "(tokens of letters, digits and _, not starting with a digit)")
    return name


def name_token(text: str) -> str:
    """A sensor id (`TT-0001`, `dome.1`) as one ROS name token / frame name: other characters
    become `_`, and a leading digit gets an `s` in front (`TT_0001`, `dome_1`, `s01`)."""
    tok = re.sub(r"[^A-Za-z0-9_]", "_", str(text))
    return tok if tok and not tok[0].isdigit() else "s" + tok


def join(namespace: str, *tokens: str) -> str:
    base = "" if namespace == "/" else namespace
    return "/".join([base, *tokens])


def dds_type(ros_type: str) -> str:
    """`pkg/msg/Name` -> `pkg::msg::dds_::Name_`."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def type_hash(ros_type: str, distro: str) -> str:
    check_distro(distro)
    if ros_type not in TYPES:
        raise Ros2Error(f"ROS type {ros_type!r}: not one the runtime publishes ({', '.join(TYPES)})")
    return HUMBLE_HASH if distro == "humble" else TYPES[ros_type]


def data_key(domain: int, topic: str, ros_type: str, distro: str) -> str:
    return f"{check_domain(domain)}/{check_name(topic).strip('/')}/{dds_type(ros_type)}/{type_hash(ros_type, distro)}"


def mangle(name: str) -> str:
    """A name inside one token chunk: `/` -> `%` (so `/` alone, the root, is `%`)."""
    return name.replace("/", "%") if name else "%"


@dataclass(frozen=True)
class Qos:
    """The QoS a publisher announces. Only volatile durability (no late-joiner cache)."""
    reliability: str = "reliable"
    depth: int = DEFAULT_DEPTH

    def __post_init__(self):
        if self.reliability not in RELIABILITY:
            raise Ros2Error(f"ROS 2 QoS reliability {self.reliability!r}: expected one of "
                            f"{', '.join(RELIABILITY)}")
        if not 1 <= int(self.depth) <= 10000:
            raise Ros2Error(f"ROS 2 QoS depth {self.depth!r}: expected 1-10000 (keep last N)")

    def token(self) -> str:
        """rmw_zenoh's QoS chunk: `<rel>:<dur>:<hist>,<depth>:<deadline s,ns>:<lifespan s,ns>:
        <liveliness kind,s,ns>`, each member empty when it is the rmw default; the depth is always
        written. Reliable keep-last-10 is `::,10:,:,:,,`."""
        rel = "" if self.reliability == "reliable" else str(RELIABILITY[self.reliability])
        return f"{rel}::,{int(self.depth)}:,:,:,,"


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str, enclave: str = "/") -> str:
    return "/".join([ADMIN_SPACE, str(check_domain(domain)), zid, str(node_id), str(node_id), "NN",
                     mangle(enclave), mangle(namespace), node])


def publisher_token(domain: int, zid: str, node_id: int, entity_id: int, namespace: str, node: str,
                    topic: str, ros_type: str, distro: str, qos: Qos, enclave: str = "/") -> str:
    return "/".join([ADMIN_SPACE, str(check_domain(domain)), zid, str(node_id), str(entity_id), "MP",
                     mangle(enclave), mangle(namespace), node, mangle(check_name(topic)),
                     dds_type(ros_type), type_hash(ros_type, distro), qos.token()])


def gid_of(token: str) -> bytes:
    """A 16-byte publisher GID derived from its liveliness token (stable for the same token)."""
    return hashlib.blake2b(token.encode(), digest_size=GID_SIZE).digest()


def attachment(seq: int, t_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment rmw_zenoh requires on every message."""
    if len(gid) != GID_SIZE:
        raise Ros2Error(f"GID: expected {GID_SIZE} bytes, got {len(gid)}")
    return struct.pack("<qqB", int(seq), int(t_ns), GID_SIZE) + bytes(gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source time ns, GID) from an rmw_zenoh attachment."""
    if len(data) != ATTACHMENT_SIZE or data[16] != GID_SIZE:
        raise Ros2Error(f"rmw_zenoh attachment: expected {ATTACHMENT_SIZE} bytes with GID length "
                        f"{GID_SIZE}, got {len(data)} bytes")
    seq, t_ns = struct.unpack_from("<qq", data)
    return seq, t_ns, bytes(data[17:])
