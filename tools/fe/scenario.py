"""FE scenario contract: gel geometry + material + mesh + indenters with keypoint moves + solver.

A scenario is the seed's "configuration file" (§III.C/E): JSON or TOML, units mm, N, MPa, rad.

Frames. Gel frame: base plane z = 0 (fixed, encastre), gel above it, dome axis = +z through the
origin. Indenter frame: origin = reference point = the indenter's tip; the body lies in local
z >= 0 so that the identity rotation presses *down* (-z) onto the gel top. A pose is a position
(mm, of the reference point in the gel frame) and a rotation vector (rad, local -> gel frame).

Keypoints. Each indenter has the same number of keypoints; keypoint j gives the translation (mm)
and rotation vector (rad) *relative to the initial pose*, rotation about the reference point in
the gel frame:  R_j = Rot(rotation_j) @ R_0,  p_j = p_0 + translation_j.  The solver moves every
indenter from keypoint j-1 to j (frame j of the result); keypoint 0 is reached from the initial
pose. The initial pose must not penetrate the gel.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ...contracts.files import atomic_write_text
from .errors import ScenarioError

log = logging.getLogger(__name__)

SCHEMA = "tensortouch.fe_scenario"
SCHEMA_VERSION = 1
GEOMETRY_KINDS = ("dome", "flattened_dome", "flat_pad", "stl")
MATERIAL_MODELS = ("yeoh", "neo_hookean", "mooney_rivlin")
INDENTER_SHAPES = {  # shape -> required params (mm)
    "sphere": ("radius",),
    "cylinder": ("radius", "length"),          # axis along local x, lowest line at local z = 0
    "box_edge": ("length", "width"),           # square prism, one edge along local x pointing down
    "flat": ("radius", "fillet"),              # flat circular punch, face at z = 0, rounded rim
    "torus": ("major_radius", "minor_radius"),  # ring in the local xy plane, lowest at z = 0
    "mesh": (),                                # closed triangle mesh (STL/OBJ/PLY), tip at origin
}
DEFAULT_FRICTION = 2.2  # seed §III.E, from lee2023influence


@dataclass
class GelGeometry:
    """Gel body. dome: hemisphere of `radius`; flattened_dome: spherical cap of base radius
    `radius` and cap height `cap_height` on a vertical skirt of height `skirt`; flat_pad: box
    size_x * size_y * thickness centred on the axis; stl: closed surface from `stl_path` (mm,
    base on z = 0)."""

    kind: str = "flattened_dome"
    radius: float = 12.0
    cap_height: float = 6.0
    skirt: float = 2.0
    size_x: float = 40.0
    size_y: float = 40.0
    thickness: float = 20.0
    stl_path: str = ""

    @property
    def top_z(self) -> float:
        """Height of the highest gel point above the base (mm); stl: unknown until meshed (nan)."""
        if self.kind == "dome":
            return self.skirt + self.radius
        if self.kind == "flattened_dome":
            return self.skirt + self.cap_height
        if self.kind == "flat_pad":
            return self.thickness
        return math.nan


@dataclass
class Material:
    """Hyperelastic gel. Yeoh: W = sum_i Ci0 (I1bar-3)^i + (J-1)^2/D1 (Abaqus form);
    neo_hookean uses C10 only; mooney_rivlin uses C10 and C01. Units MPa, D1 in 1/MPa.
    Defaults: a soft silicone (initial shear modulus 2*C10 = 0.06 MPa), D1 so that
    bulk/shear = 50 (see docs/fe.md, volumetric locking)."""

    model: str = "yeoh"
    C10: float = 0.03
    C20: float = 0.002
    C30: float = 0.0002
    C01: float = 0.0
    D1: float = 2.0 / (50 * 0.06)

    @property
    def shear_modulus(self) -> float:
        """Initial shear modulus mu0 (MPa)."""
        return 2.0 * (self.C10 + (self.C01 if self.model == "mooney_rivlin" else 0.0))

    @property
    def bulk_modulus(self) -> float:
        """Bulk modulus K = 2/D1 (MPa)."""
        return 2.0 / self.D1


@dataclass
class MeshSettings:
    """gmsh sizes (mm): `size_top` within `refine_depth` of the top surface, growing to
    `size_inside` in the core; `order` 1 = linear tets (fast, default), 2 = quadratic tets.
    refine_radius > 0 refines only a ball of that radius around the top centre (verification
    meshes of large pads); 0 = the whole free surface."""

    size_top: float = 0.7
    size_inside: float = 2.0
    refine_depth: float = 1.5
    order: int = 1
    refine_radius: float = 0.0


@dataclass
class Keypoint:
    """Pose of an indenter relative to its initial pose (see module doc)."""

    translation: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    rotation: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])


@dataclass
class Indenter:
    """A rigid indenter: analytic `shape` with `params` (mm) or a triangle mesh at `mesh_path`
    (a path relative to the scenario file is resolved against its folder), initial pose, keypoints."""

    name: str = "indenter"
    shape: str = "sphere"
    params: dict[str, float] = field(default_factory=lambda: {"radius": 5.0})
    mesh_path: str = ""
    position: list[float] = field(default_factory=lambda: [0.0, 0.0, 8.0])
    rotation: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    keypoints: list[Keypoint] = field(default_factory=list)


@dataclass
class SolverSettings:
    """Newton-Raphson with increments, cutback and penalty contact (units in field names).
    penalty_scale: contact stiffness per unit area = penalty_scale * mu0 / size_top (N/mm^3).
    friction_stiffness_ratio: tangential (stick) penalty / normal penalty (elastic slip allowance).
    max_bulk_ratio: with linear tets the bulk modulus is capped at max_bulk_ratio * mu0 (locking
    compensation, measured against CalculiX C3D10 in docs/fe.md); 0 disables the cap.
    Quadratic u/p/J tets (mesh.order = 2) always use the material's D1."""

    max_increment_mm: float = 0.5
    max_increment_rad: float = 0.05
    min_increments: int = 1
    max_iterations: int = 25
    max_cutbacks: int = 5
    tol_force: float = 1e-4
    tol_rel: float = 1e-6
    penalty_scale: float = 100.0
    friction_stiffness_ratio: float = 0.1
    max_bulk_ratio: float = 5.0
    threads: int = 2


