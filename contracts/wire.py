"""Zenoh wire format: key expressions, schemas and pure encode/decode (docs/wire.md). The key
expressions, schemas and JSON envelope live in contracts/wire_keys.py and are re-exported here.

No zenoh import here: these functions turn arrays and dataclasses into `bytes` (what zenoh-python
accepts as a payload) and back, so they can be unit-tested and reused by any transport.

Units on the wire: mm, N, MPa, N*mm, s. Every payload names its schema (`tensortouch.<kind>.v1`),
both in the Zenoh Encoding (`<mime>;<schema>`) and inside the payload/attachment; decoders reject
anything else with a `WireError` that says what arrived and what was expected.
"""
from __future__ import annotations

import functools
import json
import logging
import math
from dataclasses import dataclass, field
from dataclasses import fields as dc_fields
from typing import Any, Iterable, Sequence

import numpy as np

from .fields import CHANNEL_UNITS, CHANNELS
from .wire_keys import (  # noqa: F401 (the wire API)
    ALIVE,
    ENCODINGS,
    INFO,
    KEY_PREFIX,
    KINDS,
    MIME,
    SCHEMAS,
    WIRE_VERSION,
    NonFiniteError,
    WireError,
    alive_key,
    check_sensor_id,
    info_key,
    key,
    parse_key,
    schema_of,
)
from .wire_keys import check_encoding as _check_encoding
from .wire_keys import dumps as _dumps
from .wire_keys import loads as _loads
from .wire_keys import need as _need

log = logging.getLogger(__name__)

FIELDS_DTYPE = "<f2"                  # little-endian IEEE half precision
FLOAT16_MAX = float(np.finfo(np.float16).max)  # 65504: larger magnitudes are clipped and flagged

_HALF = np.dtype(FIELDS_DTYPE)
_HALF_SIGN, _HALF_ABS, _HALF_INF, _HALF_MAX_BITS = 0x8000, 0x7FFF, 0x7C00, 0x7BFF
SEQ_MAX = 2**63 - 1                   # seq, id and age_frames are non-negative 64-bit integers on the wire


# --------------------------------------------------------------------------- received numbers

def _number(kind: str, name: str, value: Any) -> float:
    """A received JSON number as a finite float: a string, bool or list is a WireError; NaN, infinity
    or an integer beyond the float range is a NonFiniteError (the message is dropped and counted)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise WireError(f"{kind} field {name!r}: expected a number, got {str(value)[:40]!r}")
    try:
        out = float(value)
    except OverflowError:
        raise NonFiniteError(f"{kind} field {name!r}: integer beyond the float range") from None
    if not math.isfinite(out):
        raise NonFiniteError(f"{kind} field {name!r}: non-finite number {out}")
    return out


def _integer(kind: str, name: str, value: Any) -> int:
    """A received JSON integer in 0..SEQ_MAX (seq, ids, ages)."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= SEQ_MAX:
        raise WireError(f"{kind} field {name!r}: expected an integer 0..2^63-1, got {str(value)[:40]!r}")
    return value


def _strings(kind: str, name: str, value: Any) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise WireError(f"{kind} field {name!r}: expected a list of strings")
    return tuple(value)


# --------------------------------------------------------------------------- fields


def _received_id(kind: str, obj: dict) -> str:
    """The `sensor_id` of a received payload, checked against the id pattern (docs/wire.md Keys)."""
    sensor_id = _need(kind, obj, "sensor_id")
    try:
        return check_sensor_id(sensor_id)
    except WireError as exc:
        raise WireError(f"{kind} payload: {exc}") from None

@dataclass(frozen=True)
class FieldsFrame:
    """One decoded field image: float32 (C, H, W) in the units of `units`, channel order `channels`."""
    sensor_id: str
    seq: int
    t: float
    data: np.ndarray
    channels: tuple[str, ...] = CHANNELS
    units: tuple[str, ...] = CHANNEL_UNITS
    clipped: tuple[str, ...] = ()      # channels that exceeded +-65504 and were clipped

    def channel(self, name: str) -> np.ndarray:
        try:
            return self.data[self.channels.index(name)]
        except ValueError:
            raise WireError(f"fields: no channel {name!r}; channels are {self.channels}") from None


