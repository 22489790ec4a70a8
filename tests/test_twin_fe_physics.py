"""Twin FE physics (tools/twin/fe_physics.py): scenario mapping, result conversion, non-convergence
retries."""
import json

import numpy as np
import pytest
from tensortouch.tools.twin.geometry import GelSurface
from tensortouch.tools.twin.physics import PokeSolve
from tensortouch.tools.twin.trajectory import TrajectoryConfig, plan_session

GEL = GelSurface()


def _poke(kind, seed=3):
    return plan_session(1, seed, GEL, TrajectoryConfig(kinds=(kind,), p_two=0.0, indenters=("sphere5",)))[0]


def test_fe_scenario_mapping_and_cache_key(tmp_path):
    pytest.importorskip("felupe")
    from tensortouch.tools.twin.fe_physics import FEPhysics

    p = plan_session(2, 5, GEL, TrajectoryConfig(p_two=1.0))[0]
    fe = FEPhysics(cache=tmp_path)
    sc = fe.scenario(p)
    assert len(sc.indenters) == len(p.slots) == 2
    for k, ind in enumerate(sc.indenters):
        np.testing.assert_allclose(ind.position, p.position[k])
        np.testing.assert_allclose([kp.translation for kp in ind.keypoints], p.translation[k])
    assert sc.hash() == fe.scenario(p).hash()
    assert sc.gel.radius == GEL.radius and sc.friction == 2.2


def test_fe_result_conversion_uses_surface_nodes():
    from tensortouch.tools.twin.fe_physics import from_fe_result

    class R:  # a minimal FEResult-shaped object (3 nodes, 2 on the surface, 2 frames, 1 indenter)
        nodes = np.array([[0, 0, 8.0], [1, 0, 7.9], [0, 0, 1.0]])
        surface_nodes = np.array([0, 1])
        U = np.zeros((2, 3, 3))
        CNORMF = np.zeros((2, 3, 3))
        contact_owner = -np.ones((2, 3), int)
        RF = np.array([[[0, 0, 0.0]], [[0, 0, -1.0]]])
        RM = np.zeros((2, 1, 3))
        CAREA = np.array([[0.0], [2.0]])
        scenario_hash = "abc"

    R.U[1, 0, 2] = -0.5
    R.CNORMF[1, 0, 2] = -1.0
    R.contact_owner[1, 0] = 0
    sol = from_fe_result(R, GEL)
    assert isinstance(sol, PokeSolve) and sol.nodes.shape == (2, 3)
    assert sol.depth[1, 0] == pytest.approx(0.5) and sol.depth[0, 0] == 0
    np.testing.assert_allclose(sol.contact[1, 0], [0, 0, 8.0])


def test_fe_nonconvergence_retries_with_half_increments_then_names_the_poke(tmp_path, monkeypatch):
    """tools.fe.solve is replaced by a stub that never converges (the failure path only): one retry
    at half increments, then PokeSolveFailed naming the poke, and failure markers so a resumed
    recording does not solve the same scenarios again."""
    fe_mod = pytest.importorskip("tensortouch.tools.fe")
    from tensortouch.tools.twin.fe_physics import FEPhysics, PokeSolveFailed

    calls = []

    def never(scenario, progress=None):
        calls.append(scenario.solver.max_increment_mm)
        raise fe_mod.FEConvergenceError("stub: no convergence")

    monkeypatch.setattr(fe_mod, "solve", never)
    p = _poke("press")
    with pytest.raises(PokeSolveFailed, match=r"twin poke press .*did not converge in 2 attempt"):
        FEPhysics(cache=tmp_path).solve(p)
    assert calls == [0.5, 0.25]
    assert len(list(tmp_path.glob("*.failed.json"))) == 2
    with pytest.raises(PokeSolveFailed):
        FEPhysics(cache=tmp_path).solve(p)
    assert calls == [0.5, 0.25]          # markers: not solved again
    for m in tmp_path.glob("*.failed.json"):     # markers of an older solver revision: tried again
        info = json.loads(m.read_text())
        info.pop("solver_revision")
        m.write_text(json.dumps(info))
    with pytest.raises(PokeSolveFailed):
        FEPhysics(cache=tmp_path).solve(p)
    assert calls == [0.5, 0.25, 0.5, 0.25]
