"""Zenoh wire format, the common part (docs/wire.md): key expressions, schemas, the JSON envelope
every JSON payload shares and the `WireError` decoders raise. contracts/wire.py builds the payloads on
it and re-exports these names; no zenoh import here either.
"""
from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from .errors import TensorTouchError
from .names import NAME_PATTERN, is_name

WIRE_VERSION = 1
KEY_PREFIX = "tensortouch"
KINDS = ("fields", "contacts", "wrench", "status")
INFO = "info"
ALIVE = "alive"

SCHEMAS = {kind: f"tensortouch.{kind}.v{WIRE_VERSION}" for kind in KINDS + (INFO,)}
MIME = {"fields": "application/octet-stream", "contacts": "application/json",
        "wrench": "application/json", "status": "application/json", INFO: "application/json"}
# Zenoh Encoding strings ("<mime>;<schema>") for each payload kind.
ENCODINGS = {kind: f"{MIME[kind]};{schema}" for kind, schema in SCHEMAS.items()}

# The one pattern for sensor ids, the key chunks and the file names made from them (contracts/names.py).
SENSOR_ID_PATTERN = NAME_PATTERN


class WireError(TensorTouchError):
    """A Zenoh payload does not match the wire format (schema, shape, byte length, fields)."""


class NonFiniteError(WireError):
    """A received payload holds NaN or an infinity (or a number too large for a float): such a message
    is dropped and counted by its receiver, never delivered."""


# --------------------------------------------------------------------------- key expressions

def check_sensor_id(sensor_id: str) -> str:
    """Return `sensor_id` if it is one valid key chunk (letters, digits, `_.-`, 1-64 chars)."""
    if not is_name(sensor_id):
        raise WireError(f"sensor id {str(sensor_id)[:80]!r}: expected {SENSOR_ID_PATTERN} (1-64 characters of "
                        "[A-Za-z0-9_.-] starting with a letter or digit; it becomes a Zenoh key chunk and a "
                        "folder name)")
    return sensor_id


def key(sensor_id: str, kind: str) -> str:
    """Key expression of one stream: `tensortouch/<sensor-id>/<kind>`; `sensor_id` may be `*`."""
    if kind not in KINDS + (INFO, ALIVE, "*"):
        raise WireError(f"key kind {kind!r}: expected one of {KINDS + (INFO, ALIVE)}")
    if sensor_id not in ("*", "**"):
        check_sensor_id(sensor_id)
    return f"{KEY_PREFIX}/{sensor_id}/{kind}"


def info_key(sensor_id: str) -> str:
    return key(sensor_id, INFO)


def alive_key(sensor_id: str) -> str:
    """Liveliness token key of a running sensor."""
    return key(sensor_id, ALIVE)


def parse_key(key_expr: str) -> tuple[str, str]:
    """`tensortouch/<sensor-id>/<kind>` -> (sensor_id, kind)."""
    parts = str(key_expr).split("/")
    if len(parts) != 3 or parts[0] != KEY_PREFIX:
        raise WireError(f"key {key_expr!r}: expected '{KEY_PREFIX}/<sensor-id>/<kind>'")
    check_sensor_id(parts[1])
    return parts[1], parts[2]


def schema_of(encoding: Any) -> str | None:
    """Schema part of a Zenoh Encoding string `mime;schema` (None when there is none)."""
    text = str(encoding)
    return text.split(";", 1)[1] if ";" in text else None


def check_schema(kind: str, found: Any, where: str) -> None:
    expected = SCHEMAS[kind]
    if found != expected:
        raise WireError(f"{kind} {where}: schema {found!r}, expected {expected!r} "
                        f"(wire version {WIRE_VERSION}; see docs/wire.md)")


def check_encoding(kind: str, encoding: Any) -> None:
    if encoding is not None:
        check_schema(kind, schema_of(encoding), f"encoding {str(encoding)!r}")


# --------------------------------------------------------------------------- JSON helpers

def plain(value: Any, strict: bool) -> Any:
    """numpy/tuple -> JSON-ready python; non-finite floats -> None (or WireError when strict)."""
    if isinstance(value, dict):
        return {str(k): plain(v, strict) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v, strict) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist(), strict)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        if not math.isfinite(value):
            if strict:
                raise WireError(f"non-finite number {value} cannot be sent as JSON")
            return None
        return value
    return value


def dumps(obj: dict, strict: bool = True) -> bytes:
    return json.dumps(plain(obj, strict), separators=(",", ":"), allow_nan=False).encode()


def _no_constant(kind: str):
    def refuse(token: str):
        raise NonFiniteError(f"{kind} payload: non-finite number {token} (NaN and infinities are not sent)")
    return refuse


def _finite_float(kind: str):
    def parse(text: str) -> float:
        value = float(text)
        if not math.isfinite(value):
            raise NonFiniteError(f"{kind} payload: number {text[:40]} is beyond the float range")
        return value
    return parse


def loads(kind: str, payload: bytes | bytearray | str) -> dict:
    """A JSON payload as a dict with its schema checked. NaN, Infinity and numbers beyond the float range
    raise NonFiniteError while parsing, so no decoded JSON message ever holds a non-finite number."""
    try:
        obj = json.loads(payload, parse_constant=_no_constant(kind), parse_float=_finite_float(kind))
    except WireError:
        raise
    except RecursionError:
        raise WireError(f"{kind} payload: nested too deeply") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise WireError(f"{kind} payload: not valid UTF-8 JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise WireError(f"{kind} payload: expected a JSON object, got {type(obj).__name__}")
    check_schema(kind, obj.get("schema"), "payload")
    return obj


def need(kind: str, obj: dict, name: str) -> Any:
    if name not in obj:
        raise WireError(f"{kind} payload: missing field {name!r}")
    return obj[name]
