"""A simulated fingertip sensor running the real runtime: the twin camera renders the gel under
the objects it touches (dome_contact), the frames go through `SensorLoop` (the frame loop of
`tensortouch run`: dynamic baseline, int8 network, contact clusters) and a `Publisher` puts the
contacts on Zenoh under `tensortouch/<sensor_id>/contacts`."""
from __future__ import annotations

import threading

import cv2
import numpy as np

from ...runtime.apps.loop import LoopConfig, SensorLoop
from ...runtime.apps.publisher import Publisher, PublisherConfig
from .dome_contact import DomeContactConfig, ObjectContact, displacement
from .sim_camera import SimCamera


class SimFingertip:
    def __init__(self, sensor_id: str, unit, pipeline, session, seed: int = 0,
                 contact_cfg: DomeContactConfig | None = None):
        self.sensor_id = sensor_id
        self.unit = unit
        self.contact_cfg = contact_cfg or DomeContactConfig()
        self.rng = np.random.default_rng(seed)
        self.camera = SimCamera()
        # a step-locked trial waits for every frame's contacts: BLOCK, never drop them when the
        # machine is slow (Zenoh's DROP gives up after a short wait on a full queue)
        self.publisher = Publisher(sensor_id, session=session, config=PublisherConfig(control_congestion="BLOCK"))
        self.loop = SensorLoop(self.camera, pipeline, self.publisher,
                               LoopConfig(publish_fields=False, status_every_s=3600.0))
        self.pushed = 0
        self.last_frame: np.ndarray | None = None
        self._thread = threading.Thread(target=self.loop.run, name=f"sim-{sensor_id}", daemon=True)
        self._thread.start()

    def frame(self, objects: list[ObjectContact]) -> np.ndarray:
        """RGB frame of the gel touched by `objects` (sensor frame)."""
        return gel_frame(self.unit, objects, self.rng, self.contact_cfg)

    def show(self, objects: list[ObjectContact], t: float) -> None:
        self.last_frame = self.frame(objects)
        self.camera.push(self.last_frame, t)
        self.pushed += 1

    def close(self) -> None:
        self.camera.end()
        self._thread.join(timeout=10)
        self.publisher.close()


def gel_frame(unit, objects: list[ObjectContact], rng: np.random.Generator,
              contact_cfg: DomeContactConfig | None = None) -> np.ndarray:
    """RGB frame of twin `unit`'s gel touched by `objects` (sensor frame; none: the untouched gel),
    rendered by the unit's camera with its noise drawn from `rng`."""
    r = unit.renderer
    u = None
    if objects:
        v = r.view
        u = np.zeros(v.points.shape)
        u[v.mask] = displacement(unit.gel, v.points[v.mask], v.normals[v.mask], objects,
                                 contact_cfg or DomeContactConfig())
    return cv2.cvtColor(r.render(u, 1.0, rng), cv2.COLOR_BGR2RGB)
