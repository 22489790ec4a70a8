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
        self.renderer = unit.renderer
        v = self.renderer.view
        self._pts, self._nrm, self._mask = v.points[v.mask], v.normals[v.mask], v.mask
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
        u = None
        if objects:
            u = np.zeros(self.renderer.view.points.shape)
            u[self._mask] = displacement(self.unit.gel, self._pts, self._nrm, objects, self.contact_cfg)
        img = self.renderer.render(u, 1.0, self.rng)
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def show(self, objects: list[ObjectContact], t: float) -> None:
        self.last_frame = self.frame(objects)
        self.camera.push(self.last_frame, t)
        self.pushed += 1

    def close(self) -> None:
        self.camera.end()
        self._thread.join(timeout=10)
        self.publisher.close()
