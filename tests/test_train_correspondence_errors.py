"""Stage 3 never falls back to the twin's true tables: a GPR fit that fails stops the build with one
error naming the unit (issue #42). Real chain on a tiny calibration session (analytic twin physics)."""
import pytest

pytest.importorskip("cv2")


def test_a_failed_gpr_fit_stops_the_build_naming_the_unit(tmp_path):
    from tensortouch.contracts.errors import TensorTouchError
    from tensortouch.tools.train.build import Build, BuildConfig, SessionSpec
    from tensortouch.tools.train.correspondence import CorrespondenceConfig, CorrespondenceError, build_unit_calibrations
    from tensortouch.tools.twin.unit import TwinUnit, write_true_calibration

    serial = "TWIN-T02"
    b = Build(BuildConfig(train=[SessionSpec(serial, 1, 1)], heldout=[], tables="gpr", physics="hertz-fallback"),
              tmp_path)
    write_true_calibration(TwinUnit(serial), b.store_root, b.cfg.size)
    # two calibration pokes: the GPR geometry fit needs six, so it fails for real
    with pytest.raises(CorrespondenceError, match=serial) as err:
        build_unit_calibrations(b, CorrespondenceConfig(pokes=2))
    assert isinstance(err.value, TensorTouchError) and "true tables" in str(err.value)
    assert "needs at least" in str(err.value)  # the GPR stage's own reason, passed on
    assert not (b.root / "correspondence" / f"{serial}.json").exists()  # nothing names a version to use
