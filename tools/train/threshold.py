"""The package's contact threshold, measured on training sessions (part of the export stage).

The runtime's cluster core threshold (per-pixel |f| in N, runtime/stages/contacts.py) depends on the
network: how much force it paints on an untouched gel (false contacts) and how thin it spreads a
light touch. So every package carries its own, measured after export on training sessions through
the runtime (int8, the unit's calibration): the lowest value of a grid at which no rest frame
(every indenter's measured |F| below `rest_n`, and no touch just before or after: `rest_frames`) has a
cluster core, times a margin of 4/3. The runtime takes it from `manifest.runtime.contacts.threshold_n`
(PipelineConfig.for_package); packages without it (or with null: no grid value was clean, e.g. a
minutes-long smoke model) use the ContactConfig default.

Light touches spread thinner than that threshold. The light-touch rule (ContactConfig.weak_threshold_n /
min_total_n) is measured in the same pass: per weak threshold w of `weak_grid`, min_total_n(w) = the
largest |total force| of a component above w on any rest frame × `weak_margin`; the w that detects the
most light-contact frames (measured |F| in `light_n`) with the strong threshold wins (ties: the larger w).
The same pass keeps single- and two-contact frames for merging (which cores are one contact) and, with
--support, the cluster support (how far a contact's force reaches; tools/train/support.py), chosen once
the threshold and the rule are known.

    tensortouch train threshold --package DIR --session SESSION_DIR:STORE_DIR [...] [--write]
    tensortouch train threshold --package DIR --session ... --check    # held-out detection report
    tensortouch train threshold --package DIR --units validation --rest-budget 0.005 --write   # chosen on validation units

`--tare on|off` measures with the runtime's tare on or off (PipelineConfig.tare: the network's fields for the
baseline against itself subtracted from every frame's) and, with --write, records it as `runtime.tare` beside the
settings it chose: the settings belong to the fields they were measured on. Without it the package's own is used.
"""
from __future__ import annotations

import argparse
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .support import SupportConfig, choose_merge, choose_split, choose_support, support_sample, two_sample

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ThresholdConfig:
    grid: tuple = tuple(np.round(np.arange(0.001, 0.00801, 0.00025), 5))   # N per pixel
    # the lowest clean grid value × this. 1 was not enough on held-out data: a package whose lowest clean
    # value on training sessions was 0.0015 N painted a core on 0.8 % / 1.6 % of the rest frames of the
    # held-out TWIN-H01 session / the demo there, and on none at 0.002 N
    margin: float = 4.0 / 3.0
    rest_n: float = 0.05      # a frame is at rest when every indenter's measured |F| is below this (N) ...
    # ... and no frame within ± rest_guard_s reads rest_touch_n or more: the frame just after a release (or
    # just before a touch) still holds a real light contact that the F/T reads below rest_n. Session 16: one
    # such frame (0.034 N, 0.03 s after 0.12 N, TWIN-T66) set the threshold and the light-touch bars of a
    # package for every unit (docs/history/BENCHMARKS-sessions-1-16.md "The release frame"). rest_touch_n stays above the F/T's
    # noise at rest (up to ~0.05 N on the twin), so noise spikes do not drop their neighbours.
    rest_touch_n: float = 0.1
    rest_guard_s: float = 0.1
    contact_n: float = 0.5    # ... and in contact when one is above this (detection is reported)
    min_pixels: int = 3       # as ContactConfig.min_pixels: smaller specks are not clusters
    weak_grid: tuple = (0.0004, 0.0006, 0.0008, 0.001, 0.0012)        # N per pixel
    # held-out sessions (docs/history/BENCHMARKS-sessions-1-16.md "Light contacts"): 4/3 on training rest frames left 23 false
    # rest frames in 5747 on held-out ones at w = 0.0006, 1.5 left 20 (the strong threshold alone: 16)
    weak_margin: float = 1.5
    min_total_floor_n: float = 0.02   # min_total_n is never below this (N), even on a spotless rest set
    light_n: tuple = (0.2, 1.0)   # measured |F| band (N) of the light contacts the weak rule is chosen on
    support: SupportConfig = SupportConfig()
    # the farther support is measured only on request (--support): it lowered held-out |F| MAE by 1-7 % but
    # moved the recalibration's nominal-crop errors, so its 60 % cut held on 3 of 6 units instead of 5
    # (docs/history/BENCHMARKS-sessions-1-16.md "Contact support and merging"); merging is always measured
    measure_support: bool = False
    # or a fixed cluster reach (px; floor 0 N), chosen by the build (BuildConfig.support_px, `--support-px`):
    # 20 px recovers a sliding contact's shear haze (docs/history/BENCHMARKS-sessions-1-16.md "Weights read back from the shipped package")
    support_px: float | None = None
    # The rule chosen on held-out (validation) units instead (`--rest-budget`): 0 = off, the rule above. Above 0,
    # with no margin: the lowest strong threshold with at most half this share of the rest frames holding a
    # core, then the weak rule that detects the most frames with a measured |F| ≥ detect_n while at most this
    # share holds one (`budget_rule`).
    rest_budget: float = 0.0
    detect_n: float = 0.2


