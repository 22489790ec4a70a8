"""Where the sensor sits on a fingertip: the map between a fingertip frame (tip sphere centre, as
in the hand URDF) and the sensor frame of the gel dome (docs/fields.md: base at z = 0, apex on +z).

The dome's axis points along the fingertip pad (`axis_tip`, +x of the Allegro tip frames); the
sensor x axis is the finger's long axis (`long_tip`, tip +z). A direction u from the tip sphere
centre at angle θ from the pad axis maps to the gel point at the same arc length from the apex
(θ_gel = θ · r_tip / R_cap) and the same azimuth. Pure numpy, used by both the simulated fingertip
(forward) and the controller (inverse, to place reported contacts on the hand)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..twin.geometry import GelSurface


@dataclass(frozen=True)
class SensorMount:
    axis_tip: tuple = (1.0, 0.0, 0.0)
    long_tip: tuple = (0.0, 0.0, 1.0)
    tip_radius_mm: float = 12.0
    gel: GelSurface = field(default_factory=GelSurface)

    @property
    def R_ts(self) -> np.ndarray:
        """Columns: sensor x, y, z axes in the fingertip frame."""
        z = np.asarray(self.axis_tip, float)
        z = z / np.linalg.norm(z)
        x = np.asarray(self.long_tip, float)
        x = x - (x @ z) * z
        x = x / np.linalg.norm(x)
        return np.stack([x, np.cross(z, x), z], axis=1)

    def cone_cos(self) -> float:
        """cos of the largest pad angle θ that lands on the gel."""
        return float(np.cos(0.999 * self.gel.theta_max * self.gel.profile.radius_mm / self.tip_radius_mm))

    def direction_to_gel(self, u_tip: np.ndarray) -> np.ndarray:
        """Unit directions (...,3) in the tip frame → gel surface points (...,3) mm, sensor frame."""
        u = np.asarray(u_tip, float) @ self.R_ts          # into sensor axes
        theta = np.arccos(np.clip(u[..., 2], -1.0, 1.0))
        phi = np.arctan2(u[..., 1], u[..., 0])
        th_gel = np.minimum(theta * self.tip_radius_mm / self.gel.profile.radius_mm, self.gel.theta_max * 0.999)
        return self.gel.point_at(th_gel, phi)

    def gel_to_direction(self, p_sensor: np.ndarray) -> np.ndarray:
        """Gel points (...,3) mm, sensor frame → unit directions in the tip frame."""
        th_gel, phi = self.gel.theta_phi(np.asarray(p_sensor, float))
        theta = th_gel * self.gel.profile.radius_mm / self.tip_radius_mm
        u = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
        return u @ self.R_ts.T

    def vector_to_sensor(self, v_tip: np.ndarray) -> np.ndarray:
        return np.asarray(v_tip, float) @ self.R_ts