def to_float16(arr: np.ndarray) -> np.ndarray:
    """Bit-identical to `arr.astype(float16)` (round to nearest even, overflow → ±inf, NaN as NaN), through
    OpenCV's vectorized conversion for float32 input: numpy's cast takes a slow path for values that
    become float16 subnormals (|x| < 6.1e-5, common for stresses in MPa) — measured 10 ms vs 0.05 ms
    for a 15×128×128 field (docs/runtime.md "Speed"). NaN stays NaN (its payload bits may differ from
    numpy's; encode_fields refuses NaN anyway)."""
    if arr.dtype == np.float32 and arr.size and arr.ndim >= 1:
        try:
            import cv2

            a = np.ascontiguousarray(arr)
            # x - 0.0 == x for every float32 (signed zeros, infinities and NaN too), so this is OpenCV's
            # plain float32 -> float16 conversion; it runs ~3x faster than multiply(a, 1.0, dtype=CV_16F)
            return cv2.subtract(a.reshape(-1, a.shape[-1]), 0.0, dtype=cv2.CV_16F).reshape(a.shape)
        except Exception:  # noqa: BLE001 - fall back to numpy (same bits, slower)
            pass
    with np.errstate(over="ignore", invalid="ignore"):
        return arr.astype(_HALF)


def encode_fields(fields: np.ndarray, seq: int, t: float, sensor_id: str,
                  channels: Sequence[str] = CHANNELS,
                  units: Sequence[str] = CHANNEL_UNITS) -> tuple[bytes, bytes, tuple[str, ...]]:
    """(C, H, W) float array -> (payload, attachment, clipped channel names).

    Payload: C*H*W little-endian float16, C-order. Attachment: compact JSON header (schema, sensor id,
    seq, t, shape, dtype, channels, units, clipped). |x| > 65504 (and +-inf) is clipped to +-65504
    and the channel is listed in `clipped`; NaN is refused with a WireError naming the channels
    (receivers drop a frame holding NaN).
    """
    arr = np.asarray(fields)
    if arr.ndim != 3 or arr.shape[0] != len(channels) or len(units) != len(channels):
        raise WireError(f"fields: expected shape (C={len(channels)}, H, W) with {len(channels)} "
                        f"channel names and units, got shape {arr.shape}, {len(units)} units")
    half = to_float16(arr)
    # NaN / overflow tests on the bit pattern (float16 arithmetic in numpy is slow): |x| bits > inf is NaN,
    # == inf is ±inf. One pass over the largest |x| pattern first: a finite frame (the rule) stops there.
    bits = half.view(np.uint16)
    clipped: tuple[str, ...] = ()
    if int(np.bitwise_and(bits, _HALF_ABS).max(initial=0)) >= _HALF_INF:
        nan = (bits & _HALF_ABS) > _HALF_INF
        if nan.any():
            bad = nan.reshape(nan.shape[0], -1).any(axis=1)
            raise WireError(f"fields: NaN in channel(s) {[n for n, b in zip(channels, bad) if b]} cannot be sent")
        over = (bits & _HALF_ABS) == _HALF_INF
        bad = over.reshape(over.shape[0], -1).any(axis=1)
        clipped = tuple(name for name, b in zip(channels, bad) if b)
        bits[over] = (bits[over] & _HALF_SIGN) | _HALF_MAX_BITS   # +-inf -> +-65504
    sensor_id, seq, t = check_sensor_id(sensor_id), int(seq), float(t)
    if not math.isfinite(t):
        raise WireError(f"non-finite number {t} cannot be sent as JSON")
    head, middle, tail = _fields_header_parts(sensor_id, tuple(arr.shape), tuple(channels), tuple(units))
    clip = _CLIPPED_NONE if not clipped else json.dumps(list(clipped), separators=(",", ":"))
    # json.dumps writes an int with int.__repr__ and a finite float with float.__repr__
    header = f"{head}{int.__repr__(seq)}{middle}{float.__repr__(t)}{tail}{clip}}}"
    return half.tobytes(), header.encode(), clipped


_CLIPPED_NONE = "[]"


