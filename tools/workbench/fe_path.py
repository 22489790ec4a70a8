"""The FE model path: the force the FE solves at a session's own measured keypoints predict, through
the training recipe's stage-2 resolve (tools/train/resolve_stage.py) — the very scenarios the
recipe's labels come from, so this path's floor is the label error.

Per session: stage 1 (tools/train/keypoints.py: contact periods and keypoints from the measured
poses and F/T) -> stage 2 (`session_scenarios`: one tools.fe scenario per contact period from the
measured poses, the mounted indenters and the gel's design geometry) -> solved with tools.fe (batch
runner, shared on-disk cache: a session solved once is not solved again) or, on analytic twin units
(`physics="hertz-fallback"`), the recipe's analytic stand-in (`sources.fallback_solve`). The model
force of a row = the load of the gel on the indenter (-RF) at that row's place in its period, the
FE frame parameter σ from the measured pose alone (`resolve.frame_sigma` without the force term: the
measured force is what the model is compared with, so it may not place the frame).

Stage 1 finds contact periods from |F| with hysteresis thresholds. The recipe's (1.5 / 1.1 N, for
training labels) miss light presses: on twin sessions whose presses peak at 1.5-2 N it found 2
periods in 8 pokes, so the path compared and diagnosed a quarter of the session. The FE path
detects contact with `FEPathConfig`'s thresholds, a few times the F/T's noise, so every press the
F/T sees is solved; the rest of stage 1 (pre-contact extension, keypoints) is the recipe's.

Rows the FE does not cover (in contact but outside every solved period) get NaN; `covered_rows`
keeps the rest, so this path is compared and diagnosed on the contact periods solved (and the
contact-free rows between them).
"""
from __future__ import annotations

import hashlib
import json
import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...contracts.errors import TensorTouchError
from .table import SampleTable

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FEPathConfig:
    """Stage 1 of the FE path: contact begins above `contact_force_n` and ends below `detach_force_n`
    (|F| of the F/T; 15× and 10× the twin's F/T noise of 0.02 N); at most `max_keypoints` per
    contact period (the recipe caps its labels' at 12; 8 solve ~1.5× faster, a comparison of a
    whole session costs one solve per press, and the FE between keypoints is interpolated)."""

    contact_force_n: float = 0.3
    detach_force_n: float = 0.2
    max_keypoints: int = 8


class FEModel:
    """ForceModel of one session: FE at its measured keypoints (solved on construction)."""

    name = "fe-keypoints"

    def __init__(self, session_path, calibration_meta: dict, physics: str = "fe", session=None,
                 cfg: FEPathConfig = FEPathConfig()):
        if physics not in ("fe", "hertz-fallback"):
            raise TensorTouchError(f"FE path: physics {physics!r}, expected 'fe' or 'hertz-fallback'")
        self.session_path = Path(session_path)
        self.physics = physics
        self.periods = solve_session(self.session_path, calibration_meta, physics, session, cfg)

    def fingerprint(self) -> str:
        h = hashlib.sha256(self.physics.encode())
        for p in self.periods:
            h.update(str(p["scenario"]).encode())
        return h.hexdigest()[:16]

    def predict(self, table: SampleTable) -> np.ndarray:
        """(N, 3) -RF of the row's indenter at its σ in a solved period; 0 out of contact; NaN where no
        solved period covers a row in contact."""
        t = np.asarray(table.cols["time"], dtype=np.float64)
        series = np.asarray(table.cols["series"]).astype(int)
        depth = np.asarray(table.cols.get("mocap_depth", table.cols["depth"]))
        out = np.zeros((len(t), 3))
        covered = np.zeros(len(t), bool)
        for per in self.periods:
            times = per["times"]
            for k, slot in enumerate(per["slots"]):
                m = (series == slot) & (t >= times[0]) & (t <= times[-1])
                if not m.any():
                    continue
                sig = per["sigma"](t[m])
                load = -np.asarray(per["RF"])[:, k]
                out[m] = np.array([_interp(load, s) for s in sig])
                covered[m] = True
        out[(depth > 0) & ~covered] = np.nan
        return out