@dataclass
class Scenario:
    """A complete FE scenario (the file contract of DESIGN.md §3)."""

    gel: GelGeometry = field(default_factory=GelGeometry)
    material: Material = field(default_factory=Material)
    mesh: MeshSettings = field(default_factory=MeshSettings)
    indenters: list[Indenter] = field(default_factory=list)
    friction: float = DEFAULT_FRICTION
    solver: SolverSettings = field(default_factory=SolverSettings)
    name: str = "scenario"
    base_dir: str = ""  # folder used to resolve relative paths (not part of the hash)

    @property
    def n_keypoints(self) -> int:
        return len(self.indenters[0].keypoints) if self.indenters else 0

    def to_dict(self) -> dict:
        data = asdict(self)
        data.pop("base_dir", None)
        return {"schema": SCHEMA, "schema_version": SCHEMA_VERSION, **data}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    def hash(self) -> str:
        """sha256 (16 hex) of the canonical JSON plus referenced mesh file contents: the cache key."""
        h = hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode())
        for path in self.referenced_files():
            h.update(path.read_bytes() if path.is_file() else b"missing:" + str(path).encode())
        return h.hexdigest()[:16]

    def resolve(self, path: str) -> Path:
        p = Path(path).expanduser()
        return p if p.is_absolute() or not self.base_dir else Path(self.base_dir) / p

    def referenced_files(self) -> list[Path]:
        files = [self.resolve(i.mesh_path) for i in self.indenters if i.shape == "mesh"]
        if self.gel.kind == "stl":
            files.append(self.resolve(self.gel.stl_path))
        return files

    def validate(self) -> "Scenario":
        """Raise ScenarioError naming the first invalid field; return self when valid."""
        _validate(self)
        return self


def _num(where: str, value, positive=True, allow_zero=False) -> None:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise ScenarioError(f"{where}: expected a finite number, got {value!r}")
    if positive and (value < 0 or (value == 0 and not allow_zero)):
        raise ScenarioError(f"{where}: expected a {'non-negative' if allow_zero else 'positive'} "
                            f"number, got {value!r}")


def _vec3(where: str, value) -> None:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ScenarioError(f"{where}: expected 3 numbers, got {value!r}")
    for i, v in enumerate(value):
        _num(f"{where}[{i}]", v, positive=False)