def _has_core(mag: np.ndarray, t: float, min_pixels: int) -> bool:
    n, _, stats, _ = cv2.connectedComponentsWithStats((mag > t).astype(np.uint8), connectivity=8)
    return bool(n > 1 and stats[1:, cv2.CC_STAT_AREA].max() >= min_pixels)


def rest_frames(t: np.ndarray, fmax: np.ndarray, cfg: "ThresholdConfig") -> np.ndarray:
    """(T,) bool: frames at rest: the largest measured |F| (N) is below cfg.rest_n, and no frame within
    ± cfg.rest_guard_s of this one reads cfg.rest_touch_n or more (t in s, increasing)."""
    t, fmax = np.asarray(t, float), np.asarray(fmax, float)
    touch, below = fmax >= cfg.rest_touch_n, fmax < cfg.rest_n
    if not touch.any():
        return below
    tt = t[touch]
    k = np.searchsorted(tt, t)
    near = np.minimum(np.abs(tt[np.minimum(k, len(tt) - 1)] - t), np.abs(tt[np.maximum(k - 1, 0)] - t))
    return below & (near > cfg.rest_guard_s)


def weak_totals(fp: np.ndarray, mag: np.ndarray, mask: np.ndarray, grid) -> list[float]:
    """Per weak threshold: the largest |total force| (N) of a component of pixels above it."""
    from ...runtime.stages.contacts import weak_components

    none = np.zeros(mag.shape, bool)
    return [float(weak_components(fp, mag, mask, none, w)[1].max(initial=0.0)) for w in grid]


