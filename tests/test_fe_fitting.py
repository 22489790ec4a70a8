"""Material fitting (tools/fe/fitting.py): Yeoh ranks over neo-Hookean."""
import numpy as np
import pytest

pytest.importorskip("felupe")
pytest.importorskip("gmsh")
trimesh = pytest.importorskip("trimesh")



def test_material_fit_ranks_yeoh_over_neo_hookean(tmp_path):
    from tensortouch.tools.fe.fitting import fit_report, load_test_data, synthetic_test_data

    data = synthetic_test_data(C=(0.03, 0.002, 0.0002), noise=1e-4)
    rep = fit_report(data, plot=tmp_path / "fit.png")
    fits = {f["model"]: f for f in rep["fits"]}
    assert fits["yeoh"]["rmse"] < 0.5 * fits["neo_hookean"]["rmse"]
    assert fits["yeoh"]["params"]["C10"] == pytest.approx(0.03, rel=0.05)
    assert fits["yeoh"]["stable"] and rep["hysteresis_width"] > 0
    assert (tmp_path / "fit.png").stat().st_size > 1000
    csv = "mode,stretch,stress_MPa,branch\n" + "\n".join(
        f"{m},{s},{p},{b}" for m, s, p, b in zip(data.mode, data.stretch, data.stress, data.branch))
    (tmp_path / "d.csv").write_text(csv)
    back = load_test_data(tmp_path / "d.csv")
    assert np.allclose(back.stress, data.stress)
