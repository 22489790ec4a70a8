"""What each fingertip's gel feels in the simulated world: for every object, the contact point,
the object's axis, its depth into the dome and the tangential (shear) displacement, in the sensor
frame. This reads the simulator (it is the sensor's physics), so only the simulated sensors use it.

Depth: overlap of the object with the gel sphere (tip radius) beyond the rigid core that MuJoCo
collides, capped at the gel cushion. Shear: the gel skin sticks to the object where it first
touched; the skin follows the object's material point (relative to the fingertip, along the
surface) until `max_shear_mm`, beyond which the object slips and the stick point is dragged along
(MuJoCo's own friction creeps under a static load, so it is not used for the skin). Once a
pinch has settled, `relax()` restarts the stick points (the gel's shear relaxes under a held load).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .dome_contact import ObjectContact
from .scene import Scene
from .sensor_mount import SensorMount


@dataclass(frozen=True)
class TouchConfig:
    cushion_mm: float = 1.2            # largest indentation (mm)
    max_shear_mm: float = 0.8          # stick limit of the gel skin


class GelTouch:
    """Per-fingertip contact state with the stick points kept between frames."""

    def __init__(self, scene: Scene, mount: SensorMount, cfg: TouchConfig | None = None):
        self.scene, self.mount, self.cfg = scene, mount, cfg or TouchConfig()
        self._anchor: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def relax(self) -> None:
        """A held pinch: the skin's shear relaxes, every stick point restarts where it is now."""
        self._anchor.clear()

    def _body(self, k: int):
        d = self.scene.data
        b = self.scene.objects[k].body_ids[0]
        return d.xpos[b].copy(), d.xmat[b].reshape(3, 3).copy()

    def contacts(self, tip: int) -> list[ObjectContact]:
        sc, mount, cfg = self.scene, self.mount, self.cfg
        T = sc.tip_pose(tip)
        R, c = T[:3, :3], T[:3, 3]
        out = []
        for k, o in enumerate(sc.objects):
            p, e = sc.object_axis(k)
            q = p + ((c - p) @ e) * e
            dvec = q - c
            dist = float(np.linalg.norm(dvec))
            overlap_mm = (mount.tip_radius_mm / 1000.0 + o.radius_m - dist) * 1000.0
            u_tip = R.T @ (dvec / max(dist, 1e-12))
            if overlap_mm <= 0 or u_tip @ np.asarray(mount.axis_tip, float) < mount.cone_cos():
                self._anchor.pop((tip, k), None)     # not touching the gel: the skin lets go
                continue
            bp, bR = self._body(k)
            if (tip, k) not in self._anchor:       # first touch: remember the material point
                self._anchor[(tip, k)] = (bR.T @ (q - bp), R.T @ (q - c))
            local_obj, stick_tip = self._anchor[(tip, k)]
            now_tip = R.T @ (bp + bR @ local_obj - c)
            s = now_tip - stick_tip
            s -= (s @ u_tip) * u_tip                  # along the surface
            mag = float(np.linalg.norm(s)) * 1000.0
            if mag > cfg.max_shear_mm:                # gross slip: the stick point is dragged along
                excess = s * (1 - cfg.max_shear_mm / mag)
                self._anchor[(tip, k)] = (local_obj, stick_tip + excess)
                s = s - excess
            out.append(ObjectContact(mount.direction_to_gel(u_tip), mount.vector_to_sensor(R.T @ e),
                                     o.radius_m * 1000.0, min(overlap_mm, cfg.cushion_mm),
                                     mount.vector_to_sensor(s * 1000.0), k))
        return out
