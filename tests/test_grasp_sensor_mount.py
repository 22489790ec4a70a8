"""The fingertip sensor mount (tools/grasp/sensor_mount.py): pad axis to dome apex and back."""
import numpy as np
import pytest
from tensortouch.tools.grasp.sensor_mount import SensorMount
from tensortouch.tools.twin.geometry import GelSurface


def test_mount_maps_pad_axis_to_apex_and_round_trips():
    m = SensorMount()
    apex = m.direction_to_gel(np.array([1.0, 0, 0]))
    np.testing.assert_allclose(apex, [0, 0, GelSurface().top_z], atol=1e-9)
    rng = np.random.default_rng(0)
    u = rng.normal(size=(50, 3)) + [3, 0, 0]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u @ [1, 0, 0] >= m.cone_cos()]
    np.testing.assert_allclose(m.gel_to_direction(m.direction_to_gel(u)), u, atol=1e-9)
    # arc length from the apex is kept: 12 mm tip sphere, θ = 0.3 rad → 3.6 mm on the gel
    p = m.direction_to_gel(np.array([np.cos(0.3), 0, np.sin(0.3)]))
    th, _ = m.gel.theta_phi(p)
    assert th * m.gel.profile.radius_mm == pytest.approx(0.3 * 12.0)