def _validate(s: Scenario) -> None:
    g, m = s.gel, s.material
    if g.kind not in GEOMETRY_KINDS:
        raise ScenarioError(f"gel.kind: expected one of {GEOMETRY_KINDS}, got {g.kind!r}")
    for name in ("radius", "cap_height", "size_x", "size_y", "thickness"):
        _num(f"gel.{name}", getattr(g, name))
    _num("gel.skirt", g.skirt, allow_zero=True)
    if g.kind == "flattened_dome" and g.cap_height > g.radius:
        raise ScenarioError(f"gel.cap_height: expected <= gel.radius ({g.radius}) for a flattened "
                            f"dome, got {g.cap_height}")
    if g.kind == "stl" and not s.resolve(g.stl_path).is_file():
        raise ScenarioError(f"gel.stl_path: file not found: {s.resolve(g.stl_path)}")
    if m.model not in MATERIAL_MODELS:
        raise ScenarioError(f"material.model: expected one of {MATERIAL_MODELS}, got {m.model!r}")
    for name in ("C10", "C20", "C30", "C01", "D1"):
        _num(f"material.{name}", getattr(m, name), positive=False)
    if m.D1 <= 0:
        raise ScenarioError(f"material.D1: expected > 0 (1/MPa; bulk modulus = 2/D1), got {m.D1}")
    if m.shear_modulus <= 0 or m.C10 <= 0:
        raise ScenarioError(f"material.C10: expected > 0 MPa with 2*(C10+C01) > 0, got C10={m.C10}, "
                            f"C01={m.C01}")
    if m.model == "yeoh" and m.C30 < 0:
        raise ScenarioError(f"material.C30: expected >= 0 for a Yeoh gel (stable at large strain), "
                            f"got {m.C30}")
    _num("mesh.size_top", s.mesh.size_top)
    _num("mesh.size_inside", s.mesh.size_inside)
    _num("mesh.refine_depth", s.mesh.refine_depth, allow_zero=True)
    _num("mesh.refine_radius", s.mesh.refine_radius, allow_zero=True)
    if s.mesh.size_top > s.mesh.size_inside:
        raise ScenarioError(f"mesh.size_top: expected <= mesh.size_inside, got {s.mesh.size_top} > "
                            f"{s.mesh.size_inside}")
    if s.mesh.order not in (1, 2):
        raise ScenarioError(f"mesh.order: expected 1 or 2, got {s.mesh.order!r}")
    _num("friction", s.friction, allow_zero=True)
    if not s.indenters:
        raise ScenarioError("indenters: expected at least one indenter")
    names = [i.name for i in s.indenters]
    if len(set(names)) != len(names):
        raise ScenarioError(f"indenters: names must be unique, got {names}")
    n_kp = len(s.indenters[0].keypoints)
    for k, ind in enumerate(s.indenters):
        where = f"indenters[{k}] ({ind.name})"
        if ind.shape not in INDENTER_SHAPES:
            raise ScenarioError(f"{where}.shape: expected one of {tuple(INDENTER_SHAPES)}, got {ind.shape!r}")
        for p in INDENTER_SHAPES[ind.shape]:
            if p not in ind.params:
                raise ScenarioError(f"{where}.params: missing {p!r} (mm) for shape {ind.shape!r}")
            _num(f"{where}.params.{p}", ind.params[p], allow_zero=(p == "fillet"))
        if ind.shape == "torus" and ind.params["minor_radius"] >= ind.params["major_radius"]:
            raise ScenarioError(f"{where}.params: expected minor_radius < major_radius")
        if ind.shape == "mesh" and not s.resolve(ind.mesh_path).is_file():
            raise ScenarioError(f"{where}.mesh_path: file not found: {s.resolve(ind.mesh_path)}")
        _vec3(f"{where}.position", ind.position)
        _vec3(f"{where}.rotation", ind.rotation)
        if len(ind.keypoints) != n_kp or n_kp == 0:
            raise ScenarioError(f"{where}.keypoints: expected {max(n_kp, 1)}+ keypoints, the same "
                                f"number for every indenter; got {len(ind.keypoints)}")
        for j, kp in enumerate(ind.keypoints):
            _vec3(f"{where}.keypoints[{j}].translation", kp.translation)
            _vec3(f"{where}.keypoints[{j}].rotation", kp.rotation)
    sv = s.solver
    for name in ("max_increment_mm", "max_increment_rad", "tol_force", "tol_rel", "penalty_scale",
                 "friction_stiffness_ratio"):
        _num(f"solver.{name}", getattr(sv, name))
    for name in ("min_increments", "max_iterations", "threads"):
        if not isinstance(getattr(sv, name), int) or getattr(sv, name) < 1:
            raise ScenarioError(f"solver.{name}: expected an integer >= 1, got {getattr(sv, name)!r}")


