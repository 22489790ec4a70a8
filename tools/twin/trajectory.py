"""Human-demonstrator-like indentation plans: pokes, presses, slides and twists with 1-2 indenters.

A plan is a list of `Poke`s on one session clock. Each poke holds, per indenter, the initial pose
(tip just above the rest surface, local +z along the outward surface normal so the indenter
approaches perpendicular, as a person does) and keypoints relative to it in the FE contract
(docs/fe.md: translation mm, rotation vector rad about the tip, gel frame). Between keypoints
the motion follows a minimum-jerk profile s(τ) = 10τ³ - 15τ⁴ + 6τ⁵ of the keypoint-to-keypoint
straight line, which is what the physics interpolation uses too (fields and reactions between
solved keypoints are interpolated linearly in s). Outside pokes an indenter rests at a parking
pose 30 mm above the gel; approach and retreat are straight min-jerk moves along the normal.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from .geometry import GelSurface

log = logging.getLogger(__name__)

# The FE engineer's analytic indenter set (tools/fe INDENTER_SHAPES) with the twin's default sizes.
INDENTER_SET = {
    "sphere5": {"shape": "sphere", "params": {"radius": 5.0}},
    "sphere3": {"shape": "sphere", "params": {"radius": 3.0}},
    "flat4": {"shape": "flat", "params": {"radius": 4.0, "fillet": 1.0}},
    "cylinder3": {"shape": "cylinder", "params": {"radius": 3.0, "length": 10.0}},
    "edge": {"shape": "box_edge", "params": {"length": 10.0, "width": 4.0}},
    "torus": {"shape": "torus", "params": {"major_radius": 4.0, "minor_radius": 1.5}},
}
KINDS = ("poke", "press", "slide", "twist")


@dataclass
class TrajectoryConfig:
    """Ranges of the random demonstrator (mm, s, rad)."""

    kinds: tuple = KINDS
    indenters: tuple = ("sphere5", "sphere3", "flat4", "cylinder3")
    theta_max: float = 0.6           # rad, largest contact angle θ from the axis (geometry.py)
    depth_poke: tuple = (0.4, 1.2)
    depth_press: tuple = (1.0, 2.2)
    slide: tuple = (0.4, 1.2)
    twist: tuple = (0.08, 0.25)
    max_step_mm: float = 0.5         # keypoint spacing along a press/slide
    max_step_rad: float = 0.08
    p_two: float = 0.25              # probability that a poke uses two indenters
    min_separation: float = 9.0      # mm between two simultaneous contacts
    approach_gap: float = 0.05       # mm above the surface at the initial pose
    hover: float = 6.0               # mm above the surface where approach starts
    park_height: float = 30.0
    t_approach: tuple = (0.3, 0.5)
    t_press: tuple = (0.3, 0.8)
    t_hold: tuple = (0.15, 0.5)
    t_move: tuple = (0.4, 0.9)
    t_release: tuple = (0.25, 0.5)
    t_gap: tuple = (0.5, 1.2)
    t_lead: float = 0.8              # s of rest before the first poke (baseline frames)


def with_ranges(cfg: TrajectoryConfig, ranges: dict | None, where: str = "trajectory") -> TrajectoryConfig:
    """`cfg` with fields replaced from `ranges` (e.g. {"kinds": ["slide"], "slide": [0.8, 1.6]}; JSON lists
    become tuples); an unknown field or a wrong shape is an error naming `where`."""
    from dataclasses import fields, replace

    if not ranges:
        return cfg
    known = {f.name: getattr(cfg, f.name) for f in fields(cfg)}
    out = {}
    for k, v in dict(ranges).items():
        if k not in known:
            raise ValueError(f"{where}: unknown trajectory field {k!r} (expected one of {sorted(known)})")
        cur = known[k]
        if isinstance(cur, tuple):
            if not isinstance(v, (list, tuple)) or (k not in ("kinds", "indenters") and len(v) != len(cur)):
                raise ValueError(f"{where}.{k}: expected a list like {list(cur)}, got {v!r}")
            v = tuple(v)
            if k == "kinds" and not set(v) <= set(KINDS):
                raise ValueError(f"{where}.kinds: {list(v)} not all in {list(KINDS)}")
        elif not isinstance(v, (int, float)) or isinstance(v, bool):
            raise ValueError(f"{where}.{k}: expected a number, got {v!r}")
        out[k] = v
    return replace(cfg, **out)


@dataclass
class Poke:
    kind: str
    indenters: list[str]                # names in INDENTER_SET
    slots: list[int]                    # indentation module (session indenter id) of each
    position: np.ndarray                # (K,3) initial tip positions
    rotation: np.ndarray                # (K,3) initial rotation vectors
    translation: np.ndarray             # (K,J,3) keypoint translations relative to initial
    rotvec: np.ndarray                  # (K,J,3) keypoint rotations relative to initial
    times: np.ndarray                   # (J,) keypoint times on the session clock; times[0] = start
    t_approach: float                   # approach starts here (from hover)
    t_retreat_end: float                # back at hover
    depth: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def t_start(self) -> float:
        return float(self.times[0])

    @property
    def t_end(self) -> float:
        return float(self.times[-1])

    def to_dict(self) -> dict:
        return {"kind": self.kind, "indenters": self.indenters, "slots": self.slots, "position": self.position.tolist(),
                "rotation": self.rotation.tolist(), "translation": self.translation.tolist(),
                "rotvec": self.rotvec.tolist(), "times": self.times.tolist(),
                "t_approach": self.t_approach, "t_retreat_end": self.t_retreat_end,
                "depth": self.depth, **self.extra}


def minjerk(tau: np.ndarray) -> np.ndarray:
    tau = np.clip(tau, 0.0, 1.0)
    return tau ** 3 * (10 - 15 * tau + 6 * tau * tau)


def segment_phase(times: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For session times t inside [times[0], times[-1]]: keypoint segment index j and phase s in
    [0,1] so that the motion is kp[j] + s (kp[j+1] - kp[j])."""
    t = np.asarray(t, dtype=np.float64)
    j = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    tau = (t - times[j]) / np.maximum(times[j + 1] - times[j], 1e-12)
    return j, minjerk(tau)


