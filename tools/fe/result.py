"""FE result contract: one `.npz` (allow_pickle=False) per solved scenario, written atomically.

Reference mesh stored once; per keypoint frame f (F frames), per node n (N nodes), per indenter k:

  nodes (N,3) mm          reference coordinates, gel frame (base z = 0)
  tets (E,4|10) int       tetra connectivity (gmsh/VTK node order)
  surface_nodes (M,) int  ids of the free (contact-able) surface nodes (base excluded)
  surface_tris (T,3) int  triangles of that surface, outward normals
  fixed_nodes (B,) int    ids of the encastre base nodes
  U (F,N,3) mm            displacement
  S (F,N,6) MPa           Cauchy stress, nodal (volume-weighted average), order xx,yy,zz,xy,xz,yz
  CNORMF (F,N,3) N        contact normal force on each node (zero away from contact)
  CSHEAR (F,N,3) N        contact shear (friction) force on each node
  contact_owner (F,N) int index of the indenter touching the node, -1 for none
  CAREA (F,K) mm^2        contact area per indenter (nodal areas of touching nodes)
  RF (F,K,3) N            reaction at the indenter reference point = total force the indenter
                          applies to the gel (pressing down gives RF_z < 0; Abaqus convention);
                          the gel pushes the indenter with -RF; sum_k RF = -(base reaction)
  RM (F,K,3) N*mm         moment of those forces about the current reference point
  pose_position (F,K,3) mm, pose_rotation (F,K,3) rad (rotation vector, local -> gel frame)
  converged (F,) bool     True for every frame of a normal result
  base_reaction (F,3) N   force of the fixed base on the gel (equilibrium check)
  seconds (F,) s          wall time per frame
  indenter_names (K,) str, scenario_json () str, scenario_hash () str, solver_info () str (JSON)
"""
from __future__ import annotations

import io
import json
import logging
import zipfile
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ...contracts.files import atomic_write
from .errors import FEResultError

log = logging.getLogger(__name__)

SCHEMA = "tensortouch.fe_result"
SCHEMA_VERSION = 1
STRESS_ORDER = ("xx", "yy", "zz", "xy", "xz", "yz")


@dataclass
class FEResult:
    """In-memory FE result (see module doc for shapes and units)."""

    nodes: np.ndarray
    tets: np.ndarray
    surface_nodes: np.ndarray
    surface_tris: np.ndarray
    fixed_nodes: np.ndarray
    U: np.ndarray
    S: np.ndarray
    CNORMF: np.ndarray
    CSHEAR: np.ndarray
    contact_owner: np.ndarray
    CAREA: np.ndarray
    RF: np.ndarray
    RM: np.ndarray
    pose_position: np.ndarray
    pose_rotation: np.ndarray
    converged: np.ndarray
    base_reaction: np.ndarray
    seconds: np.ndarray
    indenter_names: np.ndarray
    scenario_json: str = "{}"
    scenario_hash: str = ""
    solver_info: str = "{}"

    @property
    def n_frames(self) -> int:
        return int(self.U.shape[0])

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.shape[0])

    @property
    def n_indenters(self) -> int:
        return int(self.RF.shape[1])

    def deformed(self, frame: int) -> np.ndarray:
        """Current node coordinates (N,3) mm at `frame`."""
        return self.nodes + self.U[frame]

    def scenario(self):
        """The Scenario that produced this result."""
        from .scenario import scenario_from_dict

        return scenario_from_dict(json.loads(self.scenario_json), source="result.scenario_json")

    def check(self, where: str = "FEResult") -> "FEResult":
        """Raise FEResultError if array shapes are inconsistent."""
        N, F, K = self.n_nodes, self.n_frames, int(self.indenter_names.shape[0])
        expect = {"nodes": (N, 3), "U": (F, N, 3), "S": (F, N, 6), "CNORMF": (F, N, 3),
                  "CSHEAR": (F, N, 3), "contact_owner": (F, N), "CAREA": (F, K), "RF": (F, K, 3),
                  "RM": (F, K, 3), "pose_position": (F, K, 3), "pose_rotation": (F, K, 3),
                  "converged": (F,), "base_reaction": (F, 3), "seconds": (F,)}
        for name, shape in expect.items():
            got = getattr(self, name).shape
            if got != shape:
                raise FEResultError(f"{where}: {name} has shape {got}, expected {shape}")
        if self.tets.ndim != 2 or self.tets.shape[1] not in (4, 10):
            raise FEResultError(f"{where}: tets has shape {self.tets.shape}, expected (E,4) or (E,10)")
        if self.surface_tris.ndim != 2 or self.surface_tris.shape[1] != 3:
            raise FEResultError(f"{where}: surface_tris has shape {self.surface_tris.shape}, expected (T,3)")
        return self


def save_result(result: FEResult, path) -> Path:
    """Write `result` to `path` (.npz) atomically; refuses results with unconverged frames."""
    path = Path(path)
    result.check(str(path))
    if not bool(np.all(result.converged)):
        raise FEResultError(f"{path}: refusing to store a result with unconverged frames "
                            f"{np.flatnonzero(~result.converged).tolist()}")
    arrays = {"schema": np.array(SCHEMA), "schema_version": np.array(SCHEMA_VERSION)}
    for f in fields(FEResult):
        value = getattr(result, f.name)
        arrays[f.name] = np.array(value) if isinstance(value, str) else np.asarray(value)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return atomic_write(path, buf.getvalue())


def load_result(path) -> FEResult:
    """Load and validate an FE result written by save_result (no pickle)."""
    path = Path(path)
    if not path.is_file():
        raise FEResultError(f"{path}: FE result file not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise FEResultError(f"{path}: not a readable FE result npz ({exc})") from exc
    if str(arrays.get("schema", "")) != SCHEMA:
        raise FEResultError(f"{path}: schema: expected {SCHEMA!r}, got {arrays.get('schema')!r}")
    if int(arrays["schema_version"]) != SCHEMA_VERSION:
        raise FEResultError(f"{path}: schema_version: expected {SCHEMA_VERSION}, "
                            f"got {int(arrays['schema_version'])}")
    kwargs = {}
    for f in fields(FEResult):
        if f.name not in arrays:
            raise FEResultError(f"{path}: missing array {f.name!r}")
        value = arrays[f.name]
        kwargs[f.name] = str(value) if f.name in ("scenario_json", "scenario_hash", "solver_info") else value
    return FEResult(**kwargs).check(str(path))
