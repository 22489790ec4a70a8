"""Export a scenario as an Abaqus-style `.inp` deck (for cross-checks with Abaqus or CalculiX).

Gel: our gmsh mesh as C3D4H (hybrid linear tets), base encastre, Yeoh/NH/MR hyperelastic with the
scenario's D1 (the true material, no bulk cap). Indenters: discrete rigid surfaces (R3D3) tessellated
from the analytic shapes or read from the mesh file, each with a reference node at its tip; one
*STEP per keypoint moving the reference nodes (U = translation, UR = rotation vector, both relative
to the initial pose, as in the seed). Hard contact with Coulomb friction mu; field output U, S, RF,
CNORMF, CSHEAR, CNAREA. Coordinates in mm, forces in N, stresses in MPa.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from tools.fe.indenters import rotmat
from tools.fe.scenario import Indenter, Scenario

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


def export_inp(scenario: Scenario, path, mesh=None) -> Path:
    """Write the deck (atomic) and return its path."""
    from tools.fe.solver import build_mesh

    scenario.validate()
    gm = mesh if mesh is not None else build_mesh(scenario)
    out = [f"*HEADING\nTensorTouch FE scenario {scenario.name} hash {scenario.hash()} (units mm, N, MPa)",
           "*PART, NAME=GEL", "*NODE"]
    out += [f"{i + 1}, {x:.6f}, {y:.6f}, {z:.6f}" for i, (x, y, z) in enumerate(gm.nodes)]
    out.append("*ELEMENT, TYPE=C3D4H, ELSET=GEL")
    out += [f"{e + 1}, " + ", ".join(str(n + 1) for n in t) for e, t in enumerate(gm.corner_tets)]
    out += ["*NSET, NSET=BASE", _lines(gm.fixed_nodes + 1)]
    # free-surface faces as element-face sets S1..S4
    surf = {tuple(sorted(t)) for t in gm.surface_tris.tolist()}
    faces = {k: [] for k in range(4)}
    for e, t in enumerate(gm.corner_tets):
        for k, ids in enumerate(_FACE_IDS):
            if tuple(sorted(t[list(ids)])) in surf:
                faces[k].append(e + 1)
    for k, els in faces.items():
        if els:
            out += [f"*ELSET, ELSET=TOP_S{k + 1}", _lines(els)]
    out.append("*SURFACE, TYPE=ELEMENT, NAME=GEL_TOP")
    out += [f"TOP_S{k + 1}, S{k + 1}" for k, els in faces.items() if els]
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
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name("." + path.name + ".tmp")
    tmp.write_text("\n".join(out) + "\n")
    tmp.replace(path)
    return path
