"""Storing a recalibration (tools/recalib/store_ops.py): a version that fails verification is rolled back;
the gel profile read from calibration.json."""
import pytest
from tensortouch.contracts.errors import CalibrationError
from tensortouch.contracts.store import CalibrationStore
from tensortouch.tools.recalib.store_ops import dome_profile, store_recalibration

from tests.conftest import dome_calibration

SENSOR = "TT-FAULT"


@pytest.fixture
def store(tmp_path):
    dome_calibration(tmp_path / "calib", SENSOR)
    return CalibrationStore(tmp_path / "calib")


def test_unloadable_correction_is_rolled_back(store):
    bad = ({"file": "correction.onnx", "inputs": ["fmag"], "output": "gain"}, b"not an onnx model")
    with pytest.raises(CalibrationError, match="failed verification .*v0001 re-activated"):
        store_recalibration(store, store.load(SENSOR), {"pokes": 6}, correction=bad)
    assert store.current(SENSOR) == "v0001"


def test_dome_profile_from_calibration_json():
    p = dome_profile({"gel": {"radius_mm": 12.5, "center_z_mm": -3.0}})
    assert (p.radius_mm, p.center_z_mm) == (12.5, -3.0)
    assert dome_profile({"gel": {"radius_mm": 10}}).center_z_mm == 0.0
    with pytest.raises(CalibrationError, match="gel.radius_mm missing; cannot rebuild surface tables"):
        dome_profile({"gel": {"shape": "dome"}})