def sweep_session(session_dir, package, calibration, cfg: ThresholdConfig = ThresholdConfig()) -> dict:
    """Per grid value: rest frames with a cluster core, contact frames with one (counts); per weak
    threshold the largest component total on a rest frame; the light-contact frames' cores and totals."""
    from ...contracts.session import load_session
    from ...runtime.offline import replay_session
    from ...runtime.stages.contacts import pixel_forces
    from ..scoring import measured_at

    ses = load_session(session_dir)
    frames = ses.table("frames")
    meas = measured_at(ses, frames[:, 0])
    at_rest = rest_frames(frames[:, 0], _max_force(meas), cfg)
    grid = np.asarray(cfg.grid)
    rest_fp = np.zeros(len(grid), int)
    hit = np.zeros(len(grid), int)
    n_rest = n_contact = 0
    rest_weak = np.zeros(len(cfg.weak_grid))
    light = {"core": [], "weak": []}
    kept, seen = {"support": [], "two": []}, {"support": 0, "two": 0}
    rows = {"rest_core": [], "rest_weak": [], "touch_core": [], "touch_weak": []}   # per frame, for rest_budget
    for i, res in enumerate(replay_session(ses, package, calibration, precision="int8", threads=1)):
        if res.fields is None:
            continue
        tips = np.array([meas[k]["tip"][i] for k in meas])
        forces = np.array([meas[k]["force"][i] for k in meas])
        mags = np.linalg.norm(forces, axis=1)
        rest, contact = bool(at_rest[i]), bool(np.any(mags > cfg.contact_n))
        lit = cfg.light_n[0] < mags.max() <= cfg.light_n[1]
        fp = pixel_forces(res.fields, calibration.pixel_area)
        for name, got in (("support", support_sample(fp, tips, forces, cfg.rest_n, cfg.support)),
                          ("two", two_sample(fp, tips, forces, cfg.support))):
            if got is not None:          # every stride-th such frame, at most frames_per_session
                seen[name] += 1
                if seen[name] % cfg.support.stride == 0 and len(kept[name]) < cfg.support.frames_per_session:
                    kept[name].append(got)
        touch = bool(mags.max() >= cfg.detect_n)
        if not (rest or contact or lit or touch):
            continue
        mag = np.where(calibration.mask, np.sqrt((fp ** 2).sum(axis=0)), 0.0)
        has = np.array([_has_core(mag, t, cfg.min_pixels) for t in grid])
        if rest or lit or touch:
            tot = weak_totals(fp, mag, calibration.mask, cfg.weak_grid)
        if rest or touch:
            rows["rest_core" if rest else "touch_core"].append(has)
            rows["rest_weak" if rest else "touch_weak"].append(tot)
        if rest:
            n_rest += 1
            rest_fp += has
            rest_weak = np.maximum(rest_weak, tot)
        if lit:
            light["core"].append(has.tolist())
            light["weak"].append(tot)
        if contact:
            n_contact += 1
            hit += has
    return {"session": str(session_dir), "rest_frames": n_rest, "contact_frames": n_contact,
            "rest_with_core": rest_fp.tolist(), "contact_with_core": hit.tolist(),
            "rest_weak_max": rest_weak.tolist(), "light": light,
            "support": kept["support"], "two": kept["two"], "calibration": calibration,   # these stay in memory (not JSON)
            **{k: np.array(v, bool if k.endswith("core") else float).reshape(len(v), -1) for k, v in rows.items()}}


def _max_force(meas: dict) -> np.ndarray:
    """(T,) the largest measured |F| over the indenters (N), from `measured_at`."""
    return np.max([np.linalg.norm(m["force"], axis=1) for m in meas.values()], axis=0)


def choose(sweeps: list[dict], cfg: ThresholdConfig = ThresholdConfig()) -> dict:
    if cfg.rest_budget > 0:
        out = choose_budget(sweeps, cfg)
        return out if out["threshold_n"] is None else dict(out, **_support(sweeps, out, cfg))
    grid = np.asarray(cfg.grid)
    fp = np.sum([s["rest_with_core"] for s in sweeps], axis=0)
    hit = np.sum([s["contact_with_core"] for s in sweeps], axis=0)
    n_contact = sum(s["contact_frames"] for s in sweeps)
    clean = np.flatnonzero(fp == 0)
    measured = {"rule": f"lowest grid value with no cluster core on any rest frame (|F| < {cfg.rest_n} N, none "
                        f">= {cfg.rest_touch_n} N within ± {cfg.rest_guard_s} s) x {cfg.margin:.4g}",
                "grid_n": grid.tolist(), "rest_frames": int(sum(s["rest_frames"] for s in sweeps)),
                "rest_frames_with_core": fp.tolist(), "contact_frames": int(n_contact),
                "sessions": [Path(s["session"]).name for s in sweeps]}
    if not len(clean):   # no value is clean: say so, and let the runtime keep its default
        log.warning("contact threshold: every grid value up to %g N leaves false contacts on rest frames (%d at "
                    "the top): the network paints force on an untouched gel; no threshold recorded", grid[-1], fp[-1])
        return {"threshold_n": None, "weak_threshold_n": None, "min_total_n": None,
                "support_radius_px": None, "support_floor_n": None, "merge_n": None, "split_dip": None,
                "measured": dict(measured, contact_detected_fraction=None)}
    t = float(round(grid[int(clean[0])] * cfg.margin, 5))
    k = min(int(np.searchsorted(grid, t - 1e-12)), len(grid) - 1)      # the first grid value >= t
    measured["contact_detected_fraction"] = float(hit[k] / n_contact) if n_contact else None
    measured["detected_at_n"] = float(grid[k])
    out = dict({"threshold_n": t, "measured": measured}, **choose_weak(sweeps, k, cfg, measured))
    return dict(out, **_support(sweeps, out, cfg))


