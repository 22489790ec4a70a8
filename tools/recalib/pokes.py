"""Pokes: detection from per-frame clusters, acceptance rules, and where to poke next.

Pure: clusters in (anything with `uv_px`, `position_mm`, `force_n`, `force_mag_n`, like
runtime.stages.contacts.Cluster), poke summaries and verdicts out. A poke is a contact episode: it starts
when a cluster exceeds `contact_floor_n` and ends after `release_frames` frames without one. The
poke's predicted force and position are averaged over its plateau (frames within
`plateau_fraction` of the peak), and the reference force is averaged the same way over the gauge
readings of the episode, so a constant gauge latency does not bias the pairing.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PokeRules:
    contact_floor_n: float = 0.05      # a cluster this strong starts / sustains a poke episode
    release_frames: int = 3            # frames without contact that end an episode
    min_frames: int = 3                # shorter episodes are taps, not pokes
    plateau_fraction: float = 0.9      # frames (readings) within 90 % of the peak form the plateau
    min_force_n: float = 0.3           # "too light" below this (model peak or reference)
    max_force_n: float = 20.0          # out of range for the gel / gauge above this
    min_separation_mm: float = 4.0     # "too close" to an accepted poke (3D distance on the gel)
    second_contact_ratio: float = 0.15  # a 2nd cluster above this share of the main one → not single
    merge_radius_mm: float = 4.0       # clusters this close to the main one are the same contact (the model
                                       # may split one probe's patch: sphere R5 at 1.5 mm ≈ 3.9 mm contact radius)
    reach_fraction: float = 0.85       # suggestions stay inside this fraction of the gel's θ range
    reach_theta_rad: float | None = None  # and inside this θ (e.g. the model's trained contact range)


@dataclass
class Poke:
    """One detected poke (before or after acceptance)."""

    t0: float
    t1: float
    frames: int
    pred_force: np.ndarray          # (3,) N, plateau mean of the main cluster's force
    uv_px: np.ndarray               # (2,) model-grid position (u = column, v = row), continuous px
    xyz_mm: np.ndarray              # (3,) 3D centroid on the gel, mm
    second_ratio: float             # largest (2nd cluster / main cluster) force ratio on the plateau
    ref_force_n: float | None = None
    verdict: str = ""               # "" = accepted, else the rejection reason

    @property
    def pred_mag(self) -> float:
        return float(np.linalg.norm(self.pred_force))

    def to_dict(self) -> dict:
        return {"t0": self.t0, "t1": self.t1, "frames": self.frames,
                "pred_force_n": [float(v) for v in self.pred_force], "uv_px": [float(v) for v in self.uv_px],
                "xyz_mm": [float(v) for v in self.xyz_mm], "second_ratio": self.second_ratio,
                "ref_force_n": self.ref_force_n, "verdict": self.verdict}


@dataclass
class PokeDetector:
    """Feed (t, clusters) per frame; returns a `Poke` when an episode ends, else None."""

    rules: PokeRules = field(default_factory=PokeRules)
    _frames: list = field(default_factory=list)
    _quiet: int = 0

    @property
    def in_contact(self) -> bool:
        return bool(self._frames)

    def feed(self, t: float, clusters) -> Poke | None:
        strong = sorted((c for c in clusters if c.force_mag_n >= self.rules.contact_floor_n),
                        key=lambda c: c.force_mag_n, reverse=True)
        if strong:
            self._quiet = 0
            self._frames.append((t, strong))
            return None
        if not self._frames:
            return None
        self._quiet += 1
        if self._quiet < self.rules.release_frames:
            return None
        frames, self._frames, self._quiet = self._frames, [], 0
        if len(frames) < self.rules.min_frames:
            log.debug("episode of %d frames ignored (tap)", len(frames))
            return None
        return summarize(frames, self.rules)

    def flush(self) -> Poke | None:
        """End of the source: close an open episode."""
        frames, self._frames, self._quiet = self._frames, [], 0
        return summarize(frames, self.rules) if len(frames) >= self.rules.min_frames else None


def merge_main(clusters, radius_mm: float):
    """(force (3,), uv_px, position_mm, magnitude, strongest other contact's magnitude) of the
    strongest cluster together with the clusters within `radius_mm` of it (one contact split in parts;
    force vectors summed, positions force-weighted)."""
    main = clusters[0]
    c0 = np.asarray(main.position_mm, float)
    part = [c for c in clusters if np.linalg.norm(np.asarray(c.position_mm, float) - c0) <= radius_mm]
    other = [c.force_mag_n for c in clusters if np.linalg.norm(np.asarray(c.position_mm, float) - c0) > radius_mm]
    w = np.array([c.force_mag_n for c in part]) + 1e-12
    force = np.sum([np.asarray(c.force_n, float) for c in part], axis=0)
    uv = np.average([np.asarray(c.uv_px, float) for c in part], axis=0, weights=w)
    xyz = np.average([np.asarray(c.position_mm, float) for c in part], axis=0, weights=w)
    return force, uv, xyz, float(np.linalg.norm(force)), max(other, default=0.0)


def summarize(frames: list, rules: PokeRules = PokeRules()) -> Poke:
    """frames: [(t, clusters sorted strongest first)] → plateau-averaged poke (the main contact = the
    strongest cluster plus the parts within rules.merge_radius_mm of it)."""
    merged = [merge_main(f[1], rules.merge_radius_mm) for f in frames]
    mains = np.array([m[3] for m in merged])
    plateau = [m for m in merged if m[3] >= rules.plateau_fraction * mains.max()]
    force = np.mean([m[0] for m in plateau], axis=0)
    w = np.array([m[3] for m in plateau])
    uv = np.average([m[1] for m in plateau], axis=0, weights=w)
    xyz = np.average([m[2] for m in plateau], axis=0, weights=w)
    second = max(m[4] / m[3] if m[3] > 0 else 0.0 for m in plateau)
    return Poke(t0=float(frames[0][0]), t1=float(frames[-1][0]), frames=len(frames), pred_force=force,
                uv_px=uv, xyz_mm=xyz, second_ratio=float(second))


def reference_from_readings(t: np.ndarray, force: np.ndarray, t0: float, t1: float,
                            rules: PokeRules = PokeRules(), slack_s: float = 0.25) -> float | None:
    """Plateau mean of gauge readings (t s, force N) within [t0 - slack, t1 + slack]; None if none."""
    t = np.asarray(t, float)
    f = np.abs(np.asarray(force, float))
    sel = (t >= t0 - slack_s) & (t <= t1 + slack_s)
    if not np.any(sel):
        return None
    f = f[sel]
    return float(f[f >= rules.plateau_fraction * f.max()].mean())


def check_poke(poke: Poke, accepted: list[Poke], rules: PokeRules = PokeRules()) -> str:
    """'' if the poke is acceptable, else a sentence saying why not (shown to the user)."""
    if poke.second_ratio > rules.second_contact_ratio:
        return (f"not a single contact: a second contact carried {poke.second_ratio:.0%} of the main one's "
                "force; poke with one probe tip only")
    if poke.pred_mag < rules.min_force_n:
        return f"too light: the sensor saw {poke.pred_mag:.2f} N, press to at least {rules.min_force_n:.1f} N"
    if poke.ref_force_n is None:
        return "no reference force: the gauge gave no reading during the poke"
    if poke.ref_force_n < rules.min_force_n:
        return f"too light: the gauge read {poke.ref_force_n:.2f} N, press to at least {rules.min_force_n:.1f} N"
    if max(poke.ref_force_n, poke.pred_mag) > rules.max_force_n:
        return f"too hard: above {rules.max_force_n:.0f} N; the gel and gauge are not calibrated there"
    for i, other in enumerate(accepted):
        d = float(np.linalg.norm(poke.xyz_mm - other.xyz_mm))
        if d < rules.min_separation_mm:
            return (f"too close to accepted poke {i + 1} ({d:.1f} mm apart, need {rules.min_separation_mm:.0f} mm); "
                    "poke where the map shows X")
    return ""


def candidate_pixels(mask: np.ndarray, theta: np.ndarray, rules: PokeRules = PokeRules()) -> np.ndarray:
    """(K, 2) integer (row, col) of pixels a probe can reach: on the gel, θ ≤ reach_fraction·θmax."""
    th = np.where(mask, theta, np.nan)
    limit = rules.reach_fraction * np.nanmax(th)
    if rules.reach_theta_rad is not None:
        limit = min(limit, rules.reach_theta_rad)
    return np.argwhere(mask & (np.nan_to_num(th, nan=np.inf) <= limit))


def suggest_next(mask: np.ndarray, theta: np.ndarray, surface_xyz: np.ndarray, accepted_xyz: list,
                 rules: PokeRules = PokeRules()) -> tuple[np.ndarray, np.ndarray]:
    """Where to poke next: the apex first, then the reachable pixel farthest (3D) from every accepted
    poke (farthest-point sampling spreads 5–7 pokes over the gel). Returns (uv_px centre, xyz_mm)."""
    cand = candidate_pixels(mask, theta, rules)
    if len(cand) == 0:
        raise ValueError("calibration mask has no reachable gel pixel")
    pts = surface_xyz[cand[:, 0], cand[:, 1]]
    if len(accepted_xyz) == 0:
        k = int(np.argmin(theta[cand[:, 0], cand[:, 1]]))
    else:
        acc = np.asarray(accepted_xyz, float).reshape(-1, 3)
        dmin = np.linalg.norm(pts[:, None, :] - acc[None], axis=-1).min(axis=1)
        k = int(np.argmax(dmin))
    r, c = cand[k]
    return np.array([c + 0.5, r + 0.5]), pts[k].astype(float)


def describe(uv_px: np.ndarray, size: tuple[int, int], theta: np.ndarray, mask: np.ndarray) -> str:
    """'at 3 o'clock, 60 % of the way from the top to the rim' as seen in the camera image."""
    h, w = size
    dx, dy = uv_px[0] - w / 2, uv_px[1] - h / 2
    r, c = int(min(max(uv_px[1], 0), h - 1)), int(min(max(uv_px[0], 0), w - 1))
    frac = float(theta[r, c] / np.nanmax(np.where(mask, theta, np.nan)))
    if frac < 0.1:
        return "on the top of the dome (centre of the image)"
    hour = int(round(np.degrees(np.arctan2(dx, -dy)) % 360 / 30)) % 12 or 12
    return f"at {hour} o'clock in the camera image, {frac:.0%} of the way from the top to the rim"


def ascii_map(size: tuple[int, int], mask: np.ndarray, accepted_uv: list, target_uv=None, cols: int = 21) -> str:
    """A small text map of the gel: '.' gel, 'o' accepted pokes, 'X' the next target."""
    h, w = size
    rows = max(3, cols // 2)
    grid = [[" "] * cols for _ in range(rows)]
    for i in range(rows):
        for j in range(cols):
            if mask[int((i + 0.5) * h / rows), int((j + 0.5) * w / cols)]:
                grid[i][j] = "."

    def put(uv, ch):
        j = min(cols - 1, max(0, int(uv[0] / w * cols)))
        i = min(rows - 1, max(0, int(uv[1] / h * rows)))
        grid[i][j] = ch

    for uv in accepted_uv:
        put(uv, "o")
    if target_uv is not None:
        put(target_uv, "X")
    return "\n".join("".join(r) for r in grid)
