"""Subscriber library: receive and decode what `runtime.apps.publisher.Publisher` sends (docs/wire.md).

    from tensortouch.runtime.apps.subscriber import Subscriber
    with Subscriber("*") as sub:                        # connects to tcp/127.0.0.1:7447
        frame = sub.wait_for("fields", timeout=5.0)     # wire.FieldsFrame, float32 (15, H, W)

Callbacks run on a zenoh thread: keep them short (copy / enqueue, do not compute there).
Malformed messages are counted in `errors` and logged, never raised into zenoh nor handed to a
callback; those dropped because they hold NaN, an infinity or a number beyond the float range are
also counted in `non_finite`.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable, Sequence

import zenoh

from ...contracts import wire
from ...contracts.errors import TensorTouchError
from .publisher import _open
from .zenoh_session import release

log = logging.getLogger(__name__)

Callback = Callable[[Any], None]


def _decode(kind: str, sample: "zenoh.Sample", fields_max_shape=None) -> Any:
    if kind == "fields" and fields_max_shape is not None:
        limit = 2 * fields_max_shape[0] * fields_max_shape[1] * fields_max_shape[2]     # float16 bytes
        if len(sample.payload) > limit:           # refused before the payload is copied out of zenoh
            raise wire.WireError(f"fields: payload of {len(sample.payload)} bytes exceeds this receiver's "
                                 f"limit {tuple(fields_max_shape)} ({limit} bytes)")
    payload = sample.payload.to_bytes()
    encoding = sample.encoding
    if kind == "fields":
        att = sample.attachment
        return wire.decode_fields(payload, att.to_bytes() if att is not None else None, encoding,
                                  max_shape=fields_max_shape)
    if kind == "contacts":
        return wire.decode_contacts(payload, encoding)
    if kind == "wrench":
        return wire.decode_wrench(payload, encoding)
    return wire.decode_status(payload, encoding)


def decode_sample(sample: "zenoh.Sample", fields_max_shape=None) -> tuple[str, Any]:
    """A zenoh Sample on `tensortouch/<id>/<kind>` -> (kind, decoded object). Raises WireError."""
    sensor_id, kind = wire.parse_key(str(sample.key_expr))
    if kind not in wire.KINDS:
        raise wire.WireError(f"key {sample.key_expr}: unknown stream {kind!r}")
    msg = _decode(kind, sample, fields_max_shape)
    found = msg["sensor_id"] if isinstance(msg, dict) else msg.sensor_id
    if found != sensor_id:
        raise wire.WireError(f"{sample.key_expr}: payload names sensor {found!r}, key says {sensor_id!r}")
    return kind, msg


class Subscriber:
    """Subscribes to one sensor (or `*` for all) and decodes each stream.

    Pass an open `session` to share it (not closed by `close()`), or `connect`/`listen` endpoints
    or a `zenoh_config` (a zenoh.Config, or the path of Zenoh's JSON5 config file). With neither,
    it connects to the meeting point (runtime.apps.zenoh_session.default_endpoint(), loopback) and
    listens nowhere. `on_fields(FieldsFrame)`, `on_contacts(ContactsFrame)`,
    `on_wrench(Wrench)`, `on_status(dict)` are called for each decoded message. `fields_max_shape`
    (C, H, W) drops (and counts) larger field images before their data is converted.
    """

    def __init__(self, sensor_id: str = "*", *, session: zenoh.Session | None = None,
                 zenoh_config: zenoh.Config | str | None = None, connect: Sequence[str] = (),
                 listen: Sequence[str] = (), on_fields: Callback | None = None,
                 on_contacts: Callback | None = None, on_wrench: Callback | None = None,
                 on_status: Callback | None = None, fields_max_shape: tuple[int, int, int] | None = None):
        if sensor_id not in ("*",):
            wire.check_sensor_id(sensor_id)
        self.sensor_id = sensor_id
        self.fields_max_shape = fields_max_shape
        self._callbacks = {"fields": on_fields, "contacts": on_contacts, "wrench": on_wrench,
                           "status": on_status}
        self._cond = threading.Condition()
        self.latest: dict[str, Any] = {}
        self.counts = {kind: 0 for kind in wire.KINDS}
        self.errors = 0                  # messages dropped because they did not decode (all reasons)
        self.non_finite = 0              # ... of which because they held NaN / infinity
        self.last_error: str | None = None
        self._closed = False
        self._owns_session = session is None
        self.session = session if session is not None else _open(zenoh_config, listen, connect, "subscriber")
        try:
            self._sub = self.session.declare_subscriber(wire.key(sensor_id, "*"), self._on_sample)
        except zenoh.ZError as exc:
            self.close()
            raise TensorTouchError(f"zenoh: cannot subscribe to {wire.key(sensor_id, '*')}: {exc}") from None

    def _on_sample(self, sample: "zenoh.Sample") -> None:
        if str(sample.key_expr).rsplit("/", 1)[-1] not in wire.KINDS:
            return  # a stream added by a newer wire version: not ours to decode
        try:
            kind, msg = decode_sample(sample, self.fields_max_shape)
        except Exception as exc:  # noqa: BLE001 - never raise into zenoh's thread
            with self._cond:
                self.errors += 1
                self.non_finite += isinstance(exc, wire.NonFiniteError)
                self.last_error = str(exc)
                n = self.errors
            if n == 1 or n % 1000 == 0:
                log.warning("dropped a message on %s (%d so far): %s", sample.key_expr, n, exc)
            return
        with self._cond:
            self.latest[kind] = msg
            self.counts[kind] += 1
            self._cond.notify_all()
        callback = self._callbacks.get(kind)
        if callback is not None:
            try:
                callback(msg)
            except Exception:  # noqa: BLE001
                log.exception("on_%s callback raised", kind)

    def wait_for(self, kind: str, timeout: float = 5.0, since: int | None = None) -> Any:
        """Block until a new `kind` message arrives; return it decoded (the latest one).

        "New" means after this call, or after `since` = a value of `self.counts[kind]` read
        earlier (read it before publishing to avoid missing a fast reply).
        Raises TimeoutError (with what did arrive) after `timeout` seconds.
        """
        if kind not in wire.KINDS:
            raise ValueError(f"kind {kind!r}: expected one of {wire.KINDS}")
        deadline = time.monotonic() + timeout
        with self._cond:
            start = self.counts[kind] if since is None else since
            while self.counts[kind] == start:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(
                        f"no {kind} message on {wire.key(self.sensor_id, kind)} within {timeout} s "
                        f"(received so far: {self.counts}, decode errors: {self.errors}, of which "
                        f"non-finite: {self.non_finite})")
                self._cond.wait(left)
            return self.latest[kind]

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        sub = getattr(self, "_sub", None)
        if sub is not None:
            release(sub.undeclare, "undeclare subscriber", log)
        if self._owns_session:
            release(self.session.close, "session close", log)

    def __enter__(self) -> "Subscriber":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _session_of(obj: Any) -> zenoh.Session:
    return getattr(obj, "session", obj)


def query_info(session: Any, sensor_id: str, timeout: float = 2.0, max_bytes: int | None = None) -> dict:
    """Ask sensor `sensor_id`'s queryable for its info (model hash, calibration version, bounds...).

    `session` is a zenoh.Session, a Subscriber or a Publisher. Raises TensorTouchError when the
    sensor does not answer within `timeout` s, answers with an error, or (with `max_bytes`) with a
    larger reply.
    """
    wire.check_sensor_id(sensor_id)
    problems = []
    for reply in _session_of(session).get(wire.info_key(sensor_id), timeout=timeout):
        if reply.ok is not None:
            payload = reply.ok.payload
            if max_bytes is not None and len(payload) > max_bytes:
                problems.append(f"info reply of {len(payload)} bytes, more than the {max_bytes} accepted")
                continue
            return wire.decode_info(payload.to_bytes(), reply.ok.encoding)
        problems.append(reply.err.payload.to_string())
    detail = f": {'; '.join(problems)}" if problems else f" within {timeout} s"
    raise TensorTouchError(f"sensor {sensor_id!r} did not answer on {wire.info_key(sensor_id)}{detail}")


def alive_sensors(session: Any, timeout: float = 1.0) -> list[str]:
    """Sorted ids of the sensors whose liveliness token is currently visible."""
    ids = set()
    for reply in _session_of(session).liveliness().get(wire.alive_key("*"), timeout=timeout):
        if reply.ok is not None:
            try:
                sensor_id, _ = wire.parse_key(str(reply.ok.key_expr))
            except wire.WireError:
                continue
            ids.add(sensor_id)
    return sorted(ids)


def watch_alive(session: Any, callback: Callable[[str, bool], None], history: bool = True):
    """Call `callback(sensor_id, alive)` when a sensor appears/disappears. Returns the zenoh
    subscriber (undeclare it to stop)."""
    def on_sample(sample: "zenoh.Sample") -> None:
        try:
            sensor_id, _ = wire.parse_key(str(sample.key_expr))
            callback(sensor_id, sample.kind == zenoh.SampleKind.PUT)
        except Exception:  # noqa: BLE001
            log.exception("liveliness callback raised")

    return _session_of(session).liveliness().declare_subscriber(
        wire.alive_key("*"), on_sample, history=history)


def queued_callbacks(kinds, maxsize: int = 1000):
    """(inbox, {"on_<kind>": callback}) for a Subscriber whose messages a consumer thread takes from
    `inbox` as (kind, message); when the consumer falls behind, messages are dropped rather than
    stalling Zenoh's callback thread."""
    import queue

    inbox: queue.Queue = queue.Queue(maxsize=maxsize)

    def put(kind):
        def cb(msg):
            try:
                inbox.put_nowait((kind, msg))
            except queue.Full:
                pass
        return cb
    return inbox, {f"on_{k}": put(k) for k in kinds}