def _support(sweeps: list[dict], chosen: dict, cfg: ThresholdConfig) -> dict:
    """Merging, splitting, then the cluster support, with the chosen threshold and rule (None: sweeps without
    support frames)."""
    from dataclasses import replace

    from ...runtime.pipeline import contact_config

    samples, cals, two, two_cals = _contact_frames(sweeps)
    cc = contact_config(chosen)                 # the runtime's reading of these keys, as it will apply them
    rules = choose_merge(samples, cals, two, two_cals, cc, cfg.support)
    chosen["measured"].update(rules.pop("measured"))
    cc = replace(cc, merge_n=rules["merge_n"] or 0.0)
    split = choose_split(samples, cals, two, two_cals, cc, cfg.support)
    chosen["measured"].update(split.pop("measured"))
    rules.update(split)
    if cfg.support_px:
        chosen["measured"]["support_rule"] = f"fixed by the build: {cfg.support_px:g} px, floor 0 N"
        return dict({"support_radius_px": float(cfg.support_px), "support_floor_n": 0.0}, **rules)
    if not cfg.measure_support:
        return dict({"support_radius_px": None, "support_floor_n": None}, **rules)
    cc = replace(cc, split_dip=rules["split_dip"] or 0.0)
    res = choose_support(samples, cals, cc, cfg.support)
    chosen["measured"].update(res.pop("measured"))
    return dict(res, **rules)


def _contact_frames(sweeps: list[dict]) -> tuple[list, list, list, list]:
    """The sweeps' single-contact samples, their calibrations, two-contact samples, their calibrations."""
    samples = [x for s in sweeps for x in s.get("support", [])]
    cals = [s["calibration"] for s in sweeps for _ in s.get("support", [])]
    two = [x for s in sweeps for x in s.get("two", [])]
    two_cals = [s["calibration"] for s in sweeps for _ in s.get("two", [])]
    return samples, cals, two, two_cals


def choose_weak(sweeps: list[dict], k: int, cfg: ThresholdConfig, measured: dict) -> dict:
    """The light-touch rule for a strong threshold at grid index k (see the module doc); fills
    `measured` in place and returns the manifest keys (both None, i.e. rule off, when a sweep predates
    the rule or no session has light frames)."""
    off = {"weak_threshold_n": None, "min_total_n": None}
    if not all("light" in s for s in sweeps):
        return off
    wg = np.asarray(cfg.weak_grid)
    fmin = np.maximum(np.max([s["rest_weak_max"] for s in sweeps], axis=0) * cfg.weak_margin, cfg.min_total_floor_n)
    core = np.array([c[k] for s in sweeps for c in s["light"]["core"]], bool)
    weak = np.array([w for s in sweeps for w in s["light"]["weak"]]).reshape(len(core), len(wg))
    measured.update(weak_rule=f"per weak threshold: the largest rest-frame component total x {cfg.weak_margin:.4g}; "
                              f"the one detecting most frames with {cfg.light_n[0]} < |F| <= {cfg.light_n[1]} N",
                    weak_grid_n=wg.tolist(), weak_min_total_n=np.round(fmin, 5).tolist(), light_frames=int(len(core)))
    if not len(core):
        return off
    det = core[:, None] | (weak >= fmin[None, :])
    frac = det.mean(axis=0)
    j = len(wg) - 1 - int(np.argmax(frac[::-1]))      # the best; on ties the larger (stricter) w
    measured.update(light_detected_fraction=float(frac[j]), light_detected_strong_only=float(core.mean()),
                    light_detected_by_weak_n=np.round(frac, 4).tolist())
    return {"weak_threshold_n": float(wg[j]), "min_total_n": float(round(fmin[j], 5))}


