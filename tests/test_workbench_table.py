"""The workbench's sample table (tools/workbench/table.py): checked columns, derived covariates by hand,
storage without pickle, the residuals CSV and the nearest-time index."""
import numpy as np
import pytest
from tensortouch.contracts.errors import SessionError
from tensortouch.tools.workbench.table import SampleTable, nearest_index, write_residuals_csv


def _table():
    cols = {"t": np.array([0.0, 0.1, 0.2]), "series": np.zeros(3), "time": np.array([0.0, 0.1, 0.2]),
            "depth": np.array([0.5, 1.0, 0.2]), "max_depth": np.array([0.5, 1.0, 1.0])}
    model = np.array([[0.0, 0, -2.0], [1.0, 0, -2.0], [3.0, 4.0, 0.0]])
    normal = np.tile([0.0, 0.0, 1.0], (3, 1))
    return SampleTable(cols, model + 0.1, model, {"normal": normal}, {"sensor": "TT-1"})


def test_derived_covariates_by_hand():
    cov = _table().cov()
    np.testing.assert_allclose(cov["force_n"], [2.0, 2.0, 0.0])        # |F · n|
    np.testing.assert_allclose(cov["force_t"], [0.0, 1.0, 5.0])        # |F - (F · n) n|: the 3-4-5 shear
    np.testing.assert_allclose(cov["load_history"], [0.0, 0.0, 0.8])   # max_depth - depth, never < 0


def test_columns_are_checked():
    t = _table()
    with pytest.raises(SessionError, match="column 'series' missing"):
        SampleTable({"t": t.cols["t"], "time": t.cols["time"]}, t.meas, t.model)
    with pytest.raises(SessionError, match="column 'depth' has 2 rows, expected 3"):
        SampleTable({**t.cols, "depth": np.zeros(2)}, t.meas, t.model)
    with pytest.raises(SessionError, match=r"meas and model must both be \(N, 3\)"):
        SampleTable(t.cols, t.meas, t.model[:, :2])


def test_save_load_round_trip_and_residuals_csv(tmp_path):
    t = _table()
    t.save(tmp_path / "table.npz")
    back = SampleTable.load(tmp_path / "table.npz")
    assert back.meta == {"sensor": "TT-1"} and set(back.cols) == set(t.cols)
    np.testing.assert_array_equal(back.model, t.model)
    np.testing.assert_array_equal(back.vec["normal"], t.vec["normal"])
    write_residuals_csv(tmp_path / "residuals.csv", t, t.model)
    header, first = (tmp_path / "residuals.csv").read_text().splitlines()[:2]
    assert header.startswith("fx_meas,fy_meas,fz_meas,fx_pred,fy_pred,fz_pred,rx,ry,rz,r_mag,t,")
    row = [float(v) for v in first.split(",")]
    assert row[6:9] == [0.1, 0.1, 0.1] and row[9] == pytest.approx(np.sqrt(0.03), rel=1e-5)


def test_nearest_index_by_hand():
    t = np.array([0.0, 1.0, 2.0, 4.0])
    np.testing.assert_array_equal(nearest_index(t, np.array([-1.0, 0.4, 0.6, 2.9, 3.1, 9.0])), [0, 0, 1, 2, 3, 3])
