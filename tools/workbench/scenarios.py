"""Twin sessions for the workbench's tests, benchmark and walkthrough (recorded once, cached).

Every scenario uses one twin unit, the same two indentation modules (so a contact law fitted on a
calibration session applies), the analytic physics backend (fast; the FE backend works the same
way, slower) and few camera frames (brightness needs only a slow rate). The rig's temperature
drifts faster than the default so temperature-dependent physics is observable in a short session.
This module is the only workbench file that imports the twin: diagnosis sees sessions only.
"""
from __future__ import annotations

import hashlib
import json
import logging
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

from ...contracts import paths

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Scenario:
    seed: int
    pokes: int = 20
    effects: tuple = ()                    # ((name, {param: value}), ...) switched on in truth
    unit: str = "TWIN-WB01"
    indenters: tuple = ("sphere5", "flat4")
    kinds: tuple = ("poke", "press", "slide", "twist")
    physics: str = "hertz-fallback"
    fps: float = 2.0
    temperature_drift: float = 0.05        # degC/s
    model_size: int = 64
    extra: dict = field(default_factory=dict)  # {"trajectory": {field: value}} overrides the plan's ranges

    def key(self) -> str:
        d = {k: v for k, v in self.__dict__.items()}
        if self.kinds == Scenario.kinds:  # keys of sessions recorded before `kinds` existed
            d.pop("kinds")
        d["effects"] = [[n, dict(p)] for n, p in self.effects]
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:14]


def root() -> Path:
    return paths.cache_dir() / "workbench" / "twin"


def store_root(unit: str = "TWIN-WB01", model_size: int = 64) -> Path:
    """A calibration store holding the unit's true calibration (written once)."""
    from ...contracts.store import CalibrationStore
    from ..twin.unit import TwinUnit, write_true_calibration

    folder = root() / f"store-{unit}-{model_size}"
    if not CalibrationStore(folder).versions(unit):
        write_true_calibration(TwinUnit(unit), folder, model_size)
    return folder


def fresh_store(dest: Path, unit: str = "TWIN-WB01", model_size: int = 64) -> Path:
    """A private copy of the unit's store (tests and the bench add effects to it)."""
    src = store_root(unit, model_size)
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(src, dest)
    return dest


def record(sc: Scenario, progress=None) -> Path:
    """The scenario's session folder (recorded on first use)."""
    from ..twin.record import RecordConfig, Recorder
    from ..twin.trajectory import with_ranges

    out = root() / f"s-{sc.key()}"
    if (out / "session.json").is_file():
        return out
    cfg = RecordConfig(serial=sc.unit, pokes=sc.pokes, seed=sc.seed,
                       effects=[(n, dict(p)) for n, p in sc.effects], physics=sc.physics,
                       frame_format="mjpg", model_size=sc.model_size)
    cfg.rig = replace(cfg.rig, camera_fps=sc.fps, temperature_drift_c_per_s=sc.temperature_drift)
    cfg.trajectory = with_ranges(replace(cfg.trajectory, indenters=tuple(sc.indenters), kinds=tuple(sc.kinds)),
                                 sc.extra.get("trajectory"), f"scenario {sc.key()} extra.trajectory")
    out.parent.mkdir(parents=True, exist_ok=True)
    log.info("recording twin scenario %s -> %s", sc, out)
    Recorder(cfg, out, progress=progress).run()
    return out


# ----- the deployed-network path: FE physics (what the network was trained on), 30 fps frames at
# the shipped model's size (128 px calibration tables), a unit outside the network's training set.
NET_CALIB_SEED = 100          # calibration session (no hidden physics): the network's nominal correction
NET_TEST_SEED = 101           # the plan shared by the hidden-effect sessions (FE solves cached per poke)


def net_scenario(seed: int, pokes: int = 16, effects: tuple = (), fps: float = 30.0, **kw) -> Scenario:
    """A twin scenario for the network path (FE physics, frames at `fps`, 128 px calibration)."""
    return Scenario(seed, pokes=pokes, effects=effects, physics="fe", fps=fps, model_size=128, **kw)
