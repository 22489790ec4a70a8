"""The mesh-convergence study (tools/fe/study.py): Richardson extrapolation by hand, a solved CalculiX deck
reused."""
import pytest

pytest.importorskip("felupe")
pytest.importorskip("gmsh")
pytest.importorskip("trimesh")

from tensortouch.tools.fe.inp import export_inp_ccx

from tests.test_fe_ccx import coarse_press


def test_richardson_recovers_a_known_limit_and_refuses_oscillation():
    from tensortouch.tools.fe.study import richardson

    h = [1.4, 1.0, 0.7]
    out = richardson(h, [2.0 + 0.5 * x ** 1.5 for x in h])
    assert out["monotone"] and out["p"] == pytest.approx(1.5, abs=1e-6) and out["f0"] == pytest.approx(2.0)
    out = richardson(h, [5.3 - 0.2 * x ** 0.7 for x in h])  # rising towards the limit, order < 1
    assert out["p"] == pytest.approx(0.7, abs=1e-6) and out["f0"] == pytest.approx(5.3)
    assert richardson(h, [2.5, 2.4, 2.45]) == {"f0": None, "p": None, "monotone": False}


def test_study_reuses_a_solved_deck_without_ccx(tmp_path):
    """The study's ccx rows come back from <label>.json when the deck is byte-identical (no ccx run)."""
    import hashlib
    import json

    from tensortouch.tools.fe.study import _ccx

    sc = coarse_press()
    deck = export_inp_ccx(sc, tmp_path / "lab.inp")
    sha = hashlib.sha256(deck.read_bytes()).hexdigest()
    (tmp_path / "lab.json").write_text(json.dumps({"deck_sha256": sha, "RF": [[0, 0, -2.5]], "seconds": 12.0}))
    row = _ccx(sc, tmp_path, "lab")
    assert row["reused"] and row["RF"] == [[0, 0, -2.5]] and row["seconds"] == 12.0


def test_ccx_converged_extrapolates_over_increments_and_prices_the_cheapest_close_one():
    from tensortouch.tools.fe.study import ccx_converged

    inc = (0.5, 0.25, 0.125)
    # RF_x = 0.56 - 0.1 * inc^2 (order 2, converging to 0.56); RF_z oscillates -> finest level
    last = [[0.56 - 0.1 * h ** 2, 0.0, -z] for h, z in zip(inc, (0.78, 0.79, 0.785))]
    ref, t = ccx_converged(last, [10.0, 20.0, 40.0], (0, 2), increments=inc, tol=0.02)
    assert ref[0] == pytest.approx(0.56, rel=1e-9) and ref[2] == pytest.approx(0.785)
    assert t == 20.0   # RF_x 4.5 % off at 0.5 mm, 1.1 % at 0.25 mm (RF_z 0.6 %)
    ref, t = ccx_converged(last, [10.0, 20.0, 40.0], (0, 2), increments=inc, tol=0.01)
    assert t == 40.0   # within 1 % only at 0.125 mm (0.28 %)
    with pytest.raises(ValueError):
        ccx_converged(last[:2], [1.0, 2.0], (0,), increments=inc)
