"""Open-source hyperelastic FE of the gel (issue #3): scenario in, result out.

Public API (stable; see docs/fe.md):
    Scenario, load_scenario, save_scenario, standard_dome  -- tools.fe.scenario
    FEResult, load_result, save_result                     -- tools.fe.result
    solve(scenario, progress=None, mesh=None, engine=None) -> FEResult  -- tools.fe.solver
Heavy libraries (felupe, gmsh, trimesh) are imported lazily inside functions.
"""
from .errors import FEConvergenceError, FEError, FEResultError, ScenarioError
from .result import FEResult, load_result, save_result
from .scenario import (
    GelGeometry,
    Indenter,
    Keypoint,
    Material,
    MeshSettings,
    Scenario,
    SolverSettings,
    load_scenario,
    save_scenario,
    standard_dome,
)


def solve(scenario, progress=None, mesh=None, engine=None):
    """Solve an FE scenario; see tools.fe.solver.solve (mesh: optional prebuilt GelMesh; engine: the
    linear solver path, tools.fe.linsolve.ENGINES, None = the default)."""
    from .solver import solve as _solve

    return _solve(scenario, progress=progress, mesh=mesh, engine=engine)


__all__ = ["FEConvergenceError", "FEError", "FEResult", "FEResultError", "GelGeometry", "Indenter",
           "Keypoint", "Material", "MeshSettings", "Scenario", "ScenarioError", "SolverSettings",
           "load_result", "load_scenario", "save_result", "save_scenario", "solve", "standard_dome"]