def _align_z(n: np.ndarray) -> np.ndarray:
    """Rotation vector taking local +z onto unit vector n."""
    ez = np.array([0.0, 0.0, 1.0])
    axis = np.cross(ez, n)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.zeros(3)
    return axis / s * np.arctan2(s, float(ez @ n))


def _steps(total: float, step: float) -> int:
    return max(1, int(np.ceil(abs(total) / step - 1e-9)))


def contact_points(rng: np.random.Generator, gel: GelSurface, cfg: TrajectoryConfig, k: int,
                   restart_after: int = 500, max_draws: int = 20000) -> list[np.ndarray]:
    """k rest-surface points, uniform in area over θ ≤ theta_max, pairwise ≥ min_separation apart.

    Points are drawn one after another; a first point near the apex can leave no room for a second
    one (the cap's widest chord through the apex is 2ρ sin(theta_max / 2)), so after `restart_after`
    rejected draws in a row the set is drawn again from its first point. More than `max_draws` draws
    in all, or a separation no two points of the cap can have, is an error naming the fields."""
    rho = gel.profile.radius_mm
    if k > 1 and 2.0 * rho * np.sin(min(cfg.theta_max, np.pi / 2)) < cfg.min_separation:
        raise ValueError(f"trajectory.min_separation {cfg.min_separation:g} mm: no two points with θ ≤ "
                         f"theta_max {cfg.theta_max:g} rad are that far apart on this gel "
                         f"(at most {2.0 * rho * np.sin(cfg.theta_max):.2f} mm)")
    pts: list[np.ndarray] = []
    rejected = 0
    for _ in range(max_draws):
        th = np.arccos(1 - rng.random() * (1 - np.cos(cfg.theta_max)))
        ph = rng.uniform(-np.pi, np.pi)
        p = gel.point_at(th, ph)
        if all(np.linalg.norm(p - q) >= cfg.min_separation for q in pts):
            pts.append(p)
            rejected = 0
            if len(pts) == k:
                return pts
        else:
            rejected += 1
            if rejected >= restart_after:
                pts, rejected = [], 0
    raise ValueError(f"trajectory.min_separation {cfg.min_separation:g} mm: {k} contacts that far apart with "
                     f"θ ≤ theta_max {cfg.theta_max:g} rad not found in {max_draws} draws")


