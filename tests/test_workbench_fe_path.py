"""The workbench's FE path (tools/workbench/fe_path.py) on a short twin session, solved by the
recipe's analytic stand-in: every press the F/T sees is a solved contact period (the recipe's label
thresholds find few of a twin's light presses), and the FE force follows the measured one."""
import numpy as np
import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.tools.train.keypoints import KeypointConfig, detect_contacts
from tensortouch.tools.workbench.compare import load_table
from tensortouch.tools.workbench.fe_path import FEModel, FEPathConfig, covered_rows

pytest.importorskip("tensortouch.tools.twin.record")


def test_light_presses_are_contact_periods_on_the_fe_path():
    t = np.linspace(0.0, 6.0, 601)
    f = sum(1.2 * np.exp(-((t - c) / 0.3) ** 2) for c in (1.0, 3.0, 5.0))      # three presses peaking at 1.2 N
    cfg = FEPathConfig()
    mine = detect_contacts(t, f, KeypointConfig(contact_force_n=cfg.contact_force_n, detach_force_n=cfg.detach_force_n))
    assert len(mine) == 3 and detect_contacts(t, f, KeypointConfig()) == []


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from tensortouch.contracts.store import CalibrationStore
    from tensortouch.tools.workbench.scenarios import Scenario, record, store_root

    path = record(Scenario(9901, pokes=3, unit="TWIN-FE01", model_size=128))
    return path, CalibrationStore(store_root("TWIN-FE01", 128)).load("TWIN-FE01")


def test_fe_at_the_keypoints_follows_the_measured_force(session):
    path, cal = session
    model = FEModel(path, cal.meta, "hertz-fallback")
    table = load_table(path, cal)[0]
    pred = model.predict(table)
    keep = covered_rows(table, pred)
    on = keep & (np.linalg.norm(table.meas, axis=1) > 0.3)
    assert len(model.periods) >= 3 and on.sum() > 100
    err = np.linalg.norm(pred[on] - table.meas[on], axis=1)
    assert np.sqrt(np.mean(err ** 2)) < 0.3 * np.sqrt(np.mean(np.sum(table.meas[on] ** 2, axis=1)))


def test_unknown_fe_physics_is_refused_in_one_line(session):
    path, cal = session
    with pytest.raises(TensorTouchError, match="expected 'fe' or 'hertz-fallback'"):
        FEModel(path, cal.meta, "abaqus")
