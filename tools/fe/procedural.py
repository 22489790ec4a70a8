"""Procedural indenter set (seed §III.B) standing in for YCB objects, which we cannot download.

Pipeline per indenter (deterministic for a given seed):
  1. build a procedural object mesh M (one of OBJECT_KINDS; trimesh primitives + manifold3d booleans),
  2. sample a surface point p with outward normal n (n . (p - centroid) > 0),
  3. cut the patch  M ∩ Ball(p - d n, r)  with d = 5 mm and r in [15, 22] mm (seed values),
  4. standardize: contact normal to the axis, random scale (patch width 6..14 mm), tip at the
     origin, cylindrical connector up to 44 mm, keep the largest connected component.
Output frame = the FE indenter frame (tip at the origin, body in z >= 0 up to 44 mm). The seed's
print/Abaqus frame (base at z = 0, tip at +44 mm) is obtained by a 180 deg rotation about x and a
44 mm translation in z; `to_print_frame` does it.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from ...contracts.files import atomic_write, atomic_write_json

log = logging.getLogger(__name__)

SPHERE_OFFSET = 5.0          # d, mm (seed)
SPHERE_RADIUS = (15.0, 22.0)  # r, mm (seed)
TOP_HEIGHT = 44.0            # tip-to-base height, mm (seed)
PATCH_WIDTH = (6.0, 14.0)    # target patch size after scaling, mm (fits the 24 mm standard gel)
CONNECTOR_RADIUS = 4.0       # mm

OBJECT_KINDS = {
    "ball": "sphere (tennis ball)", "can": "cylinder with rounded rims", "box": "cracker box",
    "mug": "cylinder with a ring handle", "banana": "bent capsule chain", "pear": "two fused spheres",
    "wrench": "bar with a ring head", "pyramid": "square pyramid", "cone": "cone with a rounded tip",
    "gear": "spur gear (teeth)", "star": "five-point star prism", "bottle": "cylinder + cone + neck",
    "donut": "torus", "lbracket": "L-shaped bracket", "drill": "cylinder body with a box grip",
}


def _m(mesh):
    import trimesh

    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)


def _union(parts):
    import trimesh

    return trimesh.boolean.union(parts, engine="manifold")


def build_object(kind: str, rng: np.random.Generator):
    """Procedural object mesh (mm) of `kind`, sizes drawn from rng."""
    import trimesh
    from trimesh import creation as c

    s = rng.uniform(0.8, 1.2)
    if kind == "ball":
        return c.icosphere(4, radius=33 * s)
    if kind == "can":
        return c.capsule(height=60 * s, radius=33 * s, count=[48, 24]) if rng.random() < 0.3 else \
            _union([c.cylinder(33 * s, 90 * s, sections=64), c.capsule(80 * s, 30 * s, count=[48, 24])])
    if kind == "box":
        return c.box([60 * s, 160 * s, 210 * s])
    if kind == "mug":
        body = c.cylinder(40 * s, 90 * s, sections=64)
        handle = c.torus(25 * s, 6 * s, major_sections=48, minor_sections=16)
        handle.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
        handle.apply_translation([40 * s, 0, 0])
        return _union([body, handle])
    if kind == "banana":
        parts = []
        for k in range(7):
            a = -0.6 + 1.2 * k / 6
            sph = c.icosphere(3, radius=(18 - 8 * abs(a)) * s)
            sph.apply_translation([100 * s * math.sin(a), 100 * s * (1 - math.cos(a)), 0])
            parts.append(sph)
        return _union(parts)
    if kind == "pear":
        a, b = c.icosphere(4, radius=35 * s), c.icosphere(4, radius=22 * s)
        b.apply_translation([0, 0, 40 * s])
        return _union([a, b])
    if kind == "wrench":
        bar = c.box([150 * s, 20 * s, 8 * s])
        ring = c.torus(18 * s, 7 * s, major_sections=48, minor_sections=16)
        ring.apply_translation([80 * s, 0, 0])
        return _union([bar, ring])
    if kind == "pyramid":
        h, w = 60 * s, 50 * s
        v = np.array([[-w, -w, 0], [w, -w, 0], [w, w, 0], [-w, w, 0], [0, 0, h]], float)
        f = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        return trimesh.Trimesh(v, f)
    if kind == "cone":
        cone = c.cone(radius=30 * s, height=70 * s, sections=64)
        tip = c.icosphere(3, radius=6 * s)
        tip.apply_translation([0, 0, 70 * s - 6 * s * 1.9])
        return _union([cone, tip])
    if kind == "gear":
        parts = [c.cylinder(40 * s, 20 * s, sections=64)]
        for k in range(12):
            t = c.box([14 * s, 10 * s, 20 * s])
            ang = 2 * math.pi * k / 12
            t.apply_transform(trimesh.transformations.rotation_matrix(ang, [0, 0, 1]))
            t.apply_translation([44 * s * math.cos(ang), 44 * s * math.sin(ang), 0])
            parts.append(t)
        return _union(parts)
    if kind == "star":
        ang = np.arange(10) * math.pi / 5
        rad = np.where(np.arange(10) % 2 == 0, 45 * s, 20 * s)
        return _star_prism(np.column_stack([rad * np.cos(ang), rad * np.sin(ang)]), 25 * s)
    if kind == "bottle":
        body = c.cylinder(30 * s, 100 * s, sections=64)
        shoulder = c.cone(radius=30 * s, height=40 * s, sections=64)
        shoulder.apply_translation([0, 0, 50 * s])
        neck = c.cylinder(10 * s, 40 * s, sections=48)
        neck.apply_translation([0, 0, 80 * s])
        return _union([body, shoulder, neck])
    if kind == "donut":
        return c.torus(40 * s, 15 * s, major_sections=64, minor_sections=24)
    if kind == "lbracket":
        a, b = c.box([80 * s, 20 * s, 15 * s]), c.box([15 * s, 20 * s, 60 * s])
        b.apply_translation([32 * s, 0, 22 * s])
        return _union([a, b])
    if kind == "drill":
        body = c.cylinder(22 * s, 110 * s, sections=64)
        body.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0]))
        grip = c.box([30 * s, 25 * s, 90 * s])
        grip.apply_translation([20 * s, 0, -45 * s])
        return _union([body, grip])
    raise ValueError(f"unknown object kind {kind!r}; expected one of {list(OBJECT_KINDS)}")


def _star_prism(poly, height):
    """Closed prism over a polygon that is star-shaped about the origin (fan triangulation)."""
    import trimesh

    n = len(poly)
    v = np.vstack([np.column_stack([poly, np.zeros(n)]), np.column_stack([poly, np.full(n, height)]),
                   [[0, 0, 0], [0, 0, height]]])
    f = []
    for i in range(n):
        j = (i + 1) % n
        f += [[2 * n, j, i], [2 * n + 1, n + i, n + j], [i, j, n + j], [i, n + j, n + i]]
    return trimesh.Trimesh(v, np.array(f))


def _rotation_to(a, b):
    """Rotation matrix taking unit vector a to unit vector b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, cth = np.cross(a, b), float(np.dot(a, b))
    if cth < -1 + 1e-9:
        axis = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + cth)