def plan_session(n_pokes: int, seed: int, gel: GelSurface, cfg: TrajectoryConfig | None = None) -> list[Poke]:
    """A deterministic random plan of n_pokes for a given seed."""
    cfg = cfg or TrajectoryConfig()
    rng = np.random.default_rng(seed)
    t = cfg.t_lead
    pokes = []
    U = lambda r: float(rng.uniform(*r))  # noqa: E731
    modules = module_indenters(seed, cfg)
    for _ in range(n_pokes):
        kind = str(rng.choice(cfg.kinds))
        if len(modules) > 1 and rng.random() < cfg.p_two:
            slots = [0, 1]
        else:
            slots = [int(rng.integers(len(modules)))]
        names = [modules[s] for s in slots]
        pts = contact_points(rng, gel, cfg, len(slots))
        depth = U(cfg.depth_press if kind in ("press", "slide", "twist") else cfg.depth_poke)
        n_press = _steps(depth, cfg.max_step_mm)
        K = len(pts)
        normals = gel.normals(np.array(pts))
        start_t = t + U(cfg.t_approach)
        seg_t = [U(cfg.t_press) / n_press] * n_press
        trans = [[np.zeros(3)] for _ in range(K)]
        rots = [[np.zeros(3)] for _ in range(K)]
        for i in range(1, n_press + 1):
            for k in range(K):
                trans[k].append(-normals[k] * depth * i / n_press)
                rots[k].append(np.zeros(3))
        hold = U(cfg.t_hold)
        extra = {}
        # hold: a keypoint repeating the deepest pose (lets viscoelastic effects and hysteresis act)
        seg_t.append(hold)
        for k in range(K):
            trans[k].append(trans[k][-1].copy())
            rots[k].append(rots[k][-1].copy())
        if kind in ("slide", "twist"):
            amount = U(cfg.slide if kind == "slide" else cfg.twist) * rng.choice([-1.0, 1.0])
            n_mv = _steps(amount, cfg.max_step_mm if kind == "slide" else cfg.max_step_rad)
            dirs = []
            for k in range(K):
                a = rng.uniform(0, 2 * np.pi)
                tang = np.cross(normals[k], [np.cos(a), np.sin(a), 0.0])
                tang /= max(np.linalg.norm(tang), 1e-12)
                dirs.append(tang)
            for i in range(1, n_mv + 1):
                f = i / n_mv
                for k in range(K):
                    base = trans[k][n_press]
                    if kind == "slide":
                        trans[k].append(base + dirs[k] * amount * f)
                        rots[k].append(np.zeros(3))
                    else:
                        trans[k].append(base.copy())
                        rots[k].append(normals[k] * amount * f)
            seg_t += [U(cfg.t_move) / n_mv] * n_mv
            extra = {"amount": amount}
        n_rel = _steps(depth, 2 * cfg.max_step_mm)
        for i in range(1, n_rel + 1):
            f = i / n_rel
            for k in range(K):
                last_t, last_r = trans[k][-1], rots[k][-1]
                # lift along the normal to just above the rest surface, keeping any slide/twist
                lift = last_t + normals[k] * (depth + 2 * cfg.approach_gap) / n_rel
                trans[k].append(lift)
                rots[k].append(last_r.copy())
        seg_t += [U(cfg.t_release) / n_rel] * n_rel
        times = start_t + np.concatenate([[0.0], np.cumsum(seg_t)])
        position = np.array([p + n * cfg.approach_gap for p, n in zip(pts, normals)])
        rotation = np.array([_align_z(n) for n in normals])
        poke = Poke(kind, names, slots, position, rotation, np.array(trans, dtype=np.float64),
                    np.array(rots, dtype=np.float64), times, t, float(times[-1]) + (start_t - t),
                    depth, extra)
        pokes.append(poke)
        t = poke.t_retreat_end + U(cfg.t_gap)
    return pokes


