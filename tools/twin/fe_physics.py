"""FE physics backend of the twin: one tools.fe solve per poke, cached by scenario hash.

Each poke becomes an FE scenario (docs/fe.md): the unit's gel, the nominal material, the poke's
indenters with their initial poses and keypoints. Results are cached as FE result files under
`<cache>/twin/fe/<scenario hash>.npz` (runtime.paths.cache_dir() by default), so re-recording,
resuming or recording another unit with the same plan reuses them. The unit's stiffness scale is
applied by the recorder (exact for displacement-controlled indentation of a hyperelastic gel whose
constants are all scaled: displacements are unchanged, forces scale).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from runtime import paths
from tools.twin.geometry import GelSurface
from tools.twin.physics import PokeSolve
from tools.twin.trajectory import INDENTER_SET, Poke

log = logging.getLogger(__name__)


@dataclass
class FEPhysics:
    """Per-poke FE solves (tools.fe.solve) with an on-disk cache."""

    gel: object = None                 # tools.fe GelGeometry (default: the standard dome)
    material: object = None            # tools.fe Material (default: the standard soft silicone)
    mesh: object = None                # tools.fe MeshSettings
    solver: object = None              # tools.fe SolverSettings
    friction: float = 2.2
    cache: Path | None = None
    progress: object = None            # callable(frame, n_frames, message) passed to tools.fe.solve
    name: str = "fe"
    stats: dict = field(default_factory=lambda: {"solved": 0, "cached": 0, "seconds": 0.0})

    def __post_init__(self):
        from tools.fe import GelGeometry, Material, MeshSettings, SolverSettings

        self.gel = self.gel or GelGeometry()
        self.material = self.material or Material()
        self.mesh = self.mesh or MeshSettings()
        self.solver = self.solver or SolverSettings()
        self.cache = Path(self.cache) if self.cache else paths.cache_dir() / "twin" / "fe"

    def scenario(self, poke: Poke):
        from tools.fe import Indenter, Keypoint, Scenario

        inds = []
        for k, name in enumerate(poke.indenters):
            spec = INDENTER_SET[name]
            kps = [Keypoint([float(v) for v in poke.translation[k, j]], [float(v) for v in poke.rotvec[k, j]])
                   for j in range(poke.translation.shape[1])]
            inds.append(Indenter(name=f"{name}_{k}", shape=spec["shape"], params=dict(spec["params"]),
                                 position=[float(v) for v in poke.position[k]],
                                 rotation=[float(v) for v in poke.rotation[k]], keypoints=kps))
        return Scenario(gel=self.gel, material=self.material, mesh=self.mesh, indenters=inds,
                        friction=self.friction, solver=self.solver, name=f"twin-{poke.kind}").validate()

    def result(self, poke: Poke):
        """The FE result of a poke (from the cache, or solved and stored)."""
        from tools.fe import FEConvergenceError, load_result, save_result, solve

        sc = self.scenario(poke)
        path = self.cache / f"{sc.hash()}.npz"
        if path.is_file():
            self.stats["cached"] += 1
            return load_result(path)
        log.info("FE solve %s (%d indenter(s), %d keypoints)", sc.hash(), len(sc.indenters), sc.n_keypoints)
        try:
            res = solve(sc, progress=self.progress)
        except FEConvergenceError as exc:  # one retry with half the increments, then give up clearly
            log.warning("FE solve %s did not converge (%s); retrying with half the increment size", sc.hash(), exc)
            sv = sc.solver
            sc.solver = replace(sv, max_increment_mm=sv.max_increment_mm / 2, max_increment_rad=sv.max_increment_rad / 2)
            try:
                res = solve(sc, progress=self.progress)
            except FEConvergenceError as exc2:
                raise FEConvergenceError(f"twin poke {poke.kind} with {poke.indenters} (scenario {path.stem}): "
                                         f"FE did not converge even with half increments ({exc2}); "
                                         "record with another --seed or smaller TrajectoryConfig depths") from None
        save_result(res, path)
        self.stats["solved"] += 1
        self.stats["seconds"] += float(np.sum(res.seconds))
        return res

    def solve(self, poke: Poke) -> PokeSolve:
        return from_fe_result(self.result(poke), GelSurface.from_fe(self.gel), self.name)


def from_fe_result(res, surface: GelSurface, backend: str = "fe") -> PokeSolve:
    """Restrict an FEResult to the free surface nodes in the twin's PokeSolve form."""
    sn = np.asarray(res.surface_nodes)
    nodes = np.asarray(res.nodes)[sn]
    U = np.asarray(res.U)[:, sn]
    owner = np.asarray(res.contact_owner)[:, sn]
    fmag = np.linalg.norm(np.asarray(res.CNORMF)[:, sn], axis=-1)
    J, K = res.RF.shape[:2]
    contact = np.full((J, K, 3), np.nan)
    depth = np.zeros((J, K))
    n0 = surface.normals(nodes)  # depth = largest inward normal displacement of a touched node
    for j in range(J):
        for k in range(K):
            sel = owner[j] == k
            if sel.any():
                w = fmag[j, sel] + 1e-12
                contact[j, k] = (nodes[sel] * w[:, None]).sum(0) / w.sum()
                depth[j, k] = float(np.max(-np.sum(U[j, sel] * n0[sel], axis=1)))
    return PokeSolve(nodes, U, np.asarray(res.RF), np.asarray(res.RM), np.asarray(res.CAREA),
                     contact, depth, backend, str(res.scenario_hash))
