"""The MuJoCo world of a selective-grasp trial: the hand from its URDF, two objects between thumb
and index, an external pull on one of them.

- Hand: the (mounted) URDF compiled by MuJoCo; collision boxes of the links, fingertip spheres of
  radius `tip_collision_radius_mm` (the gel's rigid core: the gel in front of it compresses, see
  touch.py); only the fingertips collide with the objects; position actuators on all joints.
- Cables (A 2.18 mm, B 3.01 mm): taut strings, i.e. capsules of the cable's diameter on three slide
  joints whose springs are the string tension's lateral stiffness 2T/l (held at both ends 35 mm
  away). 1D `flexcomp` rods with <elasticity> (MuJoCo 4 has no cable plugin or <composite>) were
  tried: stable only with heavy vertices, and the rods slipped out between the convex fingertips.
- Rigid objects (8 mm pens): capsules on three slide joints with stiffer springs (held in a hand).
- Gravity is off: the cables are pinned, and only the pinch and the pull act. The hand's palm is
  fixed, or with `SceneConfig.arm` carried by an arm: a kinematic (mocap) palm that follows the
  commanded translation exactly, as a position-controlled arm much stiffer than the fingers would.
This module is the *world*: the trial runner and the simulated fingertip sensors read it; the
controller never does (it sees only the sensors' published contacts and the contact graph).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .task import CONTACT_SOLREF_S

OBJECTS = {   # diameter mm, kind
    "A": {"diameter_mm": 2.18, "kind": "cable"},
    "B": {"diameter_mm": 3.01, "kind": "cable"},
    "pen": {"diameter_mm": 8.0, "kind": "rigid"},
}
PAIRS = {"A+A": ("A", "A"), "A+B": ("A", "B"), "cable+rigid": ("A", "pen"), "rigid+rigid": ("pen", "pen")}


@dataclass(frozen=True)
class SceneConfig:
    timestep: float = 0.0005
    tip_collision_radius_mm: float = 11.0
    cable_length_mm: float = 70.0
    cable_tension_n: float = 3.0        # a string held taut at both ends
    cable_damping: float = 1.0
    pen_length_mm: float = 60.0
    pen_stiffness: float = 300.0        # N/m per slide axis
    pen_damping: float = 3.0
    kp: float = 3.0                     # N·m/rad position gain
    joint_damping: float = 0.08
    friction: float = 1.0
    contact: str = "soft"               # "soft": MuJoCo's default solref (20 ms); "stiff": 2 ms (tools.grasp.task)
    gap_mm: float = 5.0                 # free space between the two objects' surfaces
    arm: bool = False                   # the palm on an arm that translates it (`Scene.set_arm`, `command_arm`)


@dataclass
class SceneObject:
    name: str
    kind: str
    radius_m: float
    centre: np.ndarray                  # (3,) initial axis centre, world
    axis: np.ndarray                    # (3,) unit long axis, world
    body_ids: list = field(default_factory=list)    # the object's body
    geom_id: int = -1


def placement(r1: float, r2: float, R: float, gap: float) -> tuple[float, float]:
    """Offsets x1 < x2 (m) across the pinch at which two fingertip spheres of radius R, closed
    symmetrically, touch both objects (radii r1, r2) at once: the gap between the spheres at offset x
    is D − 2√(R² − x²), so √(R² − x_a²) − √(R² − x_b²) = r_b − r_a with the thicker object farther
    out. The objects' surfaces stay at least `gap` apart."""
    from scipy.optimize import brentq

    thin, thick = (r1, r2) if r1 <= r2 else (r2, r1)
    sep = thin + thick + gap

    def mismatch(c, sep):
        a, b = c - sep / 2, c + sep / 2
        return np.sqrt(R * R - a * a) - np.sqrt(R * R - b * b) - (thick - thin)

    while sep / 2 < 0.95 * R:
        hi = R - sep / 2 - 1e-9
        if mismatch(0.0, sep) <= 0 <= mismatch(hi, sep):
            c = brentq(mismatch, 0.0, hi, args=(sep,)) if thick > thin else 0.0
            xs = (c - sep / 2, c + sep / 2)
            return xs if r1 <= r2 else (xs[1], xs[0])
        sep += 0.0005
    raise ValueError(f"objects of radius {r1 * 1e3:.2f} and {r2 * 1e3:.2f} mm do not fit one pinch of "
                     f"{R * 1e3:.1f} mm fingertips")