def budget_rule(rest_core: np.ndarray, rest_weak: np.ndarray, touch_core: np.ndarray, touch_weak: np.ndarray,
                grid, weak_grid, budget: float, floor_n: float) -> dict | None:
    """Contact settings under a phantom budget. Rows are frames: *_core (n, G) bool, a core above grid[g]; *_weak
    (n, J), the largest |total force| (N) of a component above weak_grid[j].

    The strong threshold is the lowest grid value at which at most half the budget of the rest frames holds a
    core (the training-session rule with a budget instead of none, and no margin: a strong core also sets the
    clusters, so it is not traded for the weak rule, whose components can join two contacts). Then, of the weak
    thresholds below it and the rule off, the one with the smallest min_total_n that keeps the rest frames with
    a core within the whole budget and detects the most touch frames (ties: the rule off, then the larger weak
    threshold). None: even the top grid value leaves more than half the budget."""
    grid, weak_grid = np.asarray(grid, float), np.asarray(weak_grid, float)
    G, J = len(grid), len(weak_grid)
    for name, arr, cols in (("rest_core", rest_core, G), ("rest_weak", rest_weak, J), ("touch_core", touch_core, G),
                            ("touch_weak", touch_weak, J)):
        if arr.ndim != 2 or arr.shape[1] != cols:
            raise ValueError(f"budget_rule: {name} {arr.shape}, expected (frames, {cols})")
    if rest_core.shape[0] != rest_weak.shape[0] or touch_core.shape[0] != touch_weak.shape[0]:
        raise ValueError("budget_rule: core and weak rows of the same frames differ in number")
    if not (0 <= budget < 1):
        raise ValueError(f"budget_rule: budget {budget}; expected a share of rest frames in [0, 1)")
    R, T = rest_core.shape[0], max(touch_core.shape[0], 1)
    allowed = int(np.floor(budget * R + 1e-9))
    ok = np.flatnonzero(rest_core.sum(axis=0) <= int(np.floor(budget / 2 * R + 1e-9)))
    if not len(ok):
        return None
    k = int(ok[0])
    base = rest_core[:, k]
    options = [(None, None)]                               # the strong threshold alone
    for j in range(J):
        if weak_grid[j] >= grid[k]:
            continue
        vals = np.sort(rest_weak[~base, j])[::-1]
        a = allowed - int(base.sum())                      # phantoms the weak rule may add
        m = float(np.ceil(vals[a] * 1e5 + 1e-6) / 1e5) if a < len(vals) else 0.0   # just above the (a+1)-th largest
        options.append((j, max(m, floor_n)))
    best, best_key = None, None
    for j, m in options:
        hit = touch_core[:, k] if j is None else touch_core[:, k] | (touch_weak[:, j] >= m)
        ph = base if j is None else base | (rest_weak[:, j] >= m)
        key = (int(hit.sum()), J if j is None else j)      # the rule off is the strictest
        if best_key is None or key > best_key:
            best_key = key
            best = {"k": k, "j": j, "threshold_n": float(grid[k]),
                    "weak_threshold_n": None if j is None else float(weak_grid[j]),
                    "min_total_n": None if j is None else float(m),
                    "detected_fraction": float(hit.sum() / T), "rest_fraction": float(ph.sum() / max(R, 1))}
    return best


def _contact_detected(sweeps: list[dict], k: int) -> float | None:
    """Share of the sweeps' contact frames (|F| > contact_n) with a core above grid[k]."""
    n = sum(s["contact_frames"] for s in sweeps)
    return float(sum(s["contact_with_core"][k] for s in sweeps) / n) if n else None


