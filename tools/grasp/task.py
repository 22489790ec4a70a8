"""The selective grasp's task distribution: what a randomized trial draws from its seed.

`TaskDistribution` holds the ranges, with today's fixed scene (the seed's objects, the 0.6 N pull
along the object, friction 1, MuJoCo's default contact) as named defaults; `draw(dist, pair, seed)`
is a pure function of its arguments and returns a `TaskDraw`, which the trial applies to its world
and records in its result. A draw of the fixed scene (`fixed(pair, seed)`) is what `tensortouch grasp`
runs without `--randomize`.

- placement: the two objects' layout shifted in the objects' plane, uniform within ±`placement_mm`
  across the pinch and along the objects, and turned about the pinch axis (its normal) by a yaw
  uniform within ±`yaw_deg`;
- sizes: each cable's diameter uniform in `cable_diameter_mm`, each pen's in `pen_diameter_mm`; the
  two cables of A+A share one diameter (identical cables), A+B's are drawn apart and the thinner is A;
- pull: the force uniform in `pull_scale` × `pull_n`, its direction tilted off the pulled object's
  axis by an angle uniform within ±`pull_tilt_deg`, about a uniform azimuth;
- contact: MuJoCo friction uniform in `friction`, and one of `contacts` (soft: MuJoCo's default
  solref 20 ms; stiff: 2 ms on the fingertips and the objects) with equal chance.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

# today's fixed scene (docs/grasp.md): the seed's cables A 2.18 mm and B 3.01 mm, an 8 mm pen
FIXED_DIAMETER_MM = {"A": 2.18, "B": 3.01, "pen": 8.0}
CONTACT_SOLREF_S = {"soft": 0.02, "stiff": 0.002}   # MuJoCo contact time constant per setting


@dataclass(frozen=True)
class TaskDistribution:
    placement_mm: float = 5.0                       # ± across the pinch and along the objects
    yaw_deg: float = 15.0                           # ± about the pinch axis
    cable_diameter_mm: tuple[float, float] = (1.0, 3.0)
    pen_diameter_mm: tuple[float, float] = (6.0, 10.0)
    pull_n: float = 0.6                             # today's pull
    pull_scale: tuple[float, float] = (0.5, 2.0)    # × pull_n
    pull_tilt_deg: float = 30.0                     # ± off the pulled object's axis
    friction: tuple[float, float] = (0.3, 1.0)
    contacts: tuple[str, ...] = ("soft", "stiff")

    def __post_init__(self):
        for name in ("cable_diameter_mm", "pen_diameter_mm", "pull_scale", "friction"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"TaskDistribution.{name} = {(lo, hi)}; expected 0 < low <= high")
        bad = [c for c in self.contacts if c not in CONTACT_SOLREF_S]
        if bad or not self.contacts:
            raise ValueError(f"TaskDistribution.contacts = {self.contacts}; expected some of {tuple(CONTACT_SOLREF_S)}")


@dataclass(frozen=True)
class TaskDraw:
    pulled: int                          # which object is pulled (0 or 1)
    shift_mm: tuple[float, float]        # the layout's shift: across the pinch, along the objects
    yaw_deg: float                       # the layout turned about the pinch axis
    diameters_mm: tuple[float, float]
    pull_n: float
    pull_tilt_deg: float                 # the pull's angle off the pulled object's axis
    pull_azimuth_deg: float              # about that axis, from the across direction towards the pinch normal
    friction: float
    contact: str                         # "soft" or "stiff"

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    def pull_direction(self, axis: np.ndarray, across: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """The pull's unit direction from the pulled object's axis and the layout's across and normal
        directions (world)."""
        t, a = np.radians(self.pull_tilt_deg), np.radians(self.pull_azimuth_deg)
        side = np.cos(a) * np.asarray(across, float) + np.sin(a) * np.asarray(normal, float)
        d = np.cos(t) * np.asarray(axis, float) + np.sin(t) * side
        return d / np.linalg.norm(d)


def _kinds(pair: tuple[str, str]) -> tuple[str, str]:
    return tuple("pen" if name == "pen" else "cable" for name in pair)


def draw(dist: TaskDistribution, pair: tuple[str, str], seed: int) -> TaskDraw:
    """One trial's task, from `seed` alone (the pulled object is the seed's first draw, as in the
    fixed scene)."""
    rng = np.random.default_rng(seed)
    pulled = int(rng.integers(0, 2))
    shift = rng.uniform(-1.0, 1.0, 2) * dist.placement_mm
    yaw = float(rng.uniform(-1.0, 1.0) * dist.yaw_deg)
    kinds = _kinds(pair)
    ranges = {"cable": dist.cable_diameter_mm, "pen": dist.pen_diameter_mm}
    d = [float(rng.uniform(*ranges[k])) for k in kinds]
    if pair[0] == pair[1] and kinds[0] == "cable":     # two identical cables
        d[1] = d[0]
    elif pair == ("A", "B"):
        d = sorted(d)
    pull = float(dist.pull_n * rng.uniform(*dist.pull_scale))
    tilt = float(rng.uniform(-1.0, 1.0) * dist.pull_tilt_deg)
    azimuth = float(rng.uniform(0.0, 180.0))
    friction = float(rng.uniform(*dist.friction))
    contact = dist.contacts[int(rng.integers(0, len(dist.contacts)))]
    return TaskDraw(pulled, (float(shift[0]), float(shift[1])), yaw, (d[0], d[1]), pull, tilt, azimuth,
                    friction, contact)


def fixed(pair: tuple[str, str], seed: int, jitter_mm: float = 1.0, pull_n: float = 0.6) -> tuple[TaskDraw, np.ndarray]:
    """Today's fixed scene as a draw, and its ±`jitter_mm` placement jitter (3 numbers, mm, in the
    world; the trial removes its part along the pinch normal): the same random numbers, in the same
    order, as before the distribution existed."""
    rng = np.random.default_rng(seed)
    pulled = int(rng.integers(0, 2))
    jitter = rng.uniform(-1, 1, 3) * jitter_mm
    return TaskDraw(pulled, (0.0, 0.0), 0.0, (FIXED_DIAMETER_MM[pair[0]], FIXED_DIAMETER_MM[pair[1]]), pull_n,
                    0.0, 0.0, 1.0, "soft"), jitter


def factors(d: dict, pair: tuple[str, str]) -> dict[str, float | None]:
    """The drawn factors of a recorded draw (`TaskDraw.as_dict()`) of `pair` as numbers, for the
    table's bins; a factor the pair does not have (a cable's diameter between two pens) is None."""
    kinds = _kinds(pair)
    cables = [x for x, k in zip(d["diameters_mm"], kinds) if k == "cable"]
    pens = [x for x, k in zip(d["diameters_mm"], kinds) if k == "pen"]
    return {"shift across, size (mm)": abs(d["shift_mm"][0]), "shift along, size (mm)": abs(d["shift_mm"][1]),
            "yaw, size (°)": abs(d["yaw_deg"]),
            "thinnest cable (mm)": min(cables) if cables else None, "thickest pen (mm)": max(pens) if pens else None,
            "pull (N)": d["pull_n"], "pull tilt, size (°)": abs(d["pull_tilt_deg"]), "friction": d["friction"]}