def make_indenter(kind: str, rng: np.random.Generator):
    """One standardized indenter mesh (FE frame) + its provenance dict."""
    import trimesh
    from trimesh import creation as c

    obj = build_object(kind, rng)
    centroid = obj.centroid
    for _ in range(50):
        pts, fidx = trimesh.sample.sample_surface(obj, 64, seed=int(rng.integers(2 ** 31)))
        normals = obj.face_normals[fidx]
        ok = np.einsum("ij,ij->i", normals, pts - centroid) > 0
        if ok.any():
            break
    i = int(np.flatnonzero(ok)[0])
    p, n = pts[i], normals[i]
    r = rng.uniform(*SPHERE_RADIUS)
    ball = c.icosphere(3, radius=r)
    ball.apply_translation(p - SPHERE_OFFSET * n)
    patch = trimesh.boolean.intersection([obj, ball], engine="manifold")
    R = _rotation_to(n, np.array([0.0, 0.0, -1.0]))  # contact normal -> -z (presses downward)
    patch.apply_transform(np.vstack([np.column_stack([R, np.zeros(3)]), [0, 0, 0, 1]]))
    ext = patch.extents
    scale = rng.uniform(*PATCH_WIDTH) / max(ext[0], ext[1])
    patch.apply_scale(scale)
    tip = patch.vertices[np.argmin(patch.vertices[:, 2])]
    patch.apply_translation(-tip)
    top = float(patch.vertices[:, 2].max())
    conn_r = min(CONNECTOR_RADIUS, 0.4 * min(patch.extents[0], patch.extents[1]))
    start = max(0.5 * top, 0.5)
    conn = c.cylinder(conn_r, TOP_HEIGHT - start, sections=32)
    conn.apply_translation([0, 0, (TOP_HEIGHT + start) / 2])
    centre = patch.vertices[patch.vertices[:, 2] > 0.5 * top][:, :2].mean(axis=0) if top > 0 else np.zeros(2)
    conn.apply_translation([centre[0], centre[1], 0])
    ind = _union([patch, conn])
    parts = ind.split(only_watertight=False)
    if len(parts) > 1:
        ind = max(parts, key=lambda m: abs(m.volume))
    ind.apply_translation(-ind.vertices[np.argmin(ind.vertices[:, 2])] * [1, 1, 1])
    info = {"kind": kind, "point": p.round(4).tolist(), "normal": n.round(6).tolist(),
            "sphere_radius": round(float(r), 4), "sphere_offset": SPHERE_OFFSET, "scale": round(float(scale), 6),
            "height": round(float(ind.vertices[:, 2].max()), 4), "faces": int(len(ind.faces)),
            "watertight": bool(ind.is_watertight)}
    return ind, info


def generate_set(out_dir=None, seed: int = 0, count: int = 12) -> list[Path]:
    """Write `count` standardized indenters (cycling through the kinds) + manifest.json; deterministic."""
    if out_dir is None:
        from ...contracts.paths import cache_dir

        out_dir = cache_dir() / "fe" / "indenters"
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    kinds = list(OBJECT_KINDS)
    paths, manifest = [], []
    for k in range(count):
        kind = kinds[k % len(kinds)]
        rng = np.random.default_rng([seed, k])
        mesh, info = make_indenter(kind, rng)
        path = out / f"indenter_{k:02d}_{kind}.stl"
        atomic_write(path, lambda fh, mesh=mesh: mesh.export(file_obj=fh, file_type="stl"))
        paths.append(path)
        manifest.append({"file": path.name, "seed": [seed, k], **info})
        log.info("indenter %s: %s", path.name, info)
    atomic_write_json(out / "manifest.json", {"frame": "FE indenter frame: tip at origin, body z >= 0",
                                              "indenters": manifest}, indent=2)
    return paths


def to_print_frame(mesh):
    """Copy of an FE-frame indenter mesh in the seed's print frame (base z = 0, tip at z = 44 mm)."""
    m = mesh.copy()
    m.apply_transform(np.diag([1.0, -1.0, -1.0, 1.0]))
    m.apply_translation([0, 0, TOP_HEIGHT])
    return m
