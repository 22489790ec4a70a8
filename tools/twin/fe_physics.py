"""FE physics backend of the twin: one tools.fe solve per poke, cached by scenario hash.

Each poke becomes an FE scenario (docs/fe.md): the unit's gel, the nominal material, the poke's
indenters with their initial poses and keypoints. Results are cached as FE result files under
`<cache>/twin/fe/<scenario hash>.npz` (contracts.paths.cache_dir() by default), so re-recording,
resuming or recording another unit with the same plan reuses them. The unit's stiffness scale is
applied by the recorder (exact for displacement-controlled indentation of a hyperelastic gel whose
constants are all scaled: displacements are unchanged, forces scale).
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ...contracts import paths
from ...contracts.errors import TensorTouchError
from ...contracts.files import atomic_write_json
from .geometry import GelSurface
from .physics import PokeSolve
from .trajectory import INDENTER_SET, Poke

log = logging.getLogger(__name__)


class PokeSolveFailed(TensorTouchError):
    """Every FE attempt for a poke failed; `last_keypoint` = the last keypoint frame any attempt
    reached (-1: none), so the recorder can shorten the poke to it (record.py)."""

    def __init__(self, message: str, last_keypoint: int = -1):
        super().__init__(message)
        self.last_keypoint = int(last_keypoint)



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
    refine: tuple = (0.5,)             # retries with the increments scaled by these factors
    stats: dict = field(default_factory=lambda: {"solved": 0, "cached": 0, "failed": 0, "seconds": 0.0})

    def __post_init__(self):
        from ..fe import GelGeometry, Material, MeshSettings, SolverSettings

        self.gel = self.gel or GelGeometry()
        self.material = self.material or Material()
        self.mesh = self.mesh or MeshSettings()
        self.solver = self.solver or SolverSettings()
        self.cache = Path(self.cache) if self.cache else paths.cache_dir() / "twin" / "fe"

    def scenario(self, poke: Poke):
        from ..fe import Indenter, Keypoint, Scenario

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

    def attempts(self, poke: Poke) -> list:
        """The scenarios tried for a poke, in order: as planned, then each increment refinement."""
        sc = self.scenario(poke)
        out = [sc]
        for f in self.refine:
            sv = sc.solver
            out.append(replace(sc, solver=replace(sv, max_increment_mm=sv.max_increment_mm * f,
                                                  max_increment_rad=sv.max_increment_rad * f)))
        return out

    def result(self, poke: Poke):
        """The FE result of a poke (from the cache, or solved and stored). A scenario that did not
        converge leaves `<hash>.failed.json` (message, last converged keypoint) beside the cache so a
        resumed recording does not solve it again; when every attempt fails, PokeSolveFailed says
        which keypoint was the last one reached."""
        from ..fe import FEConvergenceError, load_result, save_result, solve
        from ..fe.solver import SOLVER_REVISION

        last, reasons = -1, []
        for k, sc in enumerate(self.attempts(poke)):
            key = sc.hash()
            path, failed = self.cache / f"{key}.npz", self.cache / f"{key}.failed.json"
            if path.is_file():
                self.stats["cached"] += 1
                return load_result(path)
            info = json.loads(failed.read_text()) if failed.is_file() else None
            if info is not None and info.get("solver_revision", 1) != SOLVER_REVISION:
                log.info("FE scenario %s failed under solver revision %s; trying again with revision %d", key,
                         info.get("solver_revision", 1), SOLVER_REVISION)
                info = None
            if info is not None:
                last = max(last, int(info.get("last_keypoint", -1)))
                reasons.append(info.get("message", ""))
                log.warning("FE scenario %s did not converge earlier (%s); skipping it", key, failed.name)
                continue
            log.info("FE solve %s (%d indenter(s), %d keypoints, increments %.3g mm / %.3g rad)", key,
                     len(sc.indenters), sc.n_keypoints, sc.solver.max_increment_mm, sc.solver.max_increment_rad)
            try:
                res = solve(sc, progress=self.progress)
            except FEConvergenceError as exc:
                conv = np.asarray(exc.partial.converged, bool) if exc.partial is not None else np.zeros(0, bool)
                reached = int(np.argmin(conv)) - 1 if not conv.all() else len(conv) - 1
                last = max(last, reached)
                reasons.append(str(exc))
                log.warning("FE solve %s of twin poke %s %s did not converge (%s)%s", key, poke.kind, poke.indenters,
                            exc, "; retrying with smaller increments" if k < len(self.refine) else "")
                atomic_write_json(failed, {"scenario": key, "solver_revision": SOLVER_REVISION,
                                     "message": str(exc), "last_keypoint": reached,
                                     "keypoints": sc.n_keypoints, "max_increment_mm": sc.solver.max_increment_mm,
                                     "max_increment_rad": sc.solver.max_increment_rad})
                self.stats["failed"] = self.stats.get("failed", 0) + 1
                continue
            save_result(res, path)
            self.stats["solved"] += 1
            self.stats["seconds"] += float(np.sum(res.seconds))
            return res
        raise PokeSolveFailed(f"twin poke {poke.kind} with {poke.indenters}: FE did not converge in "
                              f"{len(reasons)} attempt(s) (last: {reasons[-1] if reasons else '?'})", last)

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