def choose_budget(sweeps: list[dict], cfg: ThresholdConfig) -> dict:
    """`choose` with cfg.rest_budget > 0: the contact settings from `budget_rule` on the sweeps' frames."""
    def rows(key, cols):
        parts = [s[key] for s in sweeps if len(s.get(key, ()))]
        return np.concatenate(parts) if parts else np.zeros((0, cols), bool if key.endswith("core") else float)
    G, J = len(cfg.grid), len(cfg.weak_grid)
    rc, rw, tc, tw = rows("rest_core", G), rows("rest_weak", J), rows("touch_core", G), rows("touch_weak", J)
    measured = {"rule": f"no margin: the lowest grid value with at most {50 * cfg.rest_budget:.3g} % of the rest frames "
                        f"(|F| < {cfg.rest_n} N, none >= {cfg.rest_touch_n} N within ± {cfg.rest_guard_s} s) holding a "
                        f"core, then the weak rule detecting the most frames with measured |F| >= {cfg.detect_n} N with "
                        f"at most {100 * cfg.rest_budget:.3g} % holding one", "rest_budget": cfg.rest_budget, "grid_n": list(cfg.grid), "weak_grid_n": list(cfg.weak_grid),
                "rest_frames": int(rc.shape[0]), "touch_frames": int(tc.shape[0]),
                "sessions": [Path(s["session"]).name for s in sweeps]}
    best = budget_rule(rc, rw, tc, tw, cfg.grid, cfg.weak_grid, cfg.rest_budget, cfg.min_total_floor_n)
    if best is None:
        log.warning("contact threshold: every grid value up to %g N leaves more than %.3g %% of the rest frames "
                    "with a core; no threshold recorded", cfg.grid[-1], 100 * cfg.rest_budget)
        return {"threshold_n": None, "weak_threshold_n": None, "min_total_n": None, "support_radius_px": None,
                "support_floor_n": None, "merge_n": None, "split_dip": None, "measured": measured}
    measured.update(touch_detected_fraction=round(best["detected_fraction"], 5),
                    rest_with_core_fraction=round(best["rest_fraction"], 5),
                    contact_detected_fraction=_contact_detected(sweeps, best["k"]),
                    detected_at_n=best["threshold_n"])
    return {"threshold_n": best["threshold_n"], "weak_threshold_n": best["weak_threshold_n"],
            "min_total_n": best["min_total_n"], "measured": measured}


def _load(package_dir, tare: bool | None):
    """The package, its tare set in memory when `tare` is given (what the sweep's pipeline then runs)."""
    from ...runtime.stages.model import load_package

    package = load_package(package_dir)
    if tare is not None:
        package.manifest.setdefault("runtime", {})["tare"] = bool(tare)
    return package


def record(package_dir: Path, result: dict, tare: bool | None = None) -> None:
    """Write the result into the manifest (atomic): the contact settings, by ContactConfig's own field
    names, under runtime.contacts; how they were measured under runtime.measured; the tare they were
    measured with under runtime.tare when given."""
    from .package import update_manifest

    contacts = {k: v for k, v in result.items() if k != "measured"}

    def change(man):
        rt = man.setdefault("runtime", {})
        rt.setdefault("contacts", {}).update(contacts)
        rt["measured"] = result.get("measured", {})
        if tare is not None:
            rt["tare"] = bool(tare)
    update_manifest(package_dir, change)


def measure(package_dir, sessions: list[tuple], cfg: ThresholdConfig = ThresholdConfig(), write: bool = True,
            command: str | None = None, tare: bool | None = None) -> dict:
    """sessions: [(session_dir, Calibration)]; `command` is recorded with the measurement; `tare`: measure
    with the runtime's tare on/off (None: the package's own) and record it."""
    package = _load(package_dir, tare)
    sweeps = []
    for path, cal in sessions:
        sweeps.append(sweep_session(path, package, cal, cfg))
        log.info("contact threshold sweep %s: %d rest / %d contact frames", Path(path).name,
                 sweeps[-1]["rest_frames"], sweeps[-1]["contact_frames"])
    out = choose(sweeps, cfg)
    if command:
        out["measured"]["command"] = command
    if out["threshold_n"] is not None:
        log.info("contact threshold of %s: %.5f N (contact frames with a core: %.1f %%)", Path(package_dir).name,
                 out["threshold_n"], 100 * (out["measured"]["contact_detected_fraction"] or 0))
    if write:
        record(package_dir, out, tare)
    return out


