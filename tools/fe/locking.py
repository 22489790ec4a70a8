"""Volumetric-locking study: linear tets (our solver) vs quadratic tets with a mixed u/p/J
(P2/P0, felupe SolidBodyNearlyIncompressible, the analogue of Abaqus' hybrid elements).

Load case without contact so only the element formulation differs: a flat pad (bottom fixed) whose
top nodes within `punch_radius` of the centre are pushed down by `depth` (bonded rigid punch).
Returns the punch force per formulation; `python -m tools.fe.locking` prints the table.
"""
from __future__ import annotations

import logging
import time

import numpy as np

from .materials import YeohUmat
from .mesh import mesh_gel
from .scenario import GelGeometry, Material, MeshSettings

log = logging.getLogger(__name__)


def punch_force(gm, material: Material, bulk: float, formulation: str, depth=0.5, punch_radius=2.0,
                steps=4) -> float:
    """Reaction force (N, positive = compression) of the bonded punch for one formulation:
    'p1' (linear tets, displacement), 'p2' (quadratic tets, displacement), 'p2-upj' (mixed)."""
    import felupe as fem

    mesh = fem.Mesh(gm.nodes, gm.corner_tets, "tetra")
    if formulation.startswith("p2"):
        mesh = mesh.add_midpoints_edges()
        region = fem.RegionQuadraticTetra(mesh)
    else:
        region = fem.RegionTetra(mesh)
    u = fem.Field(region, dim=3)
    field = fem.FieldContainer([u])
    m = material
    if formulation == "p2-upj":
        solid = fem.SolidBodyNearlyIncompressible(YeohUmat(m.C10, m.C20, m.C30, 0.0), field, bulk=bulk)
    else:
        solid = fem.SolidBody(YeohUmat(m.C10, m.C20, m.C30, bulk), field)
    x = mesh.points
    top = np.isclose(x[:, 2], x[:, 2].max())
    punch = top & (np.hypot(x[:, 0], x[:, 1]) <= punch_radius)
    bounds = {"fixed": fem.Boundary(u, fz=0.0),
              "punch": fem.Boundary(u, mask=punch)}
    ramp = {bounds["punch"]: np.outer(np.linspace(0, -depth, steps + 1)[1:], [0, 0, 1])}
    step = fem.Step(items=[solid], ramp=ramp, boundaries=bounds)
    fem.Job(steps=[step]).evaluate(verbose=0, tol=1e-8)
    f = np.asarray(solid.assemble.vector(field).todense()).reshape(-1, 3)
    return float(-f[punch, 2].sum())


def locking_study(size_top=0.6, ratios=(50.0, 5000.0), material: Material | None = None, depth=0.5):
    """Punch forces for P1 / P2 / P2-u/p/J at the given bulk/shear ratios (one mesh)."""
    m = material or Material()
    gel = GelGeometry(kind="flat_pad", size_x=16.0, size_y=16.0, thickness=8.0)
    gm = mesh_gel(gel, MeshSettings(size_top=size_top, size_inside=2.0, refine_radius=3.0))
    rows = []
    for ratio in ratios:
        bulk = ratio * m.shear_modulus
        for form in ("p1", "p2", "p2-upj"):
            t = time.time()
            f = punch_force(gm, m, bulk, form, depth=depth)
            rows.append({"bulk_ratio": ratio, "formulation": form, "force_N": f,
                         "seconds": round(time.time() - t, 2), "nodes": len(gm.nodes)})
    return rows

