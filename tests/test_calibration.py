import json
import os

import pytest
from tensortouch.contracts.errors import CalibrationError
from tensortouch.contracts.store import CalibrationStore

from tests.conftest import dome_calibration


def test_write_load_roundtrip(calib_store):
    cal = calib_store.load("TT-TEST")
    assert cal.version == "v0001"
    assert cal.theta.shape == (32, 32) and cal.surface_xyz.shape == (32, 32, 3)
    assert cal.mask.dtype == bool and cal.mask.any() and not cal.mask.all()
    assert cal.gel_center_px == (80.0, 60.0)
    assert calib_store.sensors() == ["TT-TEST"]


def test_versions_and_rollback_restore_exact_files(calib_store):
    v1 = calib_store.load("TT-TEST")
    v2 = calib_store.derive("TT-TEST", {"effects": [{"name": "x", "params": {}}]}, provenance={"why": "test"})
    assert v2 == "v0002" and calib_store.current("TT-TEST") == "v0002"
    assert calib_store.load("TT-TEST").effects == [{"name": "x", "params": {}}]
    assert calib_store.rollback("TT-TEST") == "v0001"
    back = calib_store.load("TT-TEST")
    assert back.meta["files"] == v1.meta["files"]
    assert [h["active"] for h in calib_store.history("TT-TEST")] == [True, False]


def test_corrupt_table_detected_by_hash(calib_store):
    cal = calib_store.load("TT-TEST")
    with open(cal.folder / "theta.npy", "r+b") as fh:
        fh.seek(-4, os.SEEK_END)
        fh.write(b"\x00\x01\x02\x03")
    with pytest.raises(CalibrationError, match="theta.npy: SHA-256 mismatch"):
        calib_store.load("TT-TEST")


def test_missing_sensor_names_store(tmp_path):
    with pytest.raises(CalibrationError, match="no calibration for sensor 'NOPE'.*calib init"):
        CalibrationStore(tmp_path).load("NOPE")


def test_failed_write_leaves_previous_version_active(calib_store, monkeypatch):
    before = calib_store.load("TT-TEST")

    def disk_full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("tensortouch.contracts.store.json.dump", disk_full)
    with pytest.raises(CalibrationError, match="No space left on device.*nothing was stored"):
        calib_store.derive("TT-TEST", {"effects": []})
    monkeypatch.undo()
    assert calib_store.current("TT-TEST") == before.version
    assert calib_store.versions("TT-TEST") == ["v0001"]
    leftovers = [p.name for p in (calib_store.root / "TT-TEST" / "versions").iterdir()]
    assert leftovers == ["v0001"]
    assert calib_store.load("TT-TEST").meta["files"] == before.meta["files"]


def test_shape_mismatch_named(tmp_path):
    dome_calibration(tmp_path, size=16)
    meta_path = tmp_path / "TT-TEST" / "versions" / "v0001" / "calibration.json"
    meta = json.loads(meta_path.read_text())
    meta["model_size"] = [32, 32]
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(CalibrationError, match="expected \\(32, 32\\)"):
        CalibrationStore(tmp_path).load("TT-TEST")


def test_bad_sensor_id_rejected(tmp_path):
    with pytest.raises(CalibrationError, match="sensor id"):
        CalibrationStore(tmp_path).write("../evil", {}, {})
