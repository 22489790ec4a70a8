import numpy as np
import pytest
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.stages.geometry import DomeProfile, equidistant_theta_phi, surface_tables

# One hidden magnitude per library effect on each test bench the diagnosis is tried on: the synthetic
# sample tables of tests/workbench_synth.py and the FE twin sessions of tools/workbench/scenarios.py.
HIDDEN_BENCHES = ("synthetic", "twin")
HIDDEN_EFFECTS = {
    "temperature_softening": ({"alpha": 0.03, "t_ref": 22.0}, {"alpha": 0.04, "t_ref": 20.0}),
    "viscoelastic_relaxation": ({"g1": 0.3, "tau": 1.5}, {"g1": 0.3, "tau": 1.0}),
    "mullins_softening": ({"r": 0.3, "m": 0.5}, {"r": 0.3, "m": 0.5}),
    "strain_stiffening": ({"k": 20.0}, {"k": 15.0}),
    "friction_mismatch": ({"mu": 0.5}, {"mu": 0.15}),
    "rim_stiffening": ({"a": 1.5, "w": 3.0}, {"a": 2.0, "w": 4.0}),
    "ft_bias_drift": ({"bx": 0.0, "by": 0.001, "bz": 0.003}, {"bx": 0.0, "by": 0.002, "bz": 0.004}),
    "led_drift": ({"c": -0.002, "beta": 0.01, "t_ref": 25.0}, {"c": -0.003, "beta": 0.0, "t_ref": 25.0}),
}


def hidden_effects(bench: str) -> dict[str, dict]:
    """Effect name -> the parameters it is hidden with on `bench` (one of HIDDEN_BENCHES)."""
    column = HIDDEN_BENCHES.index(bench)
    return {name: params[column] for name, params in HIDDEN_EFFECTS.items()}


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

