"""`tensortouch listen --save out.mcap`: MCAP with Foxglove's well-known schemas (docs/viewers.md).

Written with foxglove-sdk (protobuf encoding, the schemas Foxglove's panels know), per sensor `<s>`:

| topic | schema | content |
|---|---|---|
| `/tensortouch/<s>/fields/<channel>` | foxglove.RawImage `32FC1` | one field channel, in our units (mm or MPa) |
| `/tensortouch/<s>/contacts` | foxglove.PointCloud | one point per contact: x y z (m), fx fy fz force (N), area (mm²), id |
| `/tensortouch/<s>/contact_arrows` | foxglove.SceneUpdate | one arrow per contact, along its force, 10 mm per N |
| `/tensortouch/<s>/wrench` | JSON (tensortouch.wrench.v1) | force N, torque N·mm |
| `/tensortouch/<s>/status` | JSON (tensortouch.status.v1) | the status message as sent |

3D positions are in metres (Foxglove's 3D panel works in metres), frame `<s>_gel` (the sensor
frame, docs/fields.md). Message timestamps are the frame time `t`; the MCAP log time is when the
message was received. The file is written as `<name>.partial` and renamed when the saver closes.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from .saver import Saver

ARROW_M_PER_N = 0.01            # arrow length per newton of contact force

_JSON_SCHEMAS = {
    "wrench": {"type": "object", "title": "tensortouch.wrench.v1", "properties": {
        "sensor_id": {"type": "string"}, "seq": {"type": "integer"}, "t": {"type": "number"},
        "force_n": {"type": "array", "items": {"type": "number"}},
        "torque_nmm": {"type": "array", "items": {"type": "number"}}}},
    "status": {"type": "object", "title": "tensortouch.status.v1", "properties": {
        "sensor_id": {"type": "string"}, "seq": {"type": "integer"}, "t": {"type": "number"},
        "state": {"type": "string"}, "flags": {"type": "array", "items": {"type": "string"}},
        "fps": {"type": ["number", "null"]}}},
}


def _stamp(t: float):
    from foxglove.messages import Timestamp

    ns = max(0, round(float(t) * 1e9))
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _quat_x_to(v: np.ndarray) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) turning +x onto the direction of `v` (Foxglove arrows point along +x)."""
    n = float(np.linalg.norm(v))
    if n == 0.0:
        return (0.0, 0.0, 0.0, 1.0)
    d = v / n
    w = 1.0 + d[0]                      # cross(+x, d) = (0, -d_z, d_y), dot = d_x
    if w < 1e-9:                        # opposite to +x: half turn about z
        return (0.0, 0.0, 1.0, 0.0)
    q = np.array([0.0, -d[2], d[1], w])
    q /= np.linalg.norm(q)
    return tuple(float(c) for c in q)


class McapSaver(Saver):
    """Decoded wire messages -> one MCAP file (the `tensortouch.savers` entry point `mcap`)."""

    def __init__(self, path: str | Path):
        import foxglove

        self._start(path)
        self.context = foxglove.Context()
        self.writer = foxglove.open_mcap(str(self.partial), allow_overwrite=True, context=self.context)
        self.channels: dict[str, Any] = {}

    def _channel(self, topic: str, make):
        ch = self.channels.get(topic)
        if ch is None:
            ch = self.channels[topic] = make(topic)
        return ch

    def _log(self, topic: str, make, msg) -> None:
        self._channel(topic, make).log(msg)
        self._count(topic)

    def save(self, kind: str, msg: Any) -> Path:
        import foxglove
        from foxglove import channels as fc
        from foxglove import messages as fm

        ctx = self.context
        sensor = msg["sensor_id"] if isinstance(msg, dict) else msg.sensor_id
        base, frame = f"/tensortouch/{sensor}", f"{sensor}_gel"
        if kind == "fields":
            h, w = msg.data.shape[1:]
            for name, plane in zip(msg.channels, msg.data):
                self._log(f"{base}/fields/{name}", lambda t: fc.RawImageChannel(t, context=ctx), fm.RawImage(
                    timestamp=_stamp(msg.t), frame_id=frame, width=w, height=h, encoding="32FC1",
                    step=4 * w, data=np.ascontiguousarray(plane, "<f4").tobytes()))
        elif kind == "contacts":
            names = ("x", "y", "z", "fx", "fy", "fz", "force", "area", "id")
            pts = np.array([[*(np.asarray(c.position_mm) * 1e-3), *c.force_n, c.force_mag_n, c.area_mm2, c.id]
                            for c in msg.contacts], "<f4").reshape(-1, len(names))
            f32 = fm.PackedElementFieldNumericType.Float32
            self._log(f"{base}/contacts", lambda t: fc.PointCloudChannel(t, context=ctx), fm.PointCloud(
                timestamp=_stamp(msg.t), frame_id=frame, pose=fm.Pose(position=fm.Vector3(x=0, y=0, z=0),
                                                                      orientation=fm.Quaternion(x=0, y=0, z=0, w=1)),
                point_stride=4 * len(names),
                fields=[fm.PackedElementField(name=n, offset=4 * i, type=f32) for i, n in enumerate(names)],
                data=pts.tobytes()))
            arrows = []
            for c in msg.contacts:
                f = np.asarray(c.force_n, float)
                qx, qy, qz, qw = _quat_x_to(f)
                length = ARROW_M_PER_N * float(np.linalg.norm(f))
                p = np.asarray(c.position_mm, float) * 1e-3 - (f / max(np.linalg.norm(f), 1e-12)) * length
                arrows.append(fm.ArrowPrimitive(
                    pose=fm.Pose(position=fm.Vector3(x=p[0], y=p[1], z=p[2]),
                                 orientation=fm.Quaternion(x=qx, y=qy, z=qz, w=qw)),
                    shaft_length=0.8 * length, shaft_diameter=0.0008, head_length=0.2 * length,
                    head_diameter=0.002, color=fm.Color(r=1.0, g=0.3, b=0.1, a=1.0)))
            self._log(f"{base}/contact_arrows", lambda t: fc.SceneUpdateChannel(t, context=ctx), fm.SceneUpdate(
                entities=[fm.SceneEntity(timestamp=_stamp(msg.t), frame_id=frame, id=f"{sensor}/contacts",
                                         arrows=arrows)]))
        elif kind in ("wrench", "status"):
            body = (msg if isinstance(msg, dict) else
                    {"sensor_id": msg.sensor_id, "seq": msg.seq, "t": msg.t, "force_n": list(msg.force_n),
                     "torque_nmm": list(msg.torque_nmm)})
            body = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in body.items()}
            self._log(f"{base}/{kind}", lambda t: foxglove.Channel(
                t, schema=_JSON_SCHEMAS[kind], message_encoding="json", context=ctx), body)
        return self.path

    def _end(self) -> None:
        self.writer.close()
