import numpy as np
import pytest

from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.stages.geometry import DomeProfile, equidistant_theta_phi, surface_tables


def dome_calibration(store_root, sensor_id="TT-TEST", size=32, image=(160, 120), radius_px=50.0,
                     theta_edge=np.deg2rad(100.0)):
    """Write a nominal-geometry calibration (ideal equidistant fisheye, hemispherical dome)."""
    theta, phi = equidistant_theta_phi((size, size), theta_edge)
    tables = surface_tables(theta, phi, DomeProfile(radius_mm=16.0))
    meta = {"camera": {"width": image[0], "height": image[1]},
            "gel_center_px": [image[0] / 2, image[1] / 2], "gel_radius_px": radius_px,
            "model_size": [size, size], "gel": {"shape": "dome", "radius_mm": 16.0},
            "provenance": {"method": "nominal (tests)"}}
    return CalibrationStore(store_root).write(sensor_id, tables, meta)


@pytest.fixture
def calib_store(tmp_path):
    root = tmp_path / "calibration_store"
    dome_calibration(root)
    return CalibrationStore(root)