def module_indenters(seed: int, cfg: TrajectoryConfig | None = None) -> list[str]:
    """The session's indentation modules (indenter id -> indenter name): two modules, as the seed's
    demonstrator holds one or two, unless p_two == 0."""
    cfg = cfg or TrajectoryConfig()
    rng = np.random.default_rng([seed, 1])
    first = str(rng.choice(cfg.indenters))
    if cfg.p_two <= 0:
        return [first]
    return [first, str(rng.choice([n for n in cfg.indenters if n != first] or [first]))]


def session_duration(pokes: list[Poke], cfg: TrajectoryConfig | None = None) -> float:
    cfg = cfg or TrajectoryConfig()
    return (pokes[-1].t_retreat_end if pokes else 0.0) + cfg.t_gap[0]


def poke_pose(poke: Poke, k: int, t: np.ndarray, hover: float) -> tuple[np.ndarray, np.ndarray]:
    """Tip position (T,3) and rotation vector (T,3) of the poke's k-th indenter for times t in
    [t_approach, t_retreat_end] (approach from and retreat to `hover` mm along the normal)."""
    t = np.asarray(t, dtype=np.float64)
    R0 = Rotation.from_rotvec(poke.rotation[k])
    n = R0.apply([0.0, 0.0, 1.0])
    pos = np.empty((len(t), 3))
    rot = np.empty((len(t), 3))
    a = t < poke.t_start
    s = minjerk((t[a] - poke.t_approach) / max(poke.t_start - poke.t_approach, 1e-9))
    pos[a] = poke.position[k] + np.outer(1 - s, n * hover)
    rot[a] = poke.rotation[k]
    b = t > poke.t_end
    s = minjerk((t[b] - poke.t_end) / max(poke.t_retreat_end - poke.t_end, 1e-9))
    end = poke.position[k] + poke.translation[k, -1]
    pos[b] = end + np.outer(s, n * hover)
    rot[b] = (Rotation.from_rotvec(poke.rotvec[k, -1]) * R0).as_rotvec()
    c = ~(a | b)
    if c.any():
        j, s = segment_phase(poke.times, t[c])
        tr = poke.translation[k, j] + s[:, None] * (poke.translation[k, j + 1] - poke.translation[k, j])
        rv = poke.rotvec[k, j] + s[:, None] * (poke.rotvec[k, j + 1] - poke.rotvec[k, j])
        pos[c] = poke.position[k] + tr
        rot[c] = (Rotation.from_rotvec(rv) * R0).as_rotvec()
    return pos, rot


@dataclass
class GuidedConfig:
    """A guided session (e.g. field recalibration): single-indenter presses along the surface normal
    at given points, in order, as a person follows on-screen prompts with a gauge probe."""

    points_mm: list                  # [[x, y, z]] rest-surface points (sensor frame, mm)
    depths_mm: list                  # press depth per point (mm)
    indenter: str = "sphere5"        # the gauge probe tip (INDENTER_SET name)
    hold_s: float = 1.0              # hold at depth ("hold ~1 s" in the recalibration prompt)
    seed: int = 0                    # timing jitter (approach/press/release durations, gaps)

    def to_dict(self) -> dict:
        return {"points_mm": [[float(v) for v in p] for p in self.points_mm],
                "depths_mm": [float(d) for d in self.depths_mm], "indenter": self.indenter,
                "hold_s": float(self.hold_s), "seed": int(self.seed)}


