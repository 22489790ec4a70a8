"""Rigid indenters as signed-distance shapes in their local frame (tip at origin, body in z >= 0).

Each shape returns, for local points (n,3): signed distance d (n,) mm (negative inside) and the
unit outward gradient (n,3). The Hessian (curvature, needed by the exact contact tangent) is
analytic for the sphere and a central difference of the gradient otherwise. A pose maps local to
gel frame: x = R @ xi + p.
"""
from __future__ import annotations

import logging
import math

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .errors import ScenarioError
from .scenario import Indenter

log = logging.getLogger(__name__)

FD_STEP = 1e-5  # mm, central difference step of the gradient for Hessians


def _safe_unit(v):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-300), n[..., 0]


def _box_sdf(p, half, r=0.0):
    """Rounded box centred at 0 with half sizes `half`, rounding radius r."""
    q = np.abs(p) - (np.asarray(half) - r)
    out = np.maximum(q, 0.0)
    outside = np.linalg.norm(out, axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    d = outside + inside - r
    grad = np.zeros_like(p)
    o = outside > 0
    grad[o] = out[o] / outside[o, None]
    k = np.argmax(q[~o], axis=1)
    gi = np.zeros((int((~o).sum()), 3))
    gi[np.arange(len(k)), k] = 1.0
    grad[~o] = gi
    return d, grad * np.sign(p + 1e-300)


class Shape:
    """Base class: subclasses implement sdf(xi) -> (d, grad); radius_bound bounds the body."""

    radius_bound = math.inf

    def sdf(self, xi):
        raise NotImplementedError

    def hessian(self, xi):
        h = FD_STEP
        H = np.zeros((len(xi), 3, 3))
        for j in range(3):
            e = np.zeros(3)
            e[j] = h
            H[:, :, j] = (self.sdf(xi + e)[1] - self.sdf(xi - e)[1]) / (2 * h)
        return 0.5 * (H + H.transpose(0, 2, 1))


class Sphere(Shape):
    def __init__(self, radius):
        self.r = radius
        self.c = np.array([0.0, 0.0, radius])

    def sdf(self, xi):
        n, dist = _safe_unit(xi - self.c)
        return dist - self.r, n

    def hessian(self, xi):
        n, dist = _safe_unit(xi - self.c)
        return (np.eye(3) - np.einsum("ai,aj->aij", n, n)) / np.maximum(dist, 1e-9)[:, None, None]


class Cylinder(Shape):
    """Axis along local x through (0,0,radius), flat ends at x = +-length/2."""

    def __init__(self, radius, length, fillet=0.0):
        self.r, self.hl, self.f = radius, length / 2, min(fillet, radius / 2, length / 4)

    def sdf(self, xi):
        yz = xi[:, 1:] - np.array([0.0, self.r])
        ryz = np.linalg.norm(yz, axis=1)
        q = np.column_stack([ryz - self.r + self.f, np.abs(xi[:, 0]) - self.hl + self.f])
        out = np.maximum(q, 0)
        lo = np.linalg.norm(out, axis=1)
        d = lo + np.minimum(q.max(axis=1), 0) - self.f
        g2 = np.where(lo[:, None] > 0, out / np.maximum(lo, 1e-300)[:, None],
                      np.eye(2)[np.argmax(q, axis=1)])
        radial = yz / np.maximum(ryz, 1e-300)[:, None]
        grad = np.column_stack([g2[:, 1] * np.sign(xi[:, 0]), g2[:, 0:1] * radial])
        return d, grad


class BoxEdge(Shape):
    """Square prism (side `width`, length along x) rotated 45 deg so one edge points down at 0."""

    def __init__(self, length, width, fillet=0.2):
        self.half = np.array([length / 2, width / 2, width / 2])
        self.f = min(fillet, width / 4)
        self.rot = Rotation.from_euler("x", 45, degrees=True).as_matrix()
        self.c = np.array([0.0, 0.0, width / math.sqrt(2) - self.f * (math.sqrt(2) - 1)])

    def sdf(self, xi):
        p = (xi - self.c) @ self.rot  # world->box: R^T (xi - c)
        d, g = _box_sdf(p, self.half, self.f)
        return d, g @ self.rot.T


class Flat(Shape):
    """Flat circular punch of `radius`, face at z = 0, height 10 mm, rim rounded by `fillet`."""

    def __init__(self, radius, fillet=0.5, height=10.0):
        self.r, self.f, self.hh = radius, min(fillet, radius / 2), height / 2

    def sdf(self, xi):
        rxy = np.linalg.norm(xi[:, :2], axis=1)
        q = np.column_stack([rxy - self.r + self.f, np.abs(xi[:, 2] - self.hh) - self.hh + self.f])
        out = np.maximum(q, 0)
        lo = np.linalg.norm(out, axis=1)
        d = lo + np.minimum(q.max(axis=1), 0) - self.f
        g2 = np.where(lo[:, None] > 0, out / np.maximum(lo, 1e-300)[:, None],
                      np.eye(2)[np.argmax(q, axis=1)])
        radial = xi[:, :2] / np.maximum(rxy, 1e-300)[:, None]
        return d, np.column_stack([g2[:, 0:1] * radial, g2[:, 1] * np.sign(xi[:, 2] - self.hh)])


class Torus(Shape):
    """Ring in the local xy plane, centre (0,0,minor), lowest points at z = 0."""

    def __init__(self, major_radius, minor_radius):
        self.R, self.r = major_radius, minor_radius

    def sdf(self, xi):
        rxy = np.linalg.norm(xi[:, :2], axis=1)
        radial = xi[:, :2] / np.maximum(rxy, 1e-300)[:, None]
        q = np.column_stack([rxy - self.R, xi[:, 2] - self.r])
        n2, dist = _safe_unit(q)
        return dist - self.r, np.column_stack([n2[:, 0:1] * radial, n2[:, 1]])


class MeshShape(Shape):
    """Closed triangle mesh: exact point-triangle distance over the k faces with the nearest
    centroids; sign from angle-weighted pseudonormals of the closest feature (face, edge or
    vertex; Baerentzen & Aanaes 2005), which is exact for closed meshes."""

    def __init__(self, vertices, faces, k=24):
        import trimesh

        mesh = trimesh.Trimesh(vertices, faces, process=False)
        self.v = np.asarray(vertices, float)
        self.f = np.asarray(faces, np.int64)
        tri = self.v[self.f]
        self.n = _safe_unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))[0]
        self.vn = np.asarray(mesh.vertex_normals, float)  # angle-weighted
        edges = np.sort(self.f[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
        key = edges[:, 0] * len(self.v) + edges[:, 1]
        uniq, inv = np.unique(key, return_inverse=True)
        en = np.zeros((len(uniq), 3))
        np.add.at(en, inv, np.repeat(self.n, 3, axis=0))
        self.edge_key, self.edge_n = uniq, _safe_unit(en)[0]
        self.tree = cKDTree(tri.mean(axis=1))
        self.k = min(k, len(self.f))

    def _pseudonormal(self, face, cp):
        """Pseudonormal at the closest points cp (n,3) on faces `face` (n,)."""
        tri = self.v[self.f[face]]
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        v0, v1, v2 = b - a, c - a, cp - a
        d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
        d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
        den = np.maximum(d00 * d11 - d01 * d01, 1e-300)
        w1 = (d11 * d20 - d01 * d21) / den
        w2 = (d00 * d21 - d01 * d20) / den
        bary = np.column_stack([1 - w1 - w2, w1, w2])
        zero = bary < 1e-7
        nz = zero.sum(1)
        out = self.n[face].copy()
        vtx = nz >= 2  # at a vertex: the corner with the largest weight
        if np.any(vtx):
            out[vtx] = self.vn[self.f[face[vtx], np.argmax(bary[vtx], axis=1)]]
        edg = nz == 1  # on an edge: the two corners with non-zero weight
        if np.any(edg):
            fv = self.f[face[edg]]
            zi = np.argmax(zero[edg], axis=1)
            i, j = fv[np.arange(len(zi)), (zi + 1) % 3], fv[np.arange(len(zi)), (zi + 2) % 3]
            key = np.minimum(i, j) * len(self.v) + np.maximum(i, j)
            out[edg] = self.edge_n[np.searchsorted(self.edge_key, key)]
        return out

    def sdf(self, xi):
        _, cand = self.tree.query(xi, k=self.k)
        cand = cand.reshape(len(xi), -1)
        tri = self.v[self.f[cand]]  # (n,k,3,3)
        cp = _closest_on_triangles(xi[:, None, :].repeat(cand.shape[1], 1), tri)
        dist = np.linalg.norm(xi[:, None] - cp, axis=2)
        best = np.argmin(dist, axis=1)
        rows = np.arange(len(xi))
        cpb = cp[rows, best]
        dv = xi - cpb
        pn = self._pseudonormal(cand[rows, best], cpb)
        sign = np.where(np.einsum("nj,nj->n", dv, pn) >= 0, 1.0, -1.0)
        g, dmag = _safe_unit(dv)
        small = dmag < 1e-9
        g = g * sign[:, None]
        g[small] = pn[small]
        return sign * dmag, g


def _closest_on_triangles(p, tri):
    """Closest points on triangles (...,3,3) to points (...,3) (Ericson's region tests)."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp_ = p - c
    d5, d6 = (ab * cp_).sum(-1), (ac * cp_).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = np.where(np.abs(va + vb + vc) > 1e-300, va + vb + vc, 1e-300)
    v, w = vb / denom, vc / denom
    res = a + ab * v[..., None] + ac * w[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    cases = [  # later cases override earlier ones (Ericson order reversed)
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * t_bc[..., None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * t_ac[..., None]),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * t_ab[..., None]),
        ((d6 >= 0) & (d5 <= d6), c), ((d3 >= 0) & (d4 <= d3), b), ((d1 <= 0) & (d2 <= 0), a)]
    for mask, val in cases:
        res = np.where(mask[..., None], val, res)
    return res


MAX_EDGE = 0.75  # mm: mesh indenters are subdivided so the k nearest face centroids contain the
                 # closest face of any nearby point (large faces would defeat the candidate search)


def load_mesh_shape(path, max_edge: float = MAX_EDGE) -> MeshShape:
    import trimesh

    mesh = trimesh.load(str(path), force="mesh")
    if not mesh.is_watertight:
        log.warning("indenter mesh %s is not watertight; signed distance may be wrong", path)
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge, max_iter=20)
    return MeshShape(v, f)


def make_shape(ind: Indenter, resolve=lambda p: p) -> Shape:
    """Build the Shape of an indenter description."""
    p = ind.params
    if ind.shape == "sphere":
        return Sphere(p["radius"])
    if ind.shape == "cylinder":
        return Cylinder(p["radius"], p["length"], p.get("fillet", 0.3))
    if ind.shape == "box_edge":
        return BoxEdge(p["length"], p["width"], p.get("fillet", 0.2))
    if ind.shape == "flat":
        return Flat(p["radius"], p["fillet"], p.get("height", 10.0))
    if ind.shape == "torus":
        return Torus(p["major_radius"], p["minor_radius"])
    if ind.shape == "mesh":
        return load_mesh_shape(resolve(ind.mesh_path))
    raise ScenarioError(f"indenter {ind.name}: unknown shape {ind.shape!r}")


def rotmat(rotvec) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(rotvec, float)).as_matrix()


def pose_at(ind: Indenter, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose (position, rotation vector) at fractional keypoint index s (0 = first keypoint,
    s = -1 = initial pose); linear interpolation of translation and rotation vector."""
    kps = [(np.zeros(3), np.zeros(3))] + [(np.asarray(k.translation, float), np.asarray(k.rotation, float))
                                          for k in ind.keypoints]
    s = min(max(s + 1.0, 0.0), len(kps) - 1.0)
    i = min(int(math.floor(s)), len(kps) - 2)
    f = s - i
    t = (1 - f) * kps[i][0] + f * kps[i + 1][0]
    r = (1 - f) * kps[i][1] + f * kps[i + 1][1]
    R = rotmat(r) @ rotmat(ind.rotation)
    return np.asarray(ind.position, float) + t, Rotation.from_matrix(R).as_rotvec()