def measure_split(package_dir, sessions: list[tuple], cfg: ThresholdConfig = ThresholdConfig(), write: bool = True,
                  command: str | None = None, tare: bool | None = None) -> dict:
    """Only the splitting (support.choose_split), with every other contact setting as the package has it:
    on these sessions' single- and two-contact frames. Written into the manifest's runtime.contacts
    (split_dip) and runtime.measured (the split_* keys, beside the rest of the measurement); `tare` as in
    `measure`."""
    from ..scoring import contact_config
    from .package import update_manifest

    package = _load(package_dir, tare)
    sweeps = [sweep_session(path, package, cal, cfg) for path, cal in sessions]
    samples, cals, two, two_cals = _contact_frames(sweeps)
    out = choose_split(samples, cals, two, two_cals, contact_config(package), cfg.support)
    out["measured"].update(split_sessions=[Path(s["session"]).name for s in sweeps], split_single_frames=len(samples),
                           split_two_frames=len(two), **({"split_command": command} if command else {}))
    if write:
        def change(man):
            rt = man.setdefault("runtime", {})
            rt.setdefault("contacts", {})["split_dip"] = out["split_dip"]
            rt.setdefault("measured", {}).update(out["measured"])
            if tare is not None:
                rt["tare"] = bool(tare)
        update_manifest(package_dir, change)
    return out


CHECK_BANDS = ((0.1, 0.3), (0.3, 0.5), (0.5, 1.0), (1.0, float("inf")))


def check(package_dir, sessions: list[tuple], cfg: ThresholdConfig = ThresholdConfig(), tare: bool | None = None) -> dict:
    """The package's detection (its manifest's values) on other sessions, e.g. held-out ones: per
    measured |F| band the frames with a core by the strong threshold alone and with the light-touch
    rule, and the rest frames (`rest_frames`) with a core. Same frames and fields for both."""
    from ...contracts.session import load_session
    from ...runtime.offline import replay_session
    from ...runtime.stages.contacts import light_cores, pixel_forces
    from ..scoring import contact_config, measured_at

    package = _load(package_dir, tare)
    cc = contact_config(package)
    fm, strong, rule, at_rest = [], [], [], []
    for path, cal in sessions:
        ses = load_session(path)
        frames = ses.table("frames")
        meas = measured_at(ses, frames[:, 0])
        rest_here = rest_frames(frames[:, 0], _max_force(meas), cfg)
        for i, res in enumerate(replay_session(ses, package, cal, precision="int8", threads=1)):
            if res.fields is None:
                continue
            at_rest.append(rest_here[i])
            fp = pixel_forces(res.fields, cal.pixel_area)
            mag = np.where(cal.mask, np.sqrt((fp ** 2).sum(axis=0)), 0.0)
            s = _has_core(mag, cc.threshold_n, cc.min_pixels)
            light = light_cores(fp, mag, cal.mask, (mag > cc.threshold_n) & cal.mask, cc)
            fm.append(max(np.linalg.norm(meas[k]["force"][i]) for k in meas))
            strong.append(s)
            rule.append(s or (light is not None and _has_core(light.astype(float), 0.5, cc.min_pixels)))
        log.info("check %s: %d frames", Path(path).name, len(fm))
    fm, strong, rule, rest = np.array(fm), np.array(strong), np.array(rule), np.array(at_rest, bool)
    bands = [{"band_n": [lo, hi if np.isfinite(hi) else None], "frames": int(((fm > lo) & (fm <= hi)).sum()),
              "strong_only": float(strong[(fm > lo) & (fm <= hi)].mean()) if ((fm > lo) & (fm <= hi)).any() else None,
              "with_rule": float(rule[(fm > lo) & (fm <= hi)].mean()) if ((fm > lo) & (fm <= hi)).any() else None}
             for lo, hi in CHECK_BANDS]
    return {"package": str(package_dir), "contacts": {"threshold_n": cc.threshold_n, "weak_threshold_n": cc.weak_threshold_n,
                                                      "min_total_n": cc.min_total_n},
            "sessions": [Path(p).name for p, _ in sessions], "frames": int(len(fm)), "rest_frames": int(rest.sum()),
            "rest_with_core": {"strong_only": int(strong[rest].sum()), "with_rule": int(rule[rest].sum())},
            "bands": bands}