@functools.lru_cache(maxsize=256)
def _fields_header_parts(sensor_id: str, shape: tuple, channels: tuple, units: tuple) -> tuple[str, str, str]:
    """The fields header's JSON text around seq, t and clipped, for one sensor, shape and channel list:
    (up to `"seq":`, `,"t":`, from `,"shape":` up to `"clipped":`). Joined with the numbers they are the
    bytes of json.dumps(header, separators=(",", ":")) with the members in the order of docs/wire.md."""
    def dump(value) -> str:
        return json.dumps(value, separators=(",", ":"))

    head = f'{{"schema":{dump(SCHEMAS["fields"])},"sensor_id":{dump(sensor_id)},"seq":'
    tail = (f',"shape":{dump([int(n) for n in shape])},"dtype":{dump(FIELDS_DTYPE)},"channels":{dump(list(channels))},'
            f'"units":{dump(list(units))},"clipped":')
    return head, ',"t":', tail


def decode_fields(payload: bytes | bytearray, attachment: bytes | bytearray | str | None,
                  encoding: Any = None, max_shape: tuple[int, int, int] | None = None) -> FieldsFrame:
    """Payload + attachment (+ optional Encoding) -> FieldsFrame with float32 data. With `max_shape`
    (C, H, W), a larger frame is refused before its data is converted (a receiver's memory bound)."""
    _check_encoding("fields", encoding)
    if attachment is None:
        raise WireError("fields: missing attachment (the JSON header with seq, t, shape, channels)")
    head = _loads("fields", attachment)
    shape = _need("fields", head, "shape")
    if not isinstance(shape, list):
        raise WireError(f"fields: shape must be a list of integers, got {str(shape)[:40]!r}")
    shape = tuple(_integer("fields", "shape", n) for n in shape)
    channels = _strings("fields", "channels", _need("fields", head, "channels"))
    units = _strings("fields", "units", _need("fields", head, "units"))
    if head.get("dtype", FIELDS_DTYPE) != FIELDS_DTYPE:
        raise WireError(f"fields: dtype {head.get('dtype')!r}, expected {FIELDS_DTYPE!r}")
    if len(shape) != 3 or shape[0] != len(channels) or len(units) != len(channels) or min(shape) < 1:
        raise WireError(f"fields: shape {shape} does not match {len(channels)} channels / "
                        f"{len(units)} units (every size >= 1)")
    if max_shape is not None and any(n > m for n, m in zip(shape, max_shape)):
        raise WireError(f"fields: shape {shape} exceeds this receiver's limit {tuple(max_shape)}")
    expected = 2 * shape[0] * shape[1] * shape[2]
    if len(payload) != expected:
        raise WireError(f"fields: payload is {len(payload)} bytes, expected {expected} "
                        f"(float16 x {shape})")
    sensor_id = _received_id("fields", head)
    seq = _integer("fields", "seq", _need("fields", head, "seq"))
    t = _number("fields", "t", _need("fields", head, "t"))
    clipped = _strings("fields", "clipped", head.get("clipped", []))
    half = np.frombuffer(payload, dtype=_HALF)
    # NaN and +-inf are the float16 patterns with all exponent bits set
    bad = int(np.count_nonzero((half.view(np.uint16) & _HALF_INF) == _HALF_INF))
    if bad:
        raise NonFiniteError(f"fields: {bad} non-finite value(s) (NaN/inf) in the payload")
    data = half.reshape(shape).astype(np.float32)
    return FieldsFrame(sensor_id=sensor_id, seq=seq, t=t, data=data, channels=channels, units=units,
                       clipped=clipped)


# --------------------------------------------------------------------------- contacts

def _vec(value: Any, n: int, name: str, kind: str = "contact") -> tuple[float, ...]:
    """`n` finite numbers from a received list (see _number)."""
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise WireError(f"{kind} field {name!r}: expected {n} numbers, got {str(value)[:60]!r}")
    return tuple(_number(kind, name, v) for v in value)


def _local_vec(value: Any, n: int, name: str) -> tuple[float, ...]:
    """`n` numbers from the sending side (numpy arrays and scalars welcome)."""
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise WireError(f"field {name!r}: expected {n} numbers, got {value!r}") from None
    if len(out) != n:
        raise WireError(f"field {name!r}: expected {n} numbers, got {len(out)}")
    return out


