"""Gel meshing with gmsh (OpenCASCADE kernel): dome / flattened dome / flat pad / STL.

Element size `size_top` within `refine_depth` of the free surface, growing to `size_inside` in the
core (gmsh Distance + Threshold fields). The surface/base extraction is done in numpy on the tets.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .errors import ScenarioError
from .scenario import GelGeometry, MeshSettings

log = logging.getLogger(__name__)

BASE_TOL = 1e-6  # mm: nodes with z below this are on the fixed base
_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])  # outward for positive tets


@dataclass
class GelMesh:
    """Tetra mesh of the gel plus derived surface data (all in mm)."""

    nodes: np.ndarray          # (N,3)
    tets: np.ndarray           # (E,4) or (E,10)
    surface_tris: np.ndarray   # (T,3) free surface (base excluded), outward
    surface_nodes: np.ndarray  # (M,)
    fixed_nodes: np.ndarray    # (B,)
    node_area: np.ndarray      # (N,) lumped free-surface area per node (0 inside)

    @property
    def corner_tets(self) -> np.ndarray:
        return self.tets[:, :4]


def _occ_gel(gmsh, g: GelGeometry) -> None:
    occ = gmsh.model.occ
    if g.kind in ("dome", "flattened_dome"):
        a = g.radius
        h = g.radius if g.kind == "dome" else g.cap_height
        rs = (a * a + h * h) / (2 * h)
        zc = g.skirt + h - rs
        sphere = occ.addSphere(0, 0, zc, rs)
        clip = occ.addCylinder(0, 0, g.skirt, 0, 0, h + 1.0, a * 1.001)
        cap, _ = occ.intersect([(3, sphere)], [(3, clip)])
        parts = cap
        if g.skirt > 0:
            skirt = occ.addCylinder(0, 0, 0, 0, 0, g.skirt, a)
            parts, _ = occ.fuse(cap, [(3, skirt)])
        occ.synchronize()
        if len(gmsh.model.getEntities(3)) != 1:
            raise ScenarioError(f"gel: geometry of kind {g.kind!r} did not produce one volume")
    elif g.kind == "flat_pad":
        occ.addBox(-g.size_x / 2, -g.size_y / 2, 0, g.size_x, g.size_y, g.thickness)
        occ.synchronize()
    else:
        raise ScenarioError(f"gel.kind: {g.kind!r} is not an OCC kind")


def _stl_gel(gmsh, path: str) -> None:
    gmsh.merge(path)
    gmsh.model.mesh.classifySurfaces(40 * math.pi / 180, True, True, math.pi)
    gmsh.model.mesh.createGeometry()
    surfaces = [s[1] for s in gmsh.model.getEntities(2)]
    loop = gmsh.model.geo.addSurfaceLoop(surfaces)
    gmsh.model.geo.addVolume([loop])
    gmsh.model.geo.synchronize()


def _ignore_sigpipe_again() -> None:
    """Python ignores SIGPIPE (a closed pipe or socket is an OSError); gmsh.initialize sets it back to the
    default, after which writing to a closed socket anywhere in the process kills it. Ignore it again."""
    import signal
    import threading

    if hasattr(signal, "SIGPIPE") and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)


def mesh_gel(gel: GelGeometry, settings: MeshSettings, stl_path: str = "") -> GelMesh:
    """Mesh the gel; returns nodes, tets and the free surface. Deterministic for fixed inputs."""
    import gmsh

    gmsh.initialize(interruptible=False)
    _ignore_sigpipe_again()    # gmsh's initialize resets SIGPIPE to its default (kill the process)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("gel")
        if gel.kind == "stl":
            _stl_gel(gmsh, stl_path or gel.stl_path)
        else:
            _occ_gel(gmsh, gel)
        boundary = gmsh.model.getBoundary(gmsh.model.getEntities(3), oriented=False)
        free = []
        for dim, tag in boundary:
            lo = gmsh.model.getBoundingBox(dim, tag)
            if not (abs(lo[2]) < 1e-6 and abs(lo[5]) < 1e-6):  # skip the flat base z = 0
                free.append(abs(tag))
        fd = gmsh.model.mesh.field
        fd.add("Distance", 1)
        fd.setNumbers(1, "SurfacesList", free)
        fd.setNumber(1, "Sampling", 40)
        fd.add("Threshold", 2)
        fd.setNumber(2, "InField", 1)
        fd.setNumber(2, "SizeMin", settings.size_top)
        fd.setNumber(2, "SizeMax", settings.size_inside)
        fd.setNumber(2, "DistMin", settings.refine_depth)
        fd.setNumber(2, "DistMax", settings.refine_depth + 2.0 * settings.size_inside)
        if settings.refine_radius > 0:  # size grows linearly (slope 0.3) outside a ball at the top
            top = max(gmsh.model.getBoundingBox(-1, -1)[5], 0.0)
            fd.add("MathEval", 3)
            fd.setString(3, "F", f"Min({settings.size_inside}, {settings.size_top} + 0.3*Max(0, "
                                 f"Sqrt(x*x+y*y+(z-{top})*(z-{top})) - {settings.refine_radius}))")
            fd.setAsBackgroundMesh(3)
        else:
            fd.setAsBackgroundMesh(2)
        for opt in ("MeshSizeExtendFromBoundary", "MeshSizeFromPoints", "MeshSizeFromCurvature"):
            gmsh.option.setNumber(f"Mesh.{opt}", 0)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, enodes = gmsh.model.mesh.getElementsByType(4)
    except Exception as exc:  # gmsh raises plain Exception
        raise ScenarioError(f"gel: gmsh could not mesh {gel.kind!r}: {exc}") from exc
    finally:
        gmsh.finalize()
    nodes_all = np.asarray(coords, float).reshape(-1, 3)
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags] = np.arange(len(tags))
    tets = index[np.asarray(enodes, np.int64).reshape(-1, 4)]
    used = np.unique(tets)
    remap = np.full(len(nodes_all), -1, np.int64)
    remap[used] = np.arange(len(used))
    gm = finish_mesh(nodes_all[used], remap[tets])
    return quadratic(gm) if settings.order == 2 else gm


def finish_mesh(nodes: np.ndarray, tets: np.ndarray) -> GelMesh:
    """Orient tets positively and derive free surface, base nodes and nodal areas."""
    nodes = np.asarray(nodes, float)
    tets = np.asarray(tets, np.int64).copy()
    x = nodes[tets[:, :4]]
    vol6 = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])
    neg = vol6 < 0
    if np.any(neg):  # swap corner nodes 1,2 (and the matching mid-edge nodes for tet10)
        tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
        if tets.shape[1] == 10:  # VTK/gmsh order edges: 01,12,20,03,13,23 -> swap (01<->02), (13<->23)
            tets[neg, 4], tets[neg, 6] = tets[neg, 6].copy(), tets[neg, 4].copy()
            tets[neg, 8], tets[neg, 9] = tets[neg, 9].copy(), tets[neg, 8].copy()
    faces = tets[:, :4][:, _FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = faces[counts[inv.ravel()] == 1]
    on_base = np.all(nodes[boundary, 2] < BASE_TOL, axis=1)
    tris = boundary[~on_base]
    fixed = np.flatnonzero(nodes[:, 2] < BASE_TOL)
    p = nodes[tris]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    node_area = np.bincount(tris.ravel(), np.repeat(area / 3, 3), minlength=len(nodes))
    surface_nodes = np.setdiff1d(np.unique(tris), fixed)
    log.info("gel mesh: %d nodes, %d tets, %d surface nodes", len(nodes), len(tets), len(surface_nodes))
    return GelMesh(nodes, tets, tris, surface_nodes, fixed, node_area)


_EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))  # VTK tetra10 mid-edge order


def quadratic(gm: GelMesh) -> GelMesh:
    """10-node tets with straight-edge midpoints (VTK order) from a linear GelMesh. Contact areas
    are lumped by splitting each surface triangle into 4: corners A/12, mid-edge nodes A/4."""
    tets = gm.corner_tets
    pairs = np.sort(tets[:, _EDGES].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(pairs, axis=0, return_inverse=True)
    n0 = len(gm.nodes)
    nodes = np.vstack([gm.nodes, 0.5 * (gm.nodes[uniq[:, 0]] + gm.nodes[uniq[:, 1]])])
    tets10 = np.hstack([tets, n0 + inv.reshape(-1, 6)])
    lookup = {tuple(e): n0 + i for i, e in enumerate(uniq.tolist())}
    tris = gm.surface_tris
    mids = np.array([[lookup[tuple(sorted((t[a], t[b])))] for a, b in ((0, 1), (1, 2), (0, 2))]
                     for t in tris.tolist()]).reshape(-1, 3)
    p = gm.nodes[tris]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    node_area = np.bincount(tris.ravel(), np.repeat(area / 12, 3), minlength=len(nodes))
    node_area += np.bincount(mids.ravel(), np.repeat(area / 4, 3), minlength=len(nodes))
    fixed = np.flatnonzero(nodes[:, 2] < BASE_TOL)
    surface_nodes = np.setdiff1d(np.unique(np.concatenate([tris.ravel(), mids.ravel()])), fixed)
    return GelMesh(nodes, tets10, tris, surface_nodes, fixed, node_area)


def graded(half: float, h_min: float, n: int, symmetric: bool = True) -> np.ndarray:
    """Coordinates from 0 to `half` with geometric growth from spacing h_min (mirrored if symmetric)."""
    from scipy.optimize import brentq

    q = 1.0 if abs(half - n * h_min) < 1e-12 else brentq(
        lambda q: h_min * (q ** n - 1) / (q - 1) - half, 1.0 + 1e-9, 10.0)
    t = np.concatenate([[0.0], np.cumsum(h_min * q ** np.arange(n))])
    t *= half / t[-1]
    return np.concatenate([-t[:0:-1], t]) if symmetric else t


def box_mesh(size=(10.0, 10.0, 5.0), n=(5, 5, 3), coords=None) -> GelMesh:
    """Structured tet mesh of a box [-sx/2,sx/2]x[-sy/2,sy/2]x[0,sz] (tests; no gmsh), or of the
    tensor grid `coords` = (xs, ys, zs) when given (e.g. from `graded`)."""
    xs = list(coords) if coords is not None else [
        np.linspace(-size[0] / 2, size[0] / 2, n[0] + 1), np.linspace(-size[1] / 2, size[1] / 2, n[1] + 1),
        np.linspace(0, size[2], n[2] + 1)]
    n = [len(c) - 1 for c in xs]
    X, Y, Z = np.meshgrid(*xs, indexing="ij")
    nodes = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(nodes.shape[0]).reshape(X.shape)
    hexes = []
    for i in range(n[0]):
        for j in range(n[1]):
            for k in range(n[2]):
                c = idx[i:i + 2, j:j + 2, k:k + 2]
                hexes.append([c[0, 0, 0], c[1, 0, 0], c[1, 1, 0], c[0, 1, 0],
                              c[0, 0, 1], c[1, 0, 1], c[1, 1, 1], c[0, 1, 1]])
    h = np.array(hexes)
    # 6-tet Kuhn split around the diagonal 0-6 (conforming across neighbouring cells)
    split = [[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]]
    tets = h[:, split].reshape(-1, 4)
    return finish_mesh(nodes, tets)