def fixed_support(package_dir) -> float | None:
    """The package's cluster reach when its build fixed it (support floor 0 N and a "fixed by the build" rule),
    else None: a re-measurement keeps what the build chose instead of resetting it to the runtime default."""
    man = json.loads((Path(package_dir) / "manifest.json").read_text())
    rt = man.get("runtime") or {}
    c, m = rt.get("contacts") or {}, rt.get("measured") or {}
    if c.get("support_radius_px") and c.get("support_floor_n") == 0.0 and \
            str(m.get("support_rule", "")).startswith("fixed by the build"):
        return float(c["support_radius_px"])
    return None


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--package", required=True, help="model package folder")
    ap.add_argument("--session", nargs="+", action="extend", default=[], metavar="SESSION_DIR:STORE_DIR",
                    help="a training session and the calibration store holding its unit")
    ap.add_argument("--units", help="or every recorded session of a protocol unit set (`train units record SET`), "
                                    "each unit with its calibration: validation (the sealed set is refused)")
    ap.add_argument("--units-root", help="where recorded sets live (default <cache>/units)")
    ap.add_argument("--protocol", help="protocol file of --units (default tools/train/protocol.toml)")
    ap.add_argument("--rest-budget", type=float, default=0.0, metavar="SHARE",
                    help="choose the threshold, weak threshold and min_total_n together on these (held-out) sessions: "
                         "the most frames >= 0.2 N detected with at most SHARE of the rest frames holding a core "
                         "(e.g. 0.005); 0 = the training-session rule (no core on any rest frame, x 4/3)")
    ap.add_argument("--write", action="store_true", help="record the result in the package's manifest")
    ap.add_argument("--tare", choices=("on", "off"),
                    help="measure with the runtime's tare on or off and record it with the result (default: the "
                         "package's own)")
    ap.add_argument("--support", action="store_true",
                    help="also measure a farther cluster support (off by default: docs/model_package.md 'Support')")
    ap.add_argument("--support-px", type=float, help="a fixed cluster support radius (px, floor 0 N) instead")
    ap.add_argument("--check", action="store_true",
                    help="measure nothing: report the package's own detection on these (e.g. held-out) sessions")
    ap.add_argument("--split-only", action="store_true",
                    help="choose only the splitting of joined presses (split_dip), every other setting as the package has it")


def run(args: argparse.Namespace) -> int:
    from ...contracts.errors import TensorTouchError
    from ...contracts.session import load_session
    from ...contracts.store import CalibrationStore

    if not 0 <= args.rest_budget < 1:
        raise TensorTouchError(f"--rest-budget {args.rest_budget}: expected a share of rest frames in [0, 1)")
    if not args.session and not args.units:
        raise TensorTouchError("train threshold: give --session SESSION_DIR:STORE_DIR ... or --units SET")
    pairs = []
    if args.units:
        from .protocol import load_protocol
        from .units import unit_targets, units_root

        if args.units == "sealed":
            raise TensorTouchError("train threshold: --units sealed: the sealed set is never used for a choice")
        pairs += [(path, cal) for _, path, cal in unit_targets(load_protocol(args.protocol), args.units,
                                                               units_root(args.units_root), check_whole=False)]
    for item in args.session:
        sdir, _, store = item.partition(":")
        if not store:
            raise TensorTouchError(f"--session {item!r}: expected SESSION_DIR:STORE_DIR")
        pairs.append((sdir, CalibrationStore(store).load(load_session(sdir).sensor_id)))
    tare = None if args.tare is None else args.tare == "on"
    if args.check:
        print(json.dumps(check(args.package, pairs, tare=tare), indent=1))
        return 0
    cmd = args.command_line
    if args.split_only:
        print(json.dumps(measure_split(args.package, pairs, ThresholdConfig(), write=args.write, command=cmd, tare=tare),
                         indent=1))
        return 0
    support_px = args.support_px
    if support_px is None and not args.support:    # keep a reach the build fixed (BuildConfig.support_px)
        support_px = fixed_support(args.package)
    cfg = ThresholdConfig(measure_support=args.support, support_px=support_px, rest_budget=args.rest_budget)
    print(json.dumps(measure(args.package, pairs, cfg, write=args.write, command=cmd, tare=tare), indent=1))
    return 0