def plan_guided(g: GuidedConfig, gel: GelSurface, cfg: TrajectoryConfig | None = None) -> list[Poke]:
    """Presses of one indenter (module 0) at g.points_mm, perpendicular to the surface, with the
    same keypoint spacing, approach, hold and release rules as plan_session."""
    cfg = cfg or TrajectoryConfig()
    if len(g.points_mm) != len(g.depths_mm):
        raise ValueError(f"guided plan: {len(g.points_mm)} points but {len(g.depths_mm)} depths")
    if g.indenter not in INDENTER_SET:
        raise ValueError(f"guided plan: indenter {g.indenter!r} not in {sorted(INDENTER_SET)}")
    rng = np.random.default_rng([g.seed, 7])
    U = lambda r: float(rng.uniform(*r))  # noqa: E731
    t, pokes = cfg.t_lead, []
    for p, depth in zip(np.asarray(g.points_mm, float), g.depths_mm):
        n = gel.normals(p[None])[0]
        n_press, n_rel = _steps(depth, cfg.max_step_mm), _steps(depth, 2 * cfg.max_step_mm)
        trans = [np.zeros(3)] + [-n * depth * i / n_press for i in range(1, n_press + 1)]
        trans.append(trans[-1].copy())                                            # hold
        trans += [trans[n_press] + n * (depth + 2 * cfg.approach_gap) * i / n_rel for i in range(1, n_rel + 1)]
        start_t = t + U(cfg.t_approach)
        seg_t = [U(cfg.t_press) / n_press] * n_press + [g.hold_s] + [U(cfg.t_release) / n_rel] * n_rel
        times = start_t + np.concatenate([[0.0], np.cumsum(seg_t)])
        tr = np.array([trans], dtype=np.float64)
        poke = Poke("press", [g.indenter], [0], (p + n * cfg.approach_gap)[None], _align_z(n)[None], tr,
                    np.zeros_like(tr), times, t, float(times[-1]) + (start_t - t), float(depth), {"guided": True})
        pokes.append(poke)
        t = poke.t_retreat_end + U(cfg.t_gap)
    return pokes


def shorten(poke: Poke, last: int, cfg: TrajectoryConfig | None = None) -> Poke | None:
    """The poke cut at keypoint `last` (the last one the physics could reach), followed by a release
    along each indenter's approach normal to just above the rest surface (keeping any slide/twist
    reached). Keypoint times up to `last` are unchanged; the release takes the planned release time.
    None when nothing in contact would remain (last < 1)."""
    cfg = cfg or TrajectoryConfig()
    if last < 1 or last >= poke.translation.shape[1] - 1:
        return None
    K = poke.translation.shape[0]
    normals = np.array([Rotation.from_rotvec(poke.rotation[k]).apply([0.0, 0.0, 1.0]) for k in range(K)])
    tr, rv = poke.translation[:, :last + 1], poke.rotvec[:, :last + 1]
    down = np.array([-float(tr[k, -1] @ normals[k]) for k in range(K)])         # depth along the normal
    n_rel = _steps(max(down.max(), cfg.approach_gap), 2 * cfg.max_step_mm)
    lift = [(down + 2 * cfg.approach_gap)[:, None] * normals * i / n_rel for i in range(1, n_rel + 1)]
    tr = np.concatenate([tr, np.stack([tr[:, -1] + d for d in lift], 1)], 1)
    rv = np.concatenate([rv, np.repeat(rv[:, -1:], n_rel, 1)], 1)
    seg = min(float(poke.times[-1] - poke.times[-2]), float(poke.times[-1] - poke.times[last]) / n_rel)  # ends in time
    times = np.concatenate([poke.times[:last + 1], poke.times[last] + seg * np.arange(1, n_rel + 1)])
    extra = {**poke.extra, "replanned": "shortened", "planned_keypoints": int(poke.translation.shape[1]),
             "kept_keypoints": int(last + 1)}
    return Poke(poke.kind, list(poke.indenters), list(poke.slots), poke.position.copy(), poke.rotation.copy(), tr, rv,
                times, poke.t_approach, float(times[-1]) + (poke.t_start - poke.t_approach), poke.depth, extra)


def apply_replans(plan: list[Poke], events: list[dict], cfg: TrajectoryConfig | None = None) -> list[Poke]:
    """Re-apply a recording's physics replans (truth.json `physics_events`) to its original plan:
    {"poke": i, "action": "shortened", "last_keypoint": j} or {"poke": i, "action": "skipped"}."""
    out = list(plan)
    for ev in events:
        i = int(ev["poke"])
        if ev["action"] == "shortened":
            out[i] = shorten(plan[i], int(ev["last_keypoint"]), cfg)
        elif ev["action"] == "skipped":
            out[i] = None
    return [p for p in out if p is not None]