def _hand_xml(urdf_text: str, cfg: SceneConfig) -> str:
    import mujoco

    tag = "<robot name="
    i = urdf_text.index(tag)
    j = urdf_text.index(">", i)
    compiler = ('<mujoco><compiler strippath="true" discardvisual="true" fusestatic="false" '
                'balanceinertia="true"/></mujoco>')
    spec = mujoco.MjSpec.from_string(urdf_text[:j + 1] + compiler + urdf_text[j + 1:])
    return spec, mujoco


class Scene:
    """Build with `Scene(urdf_path, q_start, point, normal, long_dir, pair, ...)`."""

    TIP_BODIES = ("link_15.0_tip", "link_3.0_tip")   # thumb, index

    def __init__(self, urdf: str, hand_joints: list[str], pair: tuple[str, str], point: np.ndarray,
                 normal: np.ndarray, across: np.ndarray, cfg: SceneConfig | None = None,
                 jitter_m: np.ndarray | None = None, diameters_mm: tuple[float, float] | None = None,
                 yaw_deg: float = 0.0):
        """`diameters_mm` overrides the pair's diameters; `yaw_deg` turns the objects' layout about
        the pinch normal (through `point`)."""
        import mujoco

        self.cfg = cfg = cfg or SceneConfig()
        with open(urdf) as fh:
            spec, _ = _hand_xml(fh.read(), cfg)
        spec.option.timestep = cfg.timestep
        spec.option.gravity = [0.0, 0.0, 0.0]
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
        for g in spec.geoms:
            g.contype, g.conaffinity = 0, 0
        for body in spec.bodies:
            if body.name in self.TIP_BODIES:
                for g in body.geoms:
                    g.size = [cfg.tip_collision_radius_mm / 1000.0, 0, 0]
                    g.contype, g.conaffinity = 2, 2
                    g.friction = [cfg.friction, 0.005, 0.0001]
                    if cfg.contact != "soft":
                        g.solref = [CONTACT_SOLREF_S[cfg.contact], 1.0]
                    g.name = "tip_" + ("thumb" if body.name == self.TIP_BODIES[0] else "index")
                    g.rgba = [0.95, 0.75, 0.2, 1.0]
        if cfg.arm:
            palm = spec.worldbody.first_body()
            if len(palm.joints):
                raise ValueError(f"the hand's root body {palm.name!r} has joints; an arm needs a fixed palm")
            palm.mocap = True
        for j in spec.joints:
            j.damping = [cfg.joint_damping, 0.0, 0.0]
            j.armature = 0.001
            j.frictionloss = 0.0
            act = spec.add_actuator()
            act.name = j.name
            act.target = j.name
            act.trntype = mujoco.mjtTrn.mjTRN_JOINT
            act.set_to_position(kp=cfg.kp)
        xml = spec.to_xml().replace('<compiler angle="radian"/>', '<compiler angle="radian" balanceinertia="true"/>', 1)
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        v = np.asarray(across, float) - (np.asarray(across, float) @ n) * n
        v /= np.linalg.norm(v)
        if yaw_deg:
            a = np.radians(yaw_deg)
            v = np.cos(a) * v + np.sin(a) * np.cross(n, v)
        e = np.cross(n, v)
        self.across, self.normal = v, n
        diam = diameters_mm or tuple(OBJECTS[k]["diameter_mm"] for k in pair)
        radii = [d / 2000.0 for d in diam]
        offsets = placement(radii[0], radii[1], cfg.tip_collision_radius_mm / 1000.0, cfg.gap_mm / 1000.0)
        jitter = np.zeros(3) if jitter_m is None else np.asarray(jitter_m, float)
        centres = [point + jitter + offsets[0] * v, point + jitter + offsets[1] * v]
        self.objects = [SceneObject(f"obj{k}", OBJECTS[name]["kind"], r, c, e)
                        for k, (name, r, c) in enumerate(zip(pair, radii, centres))]
        parts = [self._object_xml(o) for o in self.objects]
        xml = xml.replace("</worldbody>", "".join(parts) + "</worldbody>", 1)
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        self.mj = mujoco
        m = self.model
        self.tip_geoms = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "tip_thumb"),
                          mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "tip_index")]
        self.tip_bodies = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in self.TIP_BODIES]
        self.qadr = np.array([m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)] for j in hand_joints])
        self.act = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, j) for j in hand_joints])
        for o in self.objects:
            o.geom_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, o.name)
            o.body_ids = [int(m.geom_bodyid[o.geom_id])]
        self._scratch = mujoco.MjData(m)    # for `opened`: kinematics without touching the simulation
        self._palm_home = self.data.mocap_pos[0].copy() if cfg.arm else None
        self._arm_to = np.zeros(3)

    # ------------------------------------------------------------------ building
    def _object_xml(self, o: SceneObject) -> str:
        cfg = self.cfg
        e = o.axis
        rot_axis = np.cross([1.0, 0.0, 0.0], e)
        s = np.linalg.norm(rot_axis)
        angle = float(np.arctan2(s, e[0]))          # the hand model compiles with angle="radian"
        aa = (rot_axis / s if s > 1e-9 else np.array([0.0, 0.0, 1.0])).tolist() + [angle]
        aa_s = " ".join(f"{x:.6g}" for x in aa)
        if o.kind == "cable":   # a taut string: tension T over half-length l is a lateral spring 2T/l
            L = cfg.cable_length_mm / 1000.0
            k = 2.0 * cfg.cable_tension_n / (0.5 * L)
            damping, mass, rgba = cfg.cable_damping, 0.004, "0.15 0.35 0.85 1"
        else:
            L = cfg.pen_length_mm / 1000.0
            k, damping, mass, rgba = cfg.pen_stiffness, cfg.pen_damping, 0.01, "0.85 0.2 0.2 1"
        half = 0.5 * L - o.radius_m
        ax = " ".join(f"{x:.6g}" for x in o.centre)
        solref = "" if cfg.contact == "soft" else f' solref="{CONTACT_SOLREF_S[cfg.contact]:g} 1"'
        joints = "".join(f'<joint name="{o.name}_s{i}" type="slide" axis="{a}" stiffness="{k:.6g}" '
                         f'damping="{damping}"/>' for i, a in enumerate(("1 0 0", "0 1 0", "0 0 1")))
        return (f'<body name="{o.name}" pos="{ax}" axisangle="{aa_s}">{joints}'
                f'<geom name="{o.name}" type="capsule" fromto="{-half:.6g} 0 0 {half:.6g} 0 0" '
                f'size="{o.radius_m:.6g}" mass="{mass}" rgba="{rgba}" contype="2" conaffinity="2" '
                f'friction="{cfg.friction} 0.005 0.0001"{solref}/></body>')

    # ------------------------------------------------------------------ running
    def set_hand(self, q: np.ndarray) -> None:
        """Place the hand's pinch joints at q (and hold them there)."""
        self.data.qpos[self.qadr] = q
        self.data.ctrl[self.act] = q
        self.mj.mj_forward(self.model, self.data)

    def opened(self, q: np.ndarray, normal: np.ndarray, mm: float) -> np.ndarray:
        """Joint angles near q with the thumb tip moved `mm` along +normal and the index tip along
        −normal (least squares on the positional Jacobians), for approaching the objects; a negative
        `mm` closes past q. Computed on a scratch copy: the simulation's state is not touched."""
        m, d = self.model, self._scratch
        d.mocap_pos[:] = self.data.mocap_pos
        q = np.asarray(q, float).copy()
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        cols = [int(np.flatnonzero(m.jnt_qposadr == a)[0]) for a in self.qadr]
        cols = [int(m.jnt_dofadr[j]) for j in cols]
        for _ in range(5):
            d.qpos[self.qadr] = q
            self.mj.mj_kinematics(m, d)
            self.mj.mj_comPos(m, d)
            J = []
            for b in self.tip_bodies:
                jp = np.zeros((3, m.nv))
                self.mj.mj_jacBody(m, d, jp, None, b)
                J.append(jp[:, cols])
            J = np.concatenate(J)
            dx = np.concatenate([n, -n]) * (mm / 1000.0 / 5)
            q = q + np.linalg.lstsq(J, dx, rcond=None)[0]
        lo, hi = m.jnt_range[[int(np.flatnonzero(m.jnt_qposadr == a)[0]) for a in self.qadr]].T
        return np.clip(q, lo, hi)

    def command(self, q: np.ndarray) -> None:
        self.data.ctrl[self.act] = q

    def arm(self) -> np.ndarray:
        """The arm's translation of the palm from its home (world, m); zeros without an arm."""
        return np.zeros(3) if self._palm_home is None else self.data.mocap_pos[0] - self._palm_home

    def set_arm(self, t: np.ndarray) -> None:
        """Place the palm at translation t (m) from its home at once (before the trial starts)."""
        if self._palm_home is None:
            raise ValueError("this scene has no arm (SceneConfig.arm)")
        self._arm_to = np.asarray(t, float).copy()
        self.data.mocap_pos[0] = self._palm_home + self._arm_to
        self.mj.mj_forward(self.model, self.data)

    def command_arm(self, t: np.ndarray) -> None:
        """Move the palm to translation t (m), evenly over the next `step`."""
        if self._palm_home is None:
            raise ValueError("this scene has no arm (SceneConfig.arm)")
        self._arm_to = np.asarray(t, float).copy()

    def step(self, seconds: float) -> None:
        n = max(1, round(seconds / self.cfg.timestep))
        a0 = self.arm() if self._palm_home is not None else None
        for k in range(n):
            if a0 is not None:
                self.data.mocap_pos[0] = self._palm_home + a0 + (k + 1) / n * (self._arm_to - a0)
            self.mj.mj_step(self.model, self.data)

    def pull(self, k: int, force_n: float, direction: np.ndarray | None = None) -> None:
        """External force on object k's body, along its axis or along the unit `direction` (world)."""
        self.data.xfrc_applied[:] = 0.0
        o = self.objects[k]
        self.data.xfrc_applied[o.body_ids[0], :3] = force_n * (o.axis if direction is None else np.asarray(direction, float))

    def snapshot(self) -> dict:
        """Positions for drawing: fingertip centres and object axes (world, m)."""
        return {"tips": [self.tip_pose(i)[:3, 3].copy() for i in range(2)],
                "objects": [self.object_axis(k) for k in range(len(self.objects))],
                "radii": [o.radius_m for o in self.objects],
                "tip_radius": self.cfg.tip_collision_radius_mm / 1000.0}

    def release(self) -> None:
        self.data.xfrc_applied[:] = 0.0

    def tip_pose(self, i: int) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[self.tip_bodies[i]].reshape(3, 3)
        T[:3, 3] = self.data.xpos[self.tip_bodies[i]]
        return T

    def object_axis(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Current axis (centre, unit direction) of object k, world (m)."""
        o = self.objects[k]
        b = o.body_ids[0]
        R = self.data.xmat[b].reshape(3, 3)
        return self.data.xpos[b].copy(), R[:, 0].copy()

    def contact_forces(self) -> np.ndarray:
        """(2 tips, 2 objects, 3) world force each object applies to each fingertip (N)."""
        out = np.zeros((2, 2, 3))
        f6 = np.zeros(6)
        for c in range(self.data.ncon):
            con = self.data.contact[c]
            tip = [i for i, g in enumerate(self.tip_geoms) if g in (con.geom[0], con.geom[1])]
            if not tip:
                continue
            obj = self._object_of(con)
            if obj is None:
                continue
            self.mj.mj_contactForce(self.model, self.data, c, f6)
            frame = con.frame.reshape(3, 3)
            f_world = frame.T @ f6[:3]
            # contact normal points from geom/flex 1 to 2; force on the tip is minus the force on body 1
            tip_first = con.geom[0] == self.tip_geoms[tip[0]]
            out[tip[0], obj] += -f_world if tip_first else f_world
        return out

    def _object_of(self, con) -> int | None:
        for k, o in enumerate(self.objects):
            if o.geom_id in (con.geom[0], con.geom[1]):
                return k
        return None

    def touching(self) -> np.ndarray:
        """(2 tips, 2 objects) bool: simulator truth of which fingertip touches which object."""
        f = self.contact_forces()
        return np.linalg.norm(f, axis=2) > 1e-3
