"""Rerun recordings and live view: `tensortouch listen --save out.rrd`, `tensortouch view --rerun`
(docs/viewers.md).

Per sensor `<s>`, on the timelines `frame_time` (the frame time `t`, s) and `seq`:

| entity | archetype | content |
|---|---|---|
| `<s>/gel/dome` | Points3D (static) | the calibrated gel surface, mm (from the sensor's info) |
| `<s>/fields` | Tensor (channel, v, u) | the 15 field channels; `<s>/fields/channels` names them with units |
| `<s>/gel/contacts` | Points3D | contact centroids, mm, labelled with their id and force magnitude |
| `<s>/gel/forces` | Arrows3D | each contact's force, ending at the contact, 5 mm per N |
| `<s>/wrench/force_n/{x,y,z}`, `<s>/wrench/torque_nmm/{x,y,z}` | Scalars | time series, N and N·mm |
| `<s>/contacts/count`, `<s>/status/fps` | Scalars | |
| `<s>/status` | TextLog | state and flags |

3D is in mm, in the sensor frame of docs/fields.md (+z along the dome axis).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .saver import Saver

ARROW_MM_PER_N = 5.0


class RerunSaver(Saver):
    """Decoded wire messages -> a Rerun recording stream: an .rrd file (`path`, written as
    `<name>.partial` and renamed on close; the `tensortouch.savers` entry point `rrd`) or a live
    viewer at `grpc_url` (tools/viewers/rerun_live.py)."""

    def __init__(self, path: str | Path | None = None, *, grpc_url: str | None = None,
                 fields_min_interval_s: float = 0.0):
        import rerun as rr

        # a 15x128x128 float32 tensor is about 1 MB: a live view keeps up with fewer of them
        self.fields_min_interval_s = float(fields_min_interval_s)
        self._last_fields: dict[str, float] = {}

        self.rr = rr
        self.rec = rr.RecordingStream("tensortouch")
        self._start(path)
        if self.partial is not None:
            self.rec.save(str(self.partial))
        elif grpc_url:
            self.rec.connect_grpc(grpc_url)
        else:
            raise ValueError("RerunSaver needs a path (.rrd) or a gRPC url")
        self._named: set[str] = set()
        self._sensors: list[str] = []

    def _time(self, msg) -> None:
        seq, t = (msg["seq"], msg["t"]) if isinstance(msg, dict) else (msg.seq, msg.t)
        self.rec.set_time("seq", sequence=int(seq))
        self.rec.set_time("frame_time", duration=float(t))

    def _log(self, entity: str, archetype, static: bool = False) -> None:
        self.rec.log(entity, archetype, static=static)
        self._count(entity)

    def _layout(self, sensors: list[str]) -> None:
        """A default viewer layout: the gel in 3D, the fields tensor (fn_z first), force and torque plots."""
        import rerun.blueprint as rrb

        rr = self.rr
        cols = []
        for s in sensors:
            cols.append(rrb.Vertical(
                rrb.Horizontal(
                    rrb.Spatial3DView(origin=f"/{s}/gel", name=f"{s}: gel, contacts (mm), forces"),
                    rrb.TensorView(origin=f"/{s}/fields", name=f"{s}: fields (channel slider)",
                                   slice_selection=rrb.TensorSliceSelection(
                                       width=rr.TensorDimensionSelection(dimension=2),
                                       height=rr.TensorDimensionSelection(dimension=1),
                                       indices=[rr.TensorDimensionIndexSelection(dimension=0, index=11)]))),
                rrb.Horizontal(
                    rrb.TimeSeriesView(origin=f"/{s}/wrench/force_n", name=f"{s}: force (N)"),
                    rrb.TimeSeriesView(origin=f"/{s}/wrench/torque_nmm", name=f"{s}: torque (N·mm)"),
                    rrb.Vertical(rrb.TextDocumentView(origin=f"/{s}/fields/channels", name="channels"),
                                 rrb.TextLogView(origin=f"/{s}/status", name="status"))),
                row_shares=[3, 2]))
        self.rec.send_blueprint(rrb.Blueprint(rrb.Horizontal(*cols), collapse_panels=True))

    def on_info(self, info: dict) -> None:
        """The sensor's info (queryable): its gel surface becomes the static dome."""
        rr = self.rr
        sensor, surf = info.get("sensor_id"), info.get("gel_surface")
        if not sensor or not surf:
            return
        gh, gw = surf["grid"]
        xyz = np.asarray(surf["xyz_mm"], np.float32).reshape(gh * gw, 3)
        mask = np.asarray(surf["mask"], bool).reshape(gh * gw)
        self._log(f"{sensor}/gel/dome", rr.Points3D(xyz[mask], radii=0.15, colors=[150, 170, 200]), static=True)

    def save(self, kind: str, msg: Any) -> Path | None:
        rr = self.rr
        sensor = msg["sensor_id"] if isinstance(msg, dict) else msg.sensor_id
        self._time(msg)
        if sensor not in self._sensors:
            self._sensors.append(sensor)
            self._layout(self._sensors)
        if kind == "fields":
            last = self._last_fields.get(sensor)
            if last is not None and 0.0 <= msg.t - last < self.fields_min_interval_s:
                return self.path
            self._last_fields[sensor] = msg.t
            if sensor not in self._named:
                self._named.add(sensor)
                rows = "\n".join(f"| {i} | {c} | {u} |" for i, (c, u) in enumerate(zip(msg.channels, msg.units)))
                self._log(f"{sensor}/fields/channels", rr.TextDocument(
                    f"| channel index | name | unit |\n|---|---|---|\n{rows}", media_type="text/markdown"), static=True)
            self._log(f"{sensor}/fields", rr.Tensor(msg.data, dim_names=("channel", "v", "u")))
        elif kind == "contacts":
            cs = msg.contacts
            pos = np.array([c.position_mm for c in cs], np.float32).reshape(-1, 3)
            force = np.array([c.force_n for c in cs], np.float32).reshape(-1, 3)
            vec = force * ARROW_MM_PER_N
            self._log(f"{sensor}/gel/contacts", rr.Points3D(
                pos, radii=0.5,
                labels=[f"#{c.id} {c.force_mag_n:.2f} N" for c in cs], colors=[255, 90, 30]))
            self._log(f"{sensor}/gel/forces", rr.Arrows3D(vectors=vec, origins=pos - vec, colors=[255, 60, 20]))
            self._log(f"{sensor}/contacts/count", rr.Scalars(float(len(cs))))
        elif kind == "wrench":
            for name, vec in (("force_n", msg.force_n), ("torque_nmm", msg.torque_nmm)):
                for axis, v in zip("xyz", vec):
                    self._log(f"{sensor}/wrench/{name}/{axis}", rr.Scalars(float(v)))
        elif kind == "status":
            if isinstance(msg.get("fps"), (int, float)):
                self._log(f"{sensor}/status/fps", rr.Scalars(float(msg["fps"])))
            flags = ",".join(msg.get("flags") or ()) or "-"
            self._log(f"{sensor}/status", rr.TextLog(f"{msg.get('state')} flags={flags}",
                                                    level="WARN" if msg.get("flags") else "INFO"))
        return self.path

    def _end(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
