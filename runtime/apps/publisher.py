"""Zenoh publisher shell: one sensor's fields, contacts, wrench and status (docs/wire.md).

Thin shell over contracts/wire.py. The frame loop calls `publish_*`; none of them raises or blocks
on the network: puts use CongestionControl.DROP, every failure is caught and counted, and the
counts go out in the next status message (`wire` block + `publish_errors` flag).
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import zenoh

from ...contracts import wire
from ...contracts.errors import TensorTouchError
from .. import __version__
from . import zenoh_session

log = logging.getLogger(__name__)

# kept here too: callers and tests import them from runtime.apps.publisher
open_session = zenoh_session.open_session
zenoh_config = zenoh_session.zenoh_config


@dataclass
class PublisherConfig:
    """QoS per stream. Fields are bulky and only the newest matters: drop under congestion.
    Contacts/wrench are small and control-relevant: higher priority, express (no batching)."""
    fields_priority: str = "DATA"
    control_priority: str = "INTERACTIVE_HIGH"     # contacts, wrench
    status_priority: str = "DATA_LOW"
    control_express: bool = True
    # contacts/wrench under congestion: DROP (a live sensor: a late frame is worth less than the next
    # one) or BLOCK (a step-locked simulation: every frame's contacts must arrive)
    control_congestion: str = "DROP"
    log_every_n_errors: int = 1000                 # first error per stream is logged, then 1 in N


def _open(config, listen, connect, role: str) -> zenoh.Session:
    """A session from a zenoh.Config, a config file path or endpoints (Publisher, Subscriber)."""
    if config is None or isinstance(config, zenoh.Config):
        return open_session(config, listen=listen, connect=connect, role=role)
    return open_session(listen=listen, connect=connect, role=role, config_file=config)


@dataclass
class WireStats:
    sent: dict = field(default_factory=lambda: {k: 0 for k in wire.KINDS})
    errors: dict = field(default_factory=lambda: {k: 0 for k in wire.KINDS})
    clipped_frames: int = 0
    info_queries: int = 0
    last_error: str | None = None

    def as_dict(self) -> dict:
        return {"sent": dict(self.sent), "errors": dict(self.errors),
                "clipped_frames": self.clipped_frames, "info_queries": self.info_queries,
                "last_error": self.last_error}


class Publisher:
    """Publishes one sensor under `tensortouch/<sensor_id>/...`.

    Pass an open `session` to share one zenoh session between several sensors (it is then not
    closed by `close()`), or a `zenoh_config` (a zenoh.Config, or the path of Zenoh's JSON5 config
    file) / `listen` / `connect` to open one. With neither, it listens on the meeting point
    (runtime.apps.zenoh_session.default_endpoint(), loopback).
    `info` is a callable returning a dict (model name/hash, calibration version, bounds, ...)
    answered on `tensortouch/<sensor_id>/info`. `status_extra` members (e.g. `finger`) go into
    every status unless the status dict itself carries them.
    """

    def __init__(self, sensor_id: str, zenoh_config: zenoh.Config | str | None = None, *,
                 session: zenoh.Session | None = None, listen: Sequence[str] = (),
                 connect: Sequence[str] = (), info: Callable[[], dict] | None = None,
                 config: PublisherConfig | None = None, status_extra: dict | None = None):
        self.sensor_id = wire.check_sensor_id(sensor_id)
        self.config = config or PublisherConfig()
        self.status_extra = dict(status_extra or {})  # members every status carries (e.g. finger)
        self.stats = WireStats()
        self._info = info or dict
        self._lock = threading.Lock()
        self._errors_at_last_status = 0
        self._clipped_at_last_status = 0
        self._closed = False
        self._owns_session = session is None
        self.session = session if session is not None else _open(zenoh_config, listen, connect, "sensor")
        try:
            self._declare()
        except Exception:
            self.close()
            raise

    def _declare(self) -> None:
        cfg, pr, cc = self.config, zenoh.Priority, zenoh.CongestionControl
        if cfg.control_congestion not in ("DROP", "BLOCK"):
            raise TensorTouchError(f"publisher control_congestion: expected DROP or BLOCK, got {cfg.control_congestion!r}")
        control = getattr(cc, cfg.control_congestion)
        qos = {"fields": (getattr(pr, cfg.fields_priority), False, cc.DROP),
               "contacts": (getattr(pr, cfg.control_priority), cfg.control_express, control),
               "wrench": (getattr(pr, cfg.control_priority), cfg.control_express, control),
               "status": (getattr(pr, cfg.status_priority), False, cc.DROP)}
        try:
            self._pubs = {kind: self.session.declare_publisher(
                wire.key(self.sensor_id, kind), encoding=zenoh.Encoding(wire.ENCODINGS[kind]),
                congestion_control=congestion, priority=priority, express=express)
                for kind, (priority, express, congestion) in qos.items()}
            self._queryable = self.session.declare_queryable(wire.info_key(self.sensor_id),
                                                             self._on_query)
            # token last: once a sensor is seen alive, its publishers and queryable exist
            self._token = self.session.liveliness().declare_token(wire.alive_key(self.sensor_id))
        except zenoh.ZError as exc:
            raise TensorTouchError(f"zenoh: cannot declare sensor {self.sensor_id!r}: {exc}") from None
        log.info("publishing sensor %s on %s/%s/*", self.sensor_id, wire.KEY_PREFIX, self.sensor_id)

    # ---------------------------------------------------------------- frame-loop API (never raises)

    def publish_fields(self, fields_f32: np.ndarray, seq: int, t: float) -> bool:
        """(15, H, W) float fields in docs/fields.md units. Returns False if not sent."""
        try:
            payload, attachment, clipped = wire.encode_fields(fields_f32, seq, t, self.sensor_id)
        except Exception as exc:  # noqa: BLE001 - the frame loop must go on
            return self._failed("fields", exc)
        if clipped:
            with self._lock:
                self.stats.clipped_frames += 1
        return self._put("fields", payload, attachment)

    def publish_contacts(self, contacts: Iterable[wire.Contact | dict], seq: int, t: float) -> bool:
        try:
            payload = wire.encode_contacts(contacts, seq, t, self.sensor_id)
        except Exception as exc:  # noqa: BLE001
            return self._failed("contacts", exc)
        return self._put("contacts", payload)

    def publish_wrench(self, force_n: Sequence[float], torque_nmm: Sequence[float], seq: int,
                       t: float) -> bool:
        """Total force (N) and torque (N*mm) about the gel origin (see wire.wrench_from_contacts)."""
        try:
            payload = wire.encode_wrench(force_n, torque_nmm, seq, t, self.sensor_id)
        except Exception as exc:  # noqa: BLE001
            return self._failed("wrench", exc)
        return self._put("wrench", payload)

    def publish_status(self, status: dict, seq: int | None = None, t: float | None = None) -> bool:
        """Status dict; `seq`/`t` default to status['seq'] / status['t'] / wall clock.

        Adds a `wire` block with this publisher's counters and the flags `publish_errors` /
        `fields_clipped` when errors / clipping happened since the previous status.
        """
        try:
            body = {**self.status_extra, **status}
            seq = int(body.pop("seq", 0) if seq is None else seq)
            t = float(body.pop("t", time.time()) if t is None else t)
            with self._lock:
                wire_stats = self.stats.as_dict()
                n_err = sum(self.stats.errors.values())
                new_errors = n_err - self._errors_at_last_status
                new_clipped = self.stats.clipped_frames - self._clipped_at_last_status
                self._errors_at_last_status = n_err
                self._clipped_at_last_status = self.stats.clipped_frames
            flags = set(body.get("flags") or ())
            if new_errors:
                flags.add("publish_errors")
            if new_clipped:
                flags.add("fields_clipped")
            body["flags"] = sorted(flags)
            body["wire"] = wire_stats
            payload = wire.encode_status(body, seq, t, self.sensor_id)
        except Exception as exc:  # noqa: BLE001
            return self._failed("status", exc)
        return self._put("status", payload)

    def _put(self, kind: str, payload: bytes, attachment: bytes | None = None) -> bool:
        if self._closed:
            return self._failed(kind, TensorTouchError("publisher is closed"))
        try:
            self._pubs[kind].put(payload, attachment=attachment)
        except Exception as exc:  # noqa: BLE001 - zenoh errors must not reach the frame loop
            return self._failed(kind, exc)
        with self._lock:
            self.stats.sent[kind] += 1
        return True

    def _failed(self, kind: str, exc: BaseException) -> bool:
        with self._lock:
            self.stats.errors[kind] += 1
            n = self.stats.errors[kind]
            self.stats.last_error = f"{kind}: {type(exc).__name__}: {exc}"
        if n == 1 or n % max(1, self.config.log_every_n_errors) == 0:
            log.warning("sensor %s: %s not published (%d so far): %s", self.sensor_id, kind, n, exc)
        return False

    # ---------------------------------------------------------------- info queryable

    def _on_query(self, query: "zenoh.Query") -> None:
        with self._lock:
            self.stats.info_queries += 1
        try:
            payload = wire.encode_info(self._info(), self.sensor_id, __version__)
        except Exception as exc:  # noqa: BLE001 - answer with an error instead of a timeout
            log.warning("sensor %s: info callable failed: %s", self.sensor_id, exc)
            try:
                query.reply_err(f"sensor {self.sensor_id}: info unavailable: {exc}")
            except Exception:  # noqa: BLE001
                pass
            return
        try:
            query.reply(wire.info_key(self.sensor_id), payload,
                        encoding=zenoh.Encoding(wire.ENCODINGS[wire.INFO]))
        except Exception as exc:  # noqa: BLE001
            log.warning("sensor %s: info reply failed: %s", self.sensor_id, exc)

    # ---------------------------------------------------------------- lifetime

    def close(self) -> None:
        """Undeclare everything (the liveliness token disappears); close an owned session."""
        if self._closed:
            return
        self._closed = True
        for name in ("_queryable", "_token"):
            obj = getattr(self, name, None)
            if obj is not None:
                zenoh_session.release(obj.undeclare, f"undeclare {name}", log)
        for pub in getattr(self, "_pubs", {}).values():
            zenoh_session.release(pub.undeclare, "undeclare publisher", log)
        if self._owns_session and getattr(self, "session", None) is not None:
            zenoh_session.release(self.session.close, "session close", log)

    def __enter__(self) -> "Publisher":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
