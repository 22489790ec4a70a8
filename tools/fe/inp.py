"""Export a scenario as an `.inp` deck for CalculiX (default) or Abaqus (cross-checks of tools.fe).

`dialect="ccx"` (`export_inp_ccx`, runs in CalculiX 2.20 as written): flat model (no parts or
instances), base fixed by *BOUNDARY 1-3, gel as C3D4 (P1 mesh) or C3D10 (P2 mesh); each indenter is
a rigid body (*RIGID BODY, NSET, REF NODE at the tip, ROT NODE carrying the rotation vector) made of
one thin C3D4 per surface triangle whose outer face is the contact master surface; node-to-surface
penalty contact (the gel's surface nodes against the indenter's faces, as tools.fe solves it: with a
surface-to-surface pair a frictionless 1.5 mm press read 6 % apart, node-to-surface 0.5 %) with the
pressure-overclosure slope, and the stick slope of *FRICTION, set to the values tools.fe uses (ccx's
default penalty reads forces 7-10 % low); no *FRICTION when mu = 0; the bulk modulus is the one
tools.fe uses (`bulk="solver"`: capped for P1, docs/fe.md "Volumetric locking") or the material's D1
(`bulk="material"`); increments per step as in tools.fe (or at most `max_increment_mm`); the reaction
at each reference node printed to the .dat file (`tools.fe.ccx` reads it).

`dialect="abaqus"`: gel our gmsh mesh as C3D4H (hybrid linear tets), base encastre, Yeoh/NH/MR hyperelastic with the
scenario's D1 (the true material, no bulk cap). Indenters: discrete rigid surfaces (R3D3) tessellated
from the analytic shapes or read from the mesh file, each with a reference node at its tip; one
*STEP per keypoint moving the reference nodes (U = translation, UR = rotation vector, both relative
to the initial pose, as in the seed). Hard contact with Coulomb friction mu; field output U, S, RF,
CNORMF, CSHEAR, CNAREA. Coordinates in mm, forces in N, stresses in MPa.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from ...contracts.files import atomic_write_text

from .indenters import rotmat
from .scenario import Indenter, Scenario

log = logging.getLogger(__name__)

_FACE_IDS = ((0, 1, 2), (0, 1, 3), (1, 2, 3), (0, 2, 3))  # Abaqus C3D4 faces S1..S4 (node sets)


def indenter_surface(ind: Indenter, resolve=lambda p: p):
    """Triangle mesh (local frame) of an indenter for rigid-surface export."""
    import trimesh
    from trimesh import creation as c

    p = ind.params
    if ind.shape == "sphere":
        m = c.icosphere(4, radius=p["radius"])
        m.apply_translation([0, 0, p["radius"]])
    elif ind.shape == "cylinder":
        m = c.cylinder(p["radius"], p["length"], sections=64)
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        m.apply_translation([0, 0, p["radius"]])
    elif ind.shape == "box_edge":
        w = p["width"]
        m = c.box([p["length"], w, w])
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 4, [1, 0, 0]))
        m.apply_translation([0, 0, w / np.sqrt(2)])
    elif ind.shape == "flat":
        h = p.get("height", 10.0)
        m = c.cylinder(p["radius"], h, sections=64)
        m.apply_translation([0, 0, h / 2])
    elif ind.shape == "torus":
        m = c.torus(p["major_radius"], p["minor_radius"], major_sections=64, minor_sections=24)
        m.apply_translation([0, 0, p["minor_radius"]])
    else:
        m = trimesh.load(str(resolve(ind.mesh_path)), force="mesh")
    return m


def _lines(values, per=8):
    values = list(values)
    return "\n".join(", ".join(str(v) for v in values[i:i + per]) for i in range(0, len(values), per))


DIALECTS = ("ccx", "abaqus")
BULK_CHOICES = ("solver", "material")
RIGID_THICKNESS = 0.2   # mm: depth of the thin tets under each indenter surface triangle (ccx)
RIGID_MARGIN = 1.0      # mm: indenter triangles farther than this from the gel's box are left out
CCX_MIN_INCREMENT = 1e-5  # fraction of a step
# mm: increments for C3D10 (P2) decks at the true D1. At 0.5 mm, ccx's C3D10 on a top-1.0 mm P2
# mesh diverges in the press from 1.5 to 2 mm (residual 1e8 in the first iterations of the
# increment, then stalls); at 0.25 mm it converges in <= 8 iterations per increment (docs/fe.md).
C3D10_MAX_INCREMENT_MM = 0.25


def export_inp(scenario: Scenario, path, mesh=None, dialect: str = "ccx", bulk: str = "solver",
               max_increment_mm: float | None = None) -> Path:
    """Write the deck (atomic) for `dialect` ("ccx" or "abaqus") and return its path."""
    if dialect not in DIALECTS:
        raise ValueError(f"dialect {dialect!r}: expected one of {DIALECTS}")
    if dialect == "ccx":
        return export_inp_ccx(scenario, path, mesh=mesh, bulk=bulk, max_increment_mm=max_increment_mm)
    return _export_abaqus(scenario, path, mesh)


def _write(path, lines) -> Path:
    return atomic_write_text(path, "\n".join(lines) + "\n")


def _gel_faces(gm) -> dict[int, list[int]]:
    """Free-surface element faces of the gel: face number (0..3 = S1..S4) -> 1-based element ids."""
    surf = {tuple(sorted(t)) for t in gm.surface_tris.tolist()}
    faces = {k: [] for k in range(4)}
    for e, t in enumerate(gm.corner_tets):
        for k, ids in enumerate(_FACE_IDS):
            if tuple(sorted(t[list(ids)])) in surf:
                faces[k].append(e + 1)
    return faces


def _gel_lines(gm, element_type: str, tets) -> list[str]:
    """The gel's node rows (after a *NODE line), its elements (set GEL), the fixed base (set BASE)
    and its free surface GEL_TOP as element-face sets TOP_S1..TOP_S4."""
    out = [f"{i + 1}, {x:.6f}, {y:.6f}, {z:.6f}" for i, (x, y, z) in enumerate(gm.nodes)]
    out.append(f"*ELEMENT, TYPE={element_type}, ELSET=GEL")
    out += [f"{e + 1}, " + ", ".join(str(n + 1) for n in t) for e, t in enumerate(tets)]
    out += ["*NSET, NSET=BASE", _lines(gm.fixed_nodes + 1)]
    faces = _gel_faces(gm)
    for k, els in faces.items():
        if els:
            out += [f"*ELSET, ELSET=TOP_S{k + 1}", _lines(els)]
    out.append("*SURFACE, TYPE=ELEMENT, NAME=GEL_TOP")
    out += [f"TOP_S{k + 1}, S{k + 1}" for k, els in faces.items() if els]
    return out


def _material_lines(m, d1: float) -> list[str]:
    if m.model == "yeoh":
        return [f"*HYPERELASTIC, YEOH\n{m.C10:.8g}, {m.C20:.8g}, {m.C30:.8g}, {d1:.8g}, 0., 0."]
    if m.model == "neo_hookean":
        return [f"*HYPERELASTIC, NEO HOOKE\n{m.C10:.8g}, {d1:.8g}"]
    return [f"*HYPERELASTIC, MOONEY-RIVLIN\n{m.C10:.8g}, {m.C01:.8g}, {d1:.8g}"]


def rigid_tets(tri) -> tuple[np.ndarray, np.ndarray]:
    """Thin C3D4 under each outward triangle (a, b, c) of a closed surface: nodes (V+V, 3) = the
    surface vertices then each vertex moved RIGID_THICKNESS inward along its normal; tets (T, 4) =
    (a, c, b, a_inner), positive volume, whose face 1 (nodes 1-2-3) is the outer triangle."""
    v = np.asarray(tri.vertices, float)
    f = np.asarray(tri.faces, int)
    inner = v - RIGID_THICKNESS * np.asarray(tri.vertex_normals, float)
    tets = np.stack([f[:, 0], f[:, 2], f[:, 1], f[:, 0] + len(v)], axis=1)
    nodes = np.vstack([v, inner])
    x = nodes[tets]
    vol = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])
    if (vol <= 0).any():
        raise ValueError(f"indenter surface: {int((vol <= 0).sum())} triangles face inward or meet at "
                         "too sharp an edge for the rigid-body tets")
    return nodes, tets


def _near_gel(ind, nodes, tets, lo, hi) -> np.ndarray:
    """The rigid tets with a node inside the gel's bounding box (grown by RIGID_MARGIN) at the
    initial pose or any keypoint: the rest of the indenter can never touch the gel."""
    from .indenters import pose_at

    keep = np.zeros(len(tets), bool)
    for s in np.linspace(-1.0, len(ind.keypoints) - 1.0, 4 * len(ind.keypoints) + 1):
        p, rv = pose_at(ind, float(s))
        x = nodes @ rotmat(rv).T + p
        inside = np.all((x >= lo) & (x <= hi), axis=1)
        keep |= inside[tets].any(axis=1)
    if not keep.any():
        raise ValueError(f"indenter {ind.name!r}: never comes near the gel; nothing to export")
    return tets[keep]


def step_increments(scenario: Scenario, max_increment_mm: float | None = None) -> list[int]:
    """Increments per keypoint step as tools.fe's solver takes them (max_increment_mm/_rad), or with
    translations of at most `max_increment_mm` when given."""
    from .indenters import pose_at

    sv = scenario.solver
    inc_mm = sv.max_increment_mm if max_increment_mm is None else float(max_increment_mm)
    out = []
    for j in range(scenario.n_keypoints):
        n = sv.min_increments
        for ind in scenario.indenters:
            (p0, r0), (p1, r1) = pose_at(ind, j - 1.0), pose_at(ind, float(j))
            n = max(n, math.ceil(np.linalg.norm(p1 - p0) / inc_mm - 1e-9),
                    math.ceil(np.linalg.norm(r1 - r0) / sv.max_increment_rad - 1e-9))
        out.append(max(n, 1))
    return out


def export_inp_ccx(scenario: Scenario, path, mesh=None, bulk: str = "solver",
                   max_increment_mm: float | None = None) -> Path:
    """CalculiX 2.20 deck (see the module docstring); returns its path. `max_increment_mm` caps the
    deck's increments (mm of indenter travel) below the scenario's (C3D10_MAX_INCREMENT_MM)."""
    from .materials import effective_bulk
    from .solver import build_mesh

    if bulk not in BULK_CHOICES:
        raise ValueError(f"bulk {bulk!r}: expected one of {BULK_CHOICES}")
    if max_increment_mm is not None and not max_increment_mm > 0:
        raise ValueError(f"max_increment_mm: expected > 0, got {max_increment_mm!r}")
    scenario.validate()
    gm = mesh if mesh is not None else build_mesh(scenario)
    order = 2 if gm.tets.shape[1] == 10 else 1
    m, sv = scenario.material, scenario.solver
    K = effective_bulk(m, order, sv.max_bulk_ratio) if bulk == "solver" else m.bulk_modulus
    penalty = sv.penalty_scale * m.shear_modulus / scenario.mesh.size_top  # N/mm^3, as GelModel.penalty
    out = [(f"*HEADING\nTensorTouch FE scenario {scenario.name} hash {scenario.hash()} (units mm, N, MPa); "
            f"dialect ccx, bulk {bulk} K = {K:.6g} MPa"),
           "*NODE, NSET=NALL"]
    out += _gel_lines(gm, "C3D10" if order == 2 else "C3D4", gm.tets)
    out += ["*MATERIAL, NAME=GEL", *_material_lines(m, 2.0 / K), "*SOLID SECTION, ELSET=GEL, MATERIAL=GEL"]
    # rigid indenters: thin tets under the surface, one rigid body each (material needed, stiffness unused)
    out += ["*MATERIAL, NAME=RIGID", "*ELASTIC", "1000., 0.3"]
    n0 = len(gm.nodes) + 1
    e0 = len(gm.tets) + 1
    refs = []
    lo, hi = gm.nodes.min(axis=0) - RIGID_MARGIN, gm.nodes.max(axis=0) + RIGID_MARGIN
    for k, ind in enumerate(scenario.indenters):
        nodes, tets = rigid_tets(indenter_surface(ind, scenario.resolve))
        tets = _near_gel(ind, nodes, tets, lo, hi)
        used = np.unique(tets)
        renum = np.full(len(nodes), -1)
        renum[used] = np.arange(len(used))
        nodes, tets = nodes[used], renum[tets]
        R, p = rotmat(ind.rotation), np.asarray(ind.position, float)
        v = nodes @ R.T + p
        name = f"IND{k + 1}"
        out.append(f"*NODE, NSET={name}_NODES")
        out += [f"{n0 + i}, {x:.6f}, {y:.6f}, {z:.6f}" for i, (x, y, z) in enumerate(v)]
        ref, rot = n0 + len(v), n0 + len(v) + 1
        out += [f"*NODE, NSET={name}_REF", f"{ref}, {p[0]:.6f}, {p[1]:.6f}, {p[2]:.6f}",
                f"*NODE, NSET={name}_ROT", f"{rot}, {p[0]:.6f}, {p[1]:.6f}, {p[2]:.6f}"]
        out.append(f"*ELEMENT, TYPE=C3D4, ELSET={name}_EL")
        out += [f"{e0 + i}, " + ", ".join(str(n0 + j) for j in t) for i, t in enumerate(tets)]
        out += [f"*SOLID SECTION, ELSET={name}_EL, MATERIAL=RIGID",
                f"*RIGID BODY, NSET={name}_NODES, REF NODE={ref}, ROT NODE={rot}",
                f"*SURFACE, TYPE=ELEMENT, NAME={name}_SURF", f"{name}_EL, S1"]
        refs.append((name, ind))
        n0, e0 = rot + 1, e0 + len(tets)
    out += ["*BOUNDARY", "BASE, 1, 3"]
    out += ["*SURFACE INTERACTION, NAME=GEL_CONTACT",
            "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR", f"{penalty:.8g}"]
    if scenario.friction > 0:
        out += ["*FRICTION", f"{scenario.friction:.8g}, {sv.friction_stiffness_ratio * penalty:.8g}"]
    out += [f"*CONTACT PAIR, INTERACTION=GEL_CONTACT, TYPE=NODE TO SURFACE\nGEL_TOP, {name}_SURF"
            for name, _ in refs]
    for j, n_inc in enumerate(step_increments(scenario, max_increment_mm)):
        dt = 1.0 / n_inc
        out += [f"*STEP, NLGEOM, INC=1000\n** keypoint {j + 1}", "*STATIC",
                f"{dt:.8g}, 1., {CCX_MIN_INCREMENT * dt:.3g}, {dt:.8g}", "*BOUNDARY"]
        for name, ind in refs:
            kp = ind.keypoints[j]
            for dof, val in enumerate(kp.translation, 1):
                out.append(f"{name}_REF, {dof}, {dof}, {val:.10g}")
            for dof, val in enumerate(kp.rotation, 1):
                out.append(f"{name}_ROT, {dof}, {dof}, {val:.10g}")
        for name, _ in refs:   # reaction force at the reference node, reaction moment at the rotation node
            out += [f"*NODE PRINT, NSET={name}_REF", "RF", f"*NODE PRINT, NSET={name}_ROT", "RF"]
        out += ["*NODE FILE\nU, RF", "*EL FILE\nS", "*CONTACT FILE\nCDIS, CSTR", "*END STEP"]
    return _write(path, out)


def _export_abaqus(scenario: Scenario, path, mesh=None) -> Path:
    """The Abaqus-keyword deck (parts, instance GEL-1, C3D4H, R3D3 rigid surfaces)."""
    from .solver import build_mesh

    scenario.validate()
    gm = mesh if mesh is not None else build_mesh(scenario)
    out = [f"*HEADING\nTensorTouch FE scenario {scenario.name} hash {scenario.hash()} (units mm, N, MPa)",
           "*PART, NAME=GEL", "*NODE"]
    out += _gel_lines(gm, "C3D4H", gm.corner_tets)
    out += ["*SOLID SECTION, ELSET=GEL, MATERIAL=GEL", "*END PART"]
    m = scenario.material
    out.append("*MATERIAL, NAME=GEL\n*DENSITY\n1.07e-09")
    if m.model == "yeoh":
        out.append(f"*HYPERELASTIC, YEOH\n{m.C10}, {m.C20}, {m.C30}, {m.D1}, 0., 0.")
    elif m.model == "neo_hookean":
        out.append(f"*HYPERELASTIC, NEO HOOKE\n{m.C10}, {m.D1}")
    else:
        out.append(f"*HYPERELASTIC, MOONEY-RIVLIN\n{m.C10}, {m.C01}, {m.D1}")
    out += ["*ASSEMBLY, NAME=ASSEMBLY", "*INSTANCE, NAME=GEL-1, PART=GEL", "*END INSTANCE"]
    n0 = len(gm.nodes) + 1000
    refs = []
    for k, ind in enumerate(scenario.indenters):
        tri = indenter_surface(ind, scenario.resolve)
        R, p = rotmat(ind.rotation), np.asarray(ind.position, float)
        v = tri.vertices @ R.T + p
        name = f"IND{k + 1}"
        out += [f"*NODE, NSET={name}_NODES"]
        out += [f"{n0 + i}, {x:.6f}, {y:.6f}, {z:.6f}" for i, (x, y, z) in enumerate(v)]
        ref = n0 + len(v)
        out += [f"*NODE, NSET={name}_REF", f"{ref}, {p[0]:.6f}, {p[1]:.6f}, {p[2]:.6f}"]
        e0 = 10 ** 7 * (k + 1)
        out += [f"*ELEMENT, TYPE=R3D3, ELSET={name}_EL"]
        out += [f"{e0 + i}, " + ", ".join(str(n0 + j) for j in f) for i, f in enumerate(tri.faces)]
        out += [f"*RIGID BODY, REF NODE={ref}, ELSET={name}_EL",
                f"*SURFACE, TYPE=ELEMENT, NAME={name}_SURF", f"{name}_EL, SPOS"]
        refs.append((name, ref, ind))
        n0 = ref + 1000
    out.append("*END ASSEMBLY")
    out += ["*SURFACE INTERACTION, NAME=GEL_CONTACT", f"*FRICTION\n{scenario.friction}",
            "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=HARD"]
    out += [f"*CONTACT PAIR, INTERACTION=GEL_CONTACT\nGEL-1.GEL_TOP, {name}_SURF" for name, _, _ in refs]
    out += ["*BOUNDARY", "GEL-1.BASE, ENCASTRE"]
    for j in range(scenario.n_keypoints):
        out += [f"*STEP, NAME=KEYPOINT_{j + 1}, NLGEOM=YES, INC=1000", "*STATIC", "0.05, 1., 1e-08, 0.25",
                "*BOUNDARY"]
        for name, ref, ind in refs:
            kp = ind.keypoints[j]
            for dof, val in enumerate(list(kp.translation) + list(kp.rotation), 1):
                out.append(f"{name}_REF, {dof}, {dof}, {val}")
        out += ["*OUTPUT, FIELD\n*NODE OUTPUT\nU, RF\n*ELEMENT OUTPUT\nS",
                "*CONTACT OUTPUT\nCNORMF, CSHEAR, CNAREA, CSTATUS", "*END STEP"]
    return _write(path, out)