@dataclass
class Contact:
    """One contact cluster (seed §III.M). Positions mm, forces N, sensor frame (docs/fields.md)."""
    id: int                                   # stable across frames while the contact persists
    uv_px: tuple[float, float]                # pixel centroid (u = column, v = row), model grid
    position_mm: tuple[float, float, float]   # 3D centroid on the gel surface
    normal: tuple[float, float, float]        # unit outward surface normal at the centroid
    area_mm2: float
    force_n: tuple[float, float, float]       # total contact force (normal + shear)
    force_mag_n: float                        # |force_n|
    perimeter_px: float
    circularity: float                        # 4*pi*area/perimeter^2 in pixels, 1 = disc
    priority: float                           # ranking score, larger = more important
    age_frames: int                           # frames since this id first appeared

    _VECTORS = {"uv_px": 2, "position_mm": 3, "normal": 3, "force_n": 3}

    def to_dict(self) -> dict:
        out = {}
        for name in _CONTACT_FIELDS:
            value = getattr(self, name)
            if name in self._VECTORS:
                value = [float(v) for v in value]
            elif name in ("id", "age_frames"):
                value = int(value)
            else:
                value = float(value)
            out[name] = value
        if not all(math.isfinite(v) for n in _CONTACT_FIELDS
                   for v in (out[n] if isinstance(out[n], list) else (out[n],))):
            raise WireError(f"contact {self.id}: non-finite number cannot be sent as JSON: {out}")
        return out

    @classmethod
    def from_dict(cls, obj: dict) -> "Contact":
        if not isinstance(obj, dict):
            raise WireError(f"contact: expected a JSON object, got {type(obj).__name__}")
        names = _CONTACT_FIELDS
        missing = [n for n in names if n not in obj]
        if missing:
            raise WireError(f"contact: missing field(s) {missing}")
        kw: dict[str, Any] = {}
        for name in names:
            value = obj[name]
            if name in cls._VECTORS:
                kw[name] = _vec(value, cls._VECTORS[name], name)
            elif name in ("id", "age_frames"):
                kw[name] = _integer("contact", name, value)
            else:
                kw[name] = _number("contact", name, value)
        return cls(**kw)


CONTACT_FIELDS = tuple(f.name for f in dc_fields(Contact))   # the wire names; Cluster uses the same
_CONTACT_FIELDS = CONTACT_FIELDS


@dataclass(frozen=True)
class ContactsFrame:
    sensor_id: str
    seq: int
    t: float
    contacts: list[Contact] = field(default_factory=list)


def _local_contact(obj: Any) -> Contact:
    """A Contact from a dict on the sending side (numpy numbers welcome; to_dict checks finiteness)."""
    if not isinstance(obj, dict):
        raise WireError(f"contact: expected a Contact or a dict, got {type(obj).__name__}")
    missing = [n for n in CONTACT_FIELDS if n not in obj]
    if missing:
        raise WireError(f"contact: missing field(s) {missing}")
    return Contact(**{n: obj[n] for n in CONTACT_FIELDS})


def encode_contacts(contacts: Iterable[Contact | dict], seq: int, t: float, sensor_id: str) -> bytes:
    items = [(c if isinstance(c, Contact) else _local_contact(c)).to_dict() for c in contacts]
    body = {"schema": SCHEMAS["contacts"], "sensor_id": check_sensor_id(sensor_id),
            "seq": int(seq), "t": float(t), "contacts": items}
    return json.dumps(body, separators=(",", ":"), allow_nan=False).encode()  # items are plain


def decode_contacts(payload: bytes | bytearray | str, encoding: Any = None) -> ContactsFrame:
    _check_encoding("contacts", encoding)
    obj = _loads("contacts", payload)
    items = _need("contacts", obj, "contacts")
    if not isinstance(items, list):
        raise WireError("contacts payload: field 'contacts' must be a list")
    return ContactsFrame(sensor_id=_received_id("contacts", obj),
                         seq=_integer("contacts", "seq", _need("contacts", obj, "seq")),
                         t=_number("contacts", "t", _need("contacts", obj, "t")),
                         contacts=[Contact.from_dict(c) for c in items])


# --------------------------------------------------------------------------- wrench

@dataclass(frozen=True)
class Wrench:
    """Total contact force (N) and torque (N*mm) about the gel origin, sensor frame."""
    sensor_id: str
    seq: int
    t: float
    force_n: tuple[float, float, float]
    torque_nmm: tuple[float, float, float]