def _interp(arr, s):
    from ..train.resolve import interp_frames

    return interp_frames(arr, s)


def covered_rows(table: SampleTable, pred: np.ndarray) -> np.ndarray:
    return np.all(np.isfinite(pred), axis=1)


def take_rows(table: SampleTable, rows: np.ndarray) -> SampleTable:
    """The table's rows `rows` (bool mask or indices)."""
    n = len(table)
    return SampleTable({k: np.asarray(v)[rows] for k, v in table.cols.items()}, table.meas[rows], table.model[rows],
                       {k: np.asarray(v)[rows] for k, v in table.vec.items() if len(v) == n}, table.meta)


def solve_session(session_path: Path, calibration_meta: dict, physics: str, ses=None,
                  cfg: FEPathConfig = FEPathConfig()) -> list[dict]:
    """Stages 1-2 of the recipe on one session, solved: [{times, slots, RF (J, K, 3), sigma, scenario}].
    `ses`: the session already loaded (or changed in memory); its poses and F/T are used."""
    from ...contracts.session import load_session
    from ..train.keypoints import KeypointConfig, extract_keypoints, keypoints_doc
    from ..train.resolve import ResolveConfig, frame_sigma
    from ..train.resolve_stage import session_scenarios
    from ..train.sources import fallback_solve, fe_cache_dir, gel_of

    ses = ses or load_session(session_path, check_frames=False)
    kcfg = KeypointConfig(contact_force_n=cfg.contact_force_n, detach_force_n=cfg.detach_force_n,
                          max_keypoints=cfg.max_keypoints)
    frames = ses.table("frames") if ses.has("frames") else None
    kps = extract_keypoints(ses.table("poses"), ses.table("wrench"), frames, kcfg)
    doc = keypoints_doc(ses, kps, kcfg, str(Path(session_path).resolve()))
    with tempfile.TemporaryDirectory() as tmp:
        kp_file = Path(tmp) / "keypoints.json"
        kp_file.write_text(json.dumps(doc))
        items = session_scenarios(session_path, kp_file, calibration_meta)
        solved = [(i, ps) for i, ps, err in items if ps is not None]
        results = {}
        if physics == "hertz-fallback":
            surf = gel_of(calibration_meta)[1]
            for i, ps in solved:
                results[i] = fallback_solve(ps, surf)
        elif solved:
            from ..fe import load_result, save_scenario
            from ..fe.batch import run_batch

            cache = fe_cache_dir()
            files = []
            for i, ps in solved:
                f = Path(tmp) / f"p{i:02d}.json"
                save_scenario(ps.scenario, f)
                files.append(str(f))
            run_batch(files, cache, workers=ResolveConfig().workers)
            for i, ps in solved:
                path = cache / f"{ps.scenario.hash()}.npz"
                if path.is_file():
                    results[i] = load_result(path)
    from ..train.resolve import PoseTrack

    poses = ses.table("poses")
    out = []
    for i, ps in solved:
        if i not in results:
            log.warning("%s period %d: FE solve failed; its rows are left out", session_path, i)
            continue
        tracks = [PoseTrack.from_table(poses, k) for k in ps.slots]
        times = np.asarray(ps.times, dtype=np.float64)
        out.append({"times": times, "slots": list(ps.slots), "RF": np.asarray(results[i].RF, dtype=np.float64),
                    "sigma": (lambda ts, times=times, tracks=tracks: frame_sigma(ts, times, tracks)),
                    "scenario": ps.scenario.hash()})
    skipped = [err for _, ps, err in items if ps is None]
    if not out:
        raise TensorTouchError(f"{session_path}: the FE path solved no contact period"
                               + (f" ({skipped[0]})" if skipped else " (no contact period found)"))
    log.info("FE path of %s: %d of %d periods solved", session_path, len(out), len(items))
    return out