def _build(cls, data, where: str):
    """Dataclass from a dict, rejecting unknown keys (typos) with a clear message."""
    if not isinstance(data, dict):
        raise ScenarioError(f"{where}: expected a table/object, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ScenarioError(f"{where}: unknown field(s) {unknown}; expected some of {sorted(names)}")
    return cls(**data)


def scenario_from_dict(data: dict, base_dir: str = "", source: str = "scenario") -> Scenario:
    """Build and validate a Scenario from a plain dict (as read from JSON/TOML)."""
    data = dict(data)
    if data.pop("schema", SCHEMA) != SCHEMA:
        raise ScenarioError(f"{source}: schema: expected {SCHEMA!r}")
    version = data.pop("schema_version", SCHEMA_VERSION)
    if version != SCHEMA_VERSION:
        raise ScenarioError(f"{source}: schema_version: expected {SCHEMA_VERSION}, got {version!r}")
    inds = []
    for k, d in enumerate(data.pop("indenters", [])):
        d = dict(d)
        kps = [_build(Keypoint, kp, f"{source}: indenters[{k}].keypoints[{j}]")
               for j, kp in enumerate(d.pop("keypoints", []))]
        inds.append(_build(Indenter, {**d, "keypoints": kps}, f"{source}: indenters[{k}]"))
    parts = {"gel": GelGeometry, "material": Material, "mesh": MeshSettings, "solver": SolverSettings}
    built = {key: _build(cls, data.pop(key, {}), f"{source}: {key}") for key, cls in parts.items()}
    s = _build(Scenario, {**data, **built, "indenters": inds, "base_dir": base_dir}, source)
    return s.validate()


def load_scenario(path) -> Scenario:
    """Read a scenario from .json or .toml; relative mesh paths resolve against its folder."""
    path = Path(path)
    if not path.is_file():
        raise ScenarioError(f"{path}: scenario file not found")
    try:
        text = path.read_text()
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise ScenarioError(f"{path}: cannot parse scenario ({exc})") from exc
    return scenario_from_dict(data, base_dir=str(path.parent.resolve()), source=str(path))


def save_scenario(scenario: Scenario, path) -> Path:
    """Write a scenario as JSON (atomic: temp file + rename)."""
    return atomic_write_text(path, scenario.to_json())


def press_keypoints(depth: float, n: int = 5, slide: tuple[float, float] = (0.0, 0.0)) -> list[Keypoint]:
    """n keypoints: press to `depth` (mm) over the first half, then slide by `slide` (mm, x/y)."""
    n_press = max(1, (n + 1) // 2)
    kps = [Keypoint([0.0, 0.0, -depth * (j + 1) / n_press], [0.0, 0.0, 0.0]) for j in range(n_press)]
    n_slide = n - n_press
    for j in range(n_slide):
        f = (j + 1) / n_slide
        kps.append(Keypoint([slide[0] * f, slide[1] * f, -depth], [0.0, 0.0, 0.0]))
    return kps


def standard_dome(depth: float = 2.0, slide: tuple[float, float] = (1.0, 0.0), n_keypoints: int = 5,
                  radius: float = 5.0, **mesh) -> Scenario:
    """The standard gel (docs/fe.md): flattened dome, base radius 12 mm, cap height 6 mm on a 2 mm
    skirt (8 mm tall), Yeoh soft silicone, mesh 0.7 mm at the top / 2 mm inside, one rigid
    sphere (R `radius` mm) pressed `depth` mm at the apex then slid by `slide` mm, mu = 2.2."""
    gel = GelGeometry()
    ind = Indenter(name="sphere", shape="sphere", params={"radius": float(radius)},
                   position=[0.0, 0.0, gel.top_z + 0.05],
                   keypoints=press_keypoints(depth + 0.05, n_keypoints, slide))
    return Scenario(gel=gel, mesh=MeshSettings(**mesh), indenters=[ind], name="standard_dome").validate()