def wrench_from_contacts(contacts: Iterable[Contact]) -> tuple[np.ndarray, np.ndarray]:
    """Sum of cluster forces and of position x force about the gel origin: (F N, tau N*mm)."""
    force, torque = np.zeros(3), np.zeros(3)
    for c in contacts:
        f = np.asarray(c.force_n, dtype=float)
        force += f
        torque += np.cross(np.asarray(c.position_mm, dtype=float), f)
    return force, torque


def encode_wrench(force_n: Sequence[float], torque_nmm: Sequence[float], seq: int, t: float,
                  sensor_id: str) -> bytes:
    body = {"schema": SCHEMAS["wrench"], "sensor_id": check_sensor_id(sensor_id),
            "seq": int(seq), "t": float(t), "frame": "gel",
            "force_n": list(_local_vec(force_n, 3, "force_n")),
            "torque_nmm": list(_local_vec(torque_nmm, 3, "torque_nmm"))}
    # every member is a plain str / int / float already (what _dumps's `plain` would make of it); the first
    # non-finite number, in member order, is refused as `plain` refuses it
    for value in (body["t"], *body["force_n"], *body["torque_nmm"]):
        if not math.isfinite(value):
            raise WireError(f"non-finite number {value} cannot be sent as JSON")
    return json.dumps(body, separators=(",", ":"), allow_nan=False).encode()


def decode_wrench(payload: bytes | bytearray | str, encoding: Any = None) -> Wrench:
    _check_encoding("wrench", encoding)
    obj = _loads("wrench", payload)
    return Wrench(sensor_id=_received_id("wrench", obj), seq=_integer("wrench", "seq", _need("wrench", obj, "seq")),
                  t=_number("wrench", "t", _need("wrench", obj, "t")),
                  force_n=_vec(_need("wrench", obj, "force_n"), 3, "force_n", "wrench"),
                  torque_nmm=_vec(_need("wrench", obj, "torque_nmm"), 3, "torque_nmm", "wrench"))


# --------------------------------------------------------------------------- status and info

STATUS_FIELDS = ("state", "flags", "fps", "timings_ms", "model_hash", "calibration_version", "finger")


def encode_status(status: dict, seq: int, t: float, sensor_id: str) -> bytes:
    """Status dict (state, flags, fps, timings_ms, model_hash, calibration_version, finger, ...) -> JSON.

    Missing standard fields are sent as null / empty; extra keys pass through. Non-finite numbers
    become null (a status must always go out).
    """
    body: dict[str, Any] = {"schema": SCHEMAS["status"], "sensor_id": check_sensor_id(sensor_id),
                            "seq": int(seq), "t": float(t)}
    body.update({name: status.get(name) for name in STATUS_FIELDS})
    body["flags"] = sorted({str(f) for f in (status.get("flags") or ())})
    body["timings_ms"] = dict(status.get("timings_ms") or {})
    body.update({k: v for k, v in status.items() if k not in body})
    return _dumps(body, strict=False)


def decode_status(payload: bytes | bytearray | str, encoding: Any = None) -> dict:
    _check_encoding("status", encoding)
    obj = _loads("status", payload)
    for name in ("sensor_id", "seq", "t", "state", "flags", "timings_ms"):
        _need("status", obj, name)
    _received_id("status", obj)
    _integer("status", "seq", obj["seq"])
    _number("status", "t", obj["t"])
    if not isinstance(obj["flags"], list) or not isinstance(obj["timings_ms"], dict):
        raise WireError("status payload: 'flags' must be a list and 'timings_ms' an object")
    return obj


def encode_info(info: dict, sensor_id: str, runtime_version: str) -> bytes:
    """Sensor info (model name/hash, calibration version, bounds, ...) -> JSON for the queryable."""
    body: dict[str, Any] = {"schema": SCHEMAS[INFO], "sensor_id": check_sensor_id(sensor_id),
                            "channels": list(CHANNELS), "units": list(CHANNEL_UNITS)}
    body.update(info)
    body.update(schema=SCHEMAS[INFO], sensor_id=sensor_id, runtime_version=runtime_version,
                wire_version=WIRE_VERSION,
                keys={kind: key(sensor_id, kind) for kind in KINDS + (ALIVE,)})
    return _dumps(body, strict=False)


def decode_info(payload: bytes | bytearray | str, encoding: Any = None) -> dict:
    _check_encoding(INFO, encoding)
    obj = _loads(INFO, payload)
    _received_id(INFO, obj)
    return obj
