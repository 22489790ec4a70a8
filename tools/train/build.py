"""The build folder of `tensortouch train all --recipe NAME`: its configuration, paths and stamps.

    (0) sessions → (1) keypoints → (2) FE labels → (3) 2D–3D correspondence → (4) sim-to-real ratios
    → (5) dataset → (6) [MAE pretrain] + fit → (7) export → exported_models/<name>/ → (8) evaluation

Every stage writes under `<cache>/train/<build>/` (contracts.paths.cache_dir()) and finishes with a
stamp file `stamps/<stage>.json` (config key, outputs, wall time); a rerun skips stamped stages whose
configuration is unchanged, and the long stages (recording, fitting) resume inside themselves.
The build configuration is one dataclass (`BuildConfig`); a recipe (tools/train/recipe.py) gives its fields.
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ...contracts.files import atomic_write_json

log = logging.getLogger(__name__)

STAGES = ("sessions", "keypoints", "fe", "correspondence", "simreal", "dataset", "pretrain", "fit",
          "export", "evaluate")


@dataclass
class SessionSpec:
    serial: str
    seed: int
    pokes: int
    frames: str = "mjpg"          # ffv1 | mjpg | png
    quality: int = 80             # MJPG quality (the shipped demo uses 65)
    # the plan's ranges (tools.twin.trajectory.TrajectoryConfig fields), e.g. {"kinds": ["slide"],
    # "slide": [0.8, 1.6]}: sessions rich in one motion; empty = the twin's defaults
    trajectory: dict = field(default_factory=dict)
    # the twin's world (tools/twin/world.py): "label" = the labels' own physics and an ideal rig (the
    # ceiling); "rig" = a world that differs from the label solver, estimated as a rig would (rig_estimate)
    world: str = "label"
    # WorldConfig fields that differ from its defaults, world "rig" only (e.g. {"c10": 0, "c20": 0, "c30": 0}:
    # the unit's stiffness nominal; the other differences as drawn): one difference switched off at a time
    # is how the label budget gives each its share (docs/train.md)
    world_params: dict = field(default_factory=dict)
    # this session's twin physics when not the build's (BuildConfig.physics): a distilled build
    # (BuildConfig.teacher) needs frames only, so some of its sessions may use the analytic
    # "hertz-fallback" (seconds of CPU) instead of FE (minutes per poke); "" = the build's
    physics: str = ""

    @property
    def name(self) -> str:
        return f"{self.serial}-s{self.seed}"

    def record_config(self, physics: str, size: int):
        """The twin RecordConfig that records (and, for labels, re-plans) this session."""
        from ..twin.record import RecordConfig
        from ..twin.trajectory import with_ranges

        rcfg = RecordConfig(serial=self.serial, pokes=self.pokes, seed=self.seed, physics=self.physics or physics,
                            frame_format=self.frames, mjpg_quality=self.quality, model_size=size, world=self.world,
                            world_params=dict(self.world_params) or None)
        rcfg.trajectory = with_ranges(rcfg.trajectory, self.trajectory, f"session {self.name} trajectory")
        return rcfg


def _train_sessions() -> list[SessionSpec]:
    # seeds chosen so the 4 indenters of the twin's set all appear (sphere R5/R3, flat R4, cylinder R3)
    q = (65, 80, 95, 65, 80, 95)
    return [SessionSpec(f"TWIN-T{i + 1:02d}", s, 5, "mjpg", q[i]) for i, s in enumerate((101, 102, 103, 107, 108, 112))]


def _heldout_sessions() -> list[SessionSpec]:
    return [SessionSpec("TWIN-H01", 201, 5, "mjpg", 65)]


@dataclass
class BuildConfig:
    name: str = "hiera-qup-128"                   # package name in exported_models/
    build: str = "main"                           # folder under <cache>/train/
    size: int = 128                               # model input = calibration table size
    train: list = field(default_factory=_train_sessions)
    heldout: list = field(default_factory=_heldout_sessions)
    physics: str = "fe"                           # twin physics (fe; hertz-fallback only for smoke tests)
    fe: str = "resolve"                           # stage 2: resolve (FE from measured keypoints) | twin (twin's solves)
    max_bulk_ratio: float = 5.0                   # stage 2 resolve: locking cap of the label solves (tools.fe SolverSettings)
    tables: str = "gpr"                           # θ/φ tables of the targets: gpr (stage 3 pokes) | truth (twin)
    crop: str = "nominal"                         # stage 3's crop radius: nominal (the design's rim radius) | rim (the
                                                  # unit's rim measured in its calibration rest frames, as `calib init` does)
    contact_stride: int = 2                       # every n-th in-contact frame becomes a sample
    label_frames: str = "interpolated"            # fe = "resolve": labels at every frame of an FE span | "checked" | "fe" | "keypoint"
    label_sigma: str = "pose"                     # a label between FE frames is placed by the mocap pose | "pose+ft"
                                                  # (pose and F/T force: labels 1.5–3× nearer the F/T, docs/train.md)
    # stage 1 dual threshold. The seed's 1.5 N / 1.1 N (KeypointConfig) suit its stiffer gel; the twin's gel
    # peaks at 0.2–5 N per poke, so 1.5 N dropped 15 of 35 pokes (their frames then only "busy", unlabelled).
    # 0.5 N is 25× the F/T noise (0.02 N); detach keeps the seed's ratio 1.1/1.5.
    contact_force_n: float = 0.5
    detach_force_n: float = 0.37
    rest_fraction: float = 0.15                   # rest (no contact) samples relative to contact samples
    val_fraction: float = 0.1
    arch: str = "hiera_qup"
    pretrain_epochs: int = 8                      # MAE pretraining epochs (0: skip)
    epochs: int = 30
    batch: int = 4
    lr: float = 1e-3
    fg_weight: float = 20.0                       # foreground-weighted L1 (FitConfig.fg_weight)
    force_weight: float = 0.0                     # total-force loss term per N (FitConfig.force_weight)
    light_weight: float = 0.0                     # light-contact sample weight exponent (FitConfig.light_weight)
    pixel_force_weight: float = 0.0               # per-pixel force term per N (FitConfig.pixel_force_weight)
    measured_force_weight: float = 0.0            # total force vs the rig's F/T per N (FitConfig.measured_force_weight;
                                                  # a distilled build: its dataset keeps the measured force per sample)
    measured_force_split: bool = False            # ... and, where two indenters press at once, each one's force on its
                                                  # side of the two (FitConfig.measured_force_split; distilled builds)
    fit_seed: int = 0                             # the fit's weight init and sample order (FitConfig.seed)
    photometric: float = 0.0                      # input jitter of LED brightness ± this (FitConfig.photometric)
    augment_crop: bool = False                    # the fit warps input and target to jittered crops: radius
                                                  # × U(1 ± crop_scale_jitter), centre ± crop_center_jitter_px
    init_from: str = ""                           # fine-tune the fit from this state dict (FitConfig.init_from)
    init_bounds: str = ""                         # the bounds init_from was trained with (FitConfig.init_bounds)
    threads: int = 2
    device: str = "auto"                          # training device auto | cpu | cuda (not in any stage key)
    fe_cluster: str = ""                          # stage 2 FE batch on this Dask scheduler (tcp://host:8786); "" = local
    quantization_samples: int = 128                # inputs that set the int8 ranges (ExportConfig)
    quantization_pick: str = "spread"              # spread over the train split | "first" (ExportConfig)
    quantization_scheme: str = "hybrid"           # ExportConfig.scheme: hybrid | static | full (convnet: every op)
    threshold_sessions: int = 6                   # training sessions the package's contact threshold is measured on
    support_px: float = 0.0                       # a fixed cluster support radius (px, floor 0); 0 = the runtime default
    latency_runs: int = 50
    eval_contact_n: float = 1.5                   # stage 8: measured |F| above this = contact (seed §III.C)
    eval_demo: bool = True                        # also evaluate on runtime/demo (held out: own unit/plan)
    models_dir: str = ""                          # default contracts.paths.models_dir()
    figures: bool = True                          # write docs/ figures (Fig. 10/11 style) after evaluation
    # Distillation (tools/train/distill.py): with a teacher package the dataset's targets are the teacher's
    # outputs on the training sessions' frames, so stages 1–4 (keypoints, FE labels, tables, sim-to-real) are
    # skipped; each frame is also cropped `distill_copies` more times at a jittered rim (radius × U(1 ± s),
    # centre ± c px), the per-unit crop variation of the protocol's units, and labelled by the teacher there.
    teacher: str = ""                             # a model package folder ("" = FE labels)
    distill_copies: int = 0
    crop_scale_jitter: float = 0.04               # units' rims are 105.7–114.3 px against the nominal 110.09 px
    crop_center_jitter_px: float = 1.0

    @staticmethod
    def from_dict(d: dict) -> "BuildConfig":
        d = {k: v for k, v in d.items() if not k.startswith("_")}     # "_about" etc.: comments in recipes
        for k in ("train", "heldout"):
            if k in d:
                d[k] = [s if isinstance(s, SessionSpec) else SessionSpec(**s) for s in d[k]]
        return BuildConfig(**d)

    def to_dict(self) -> dict:
        d = json.loads(json.dumps(asdict(self)))
        for k in ("train", "heldout"):      # default plans stay out (stage keys of older builds stay valid)
            for spec in d.get(k) or []:
                if not spec.get("trajectory"):
                    spec.pop("trajectory", None)
                if not spec.get("physics"):
                    spec.pop("physics", None)
                if spec.get("world") == "label":
                    spec.pop("world")
                if not spec.get("world_params"):
                    spec.pop("world_params", None)
        return d


def stage_keys(cfg: BuildConfig) -> dict[str, str]:
    """Config key per stage: the fields that stage (and the stages before it) depend on."""
    d = cfg.to_dict()
    deps = {"sessions": ["train", "heldout", "physics", "size"],
            "keypoints": ["contact_force_n", "detach_force_n"], "fe": ["fe", "max_bulk_ratio"], "correspondence": ["tables", "crop"], "simreal": [],
            "dataset": ["tables", "contact_stride", "label_frames", "label_sigma", "rest_fraction", "val_fraction",
                        "teacher", "distill_copies", "crop_scale_jitter", "crop_center_jitter_px", "measured_force_weight",
                        "measured_force_split"],
            "pretrain": ["arch", "pretrain_epochs", "batch", "lr"],
            "fit": ["arch", "epochs", "batch", "lr", "fg_weight", "force_weight", "light_weight", "pixel_force_weight",
                    "measured_force_weight", "measured_force_split", "init_from",
                    "init_bounds", "fit_seed", "photometric", "augment_crop"],
            "export": ["name", "quantization_samples", "quantization_pick", "threshold_sessions", "support_px",
                       "quantization_scheme"],
            "evaluate": ["eval_demo", "eval_contact_n"]}
    # in the key only when not these values (older stamps stay valid; builds before the thresholds were
    # configurable ran stage 1 with the seed's 1.5 / 1.1 N)
    optional = {"label_frames": "interpolated", "label_sigma": "pose", "fit_seed": 0, "photometric": 0.0, "augment_crop": False, "force_weight": 0.0, "light_weight": 0.0, "pixel_force_weight": 0.0, "measured_force_weight": 0.0, "measured_force_split": False, "init_from": "", "init_bounds": "", "contact_force_n": 1.5,
                "detach_force_n": 1.1, "max_bulk_ratio": 5.0, "threshold_sessions": 6, "quantization_pick": "first", "support_px": 0.0,
                "crop": "nominal", "quantization_scheme": "hybrid", "teacher": "", "distill_copies": 0, "crop_scale_jitter": 0.04,
                "crop_center_jitter_px": 1.0}
    keys, acc = {}, {}
    for st in STAGES:
        for k in deps[st]:
            if k in optional and d[k] == optional[k]:
                continue
            acc[k] = d[k]
        keys[st] = hashlib.sha256(json.dumps(acc, sort_keys=True).encode()).hexdigest()[:16]
    return keys


class Build:
    """Paths and stamps of one build folder."""

    def __init__(self, cfg: BuildConfig, root: Path | None = None, command: str = "", step: str = ""):
        from ...contracts.names import confined
        from ...contracts.paths import cache_dir

        self.cfg = cfg
        self.root = Path(root) if root else confined(cache_dir() / "train", cfg.build, "build name")
        self.command = command
        self.step = step          # a recipe step: the stages from pretrain on keep one stamp per step
        self.keys = stage_keys(cfg)
        for sub in ("stamps", "sessions", "keypoints", "fe", "correspondence", "simreal", "runs", "eval"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)

    # -- locations -------------------------------------------------------------------------
    @property
    def store_root(self) -> Path:
        """The build's own calibration store (true + GPR calibrations of the twin units)."""
        return self.root / "calibration_store"

    @property
    def dataset(self) -> Path:
        return self.root / "dataset"

    def session(self, spec: SessionSpec) -> Path:
        from ...contracts.names import confined

        return confined(self.root / "sessions", spec.name, "session (serial-seed)")

    def all_sessions(self) -> list[SessionSpec]:
        return list(self.cfg.train) + list(self.cfg.heldout)

    # -- stamps ----------------------------------------------------------------------------
    def stamp_path(self, stage: str) -> Path:
        if self.step and STAGES.index(stage) >= STAGES.index("pretrain"):
            return self.root / "stamps" / f"{stage}@{self.step}.json"
        return self.root / "stamps" / f"{stage}.json"

    def done(self, stage: str) -> bool:
        p = self.stamp_path(stage)
        if not p.is_file():
            return False
        try:
            doc = json.loads(p.read_text())
        except ValueError:
            return False
        if doc.get("key") != self.keys[stage]:
            return False
        if stage == "export":   # the package may have been deleted or replaced since
            man = Path(doc.get("package", "")) / "manifest.json"
            try:
                return json.loads(man.read_text())["training"]["data_hash"] == self.read_stamp("dataset").get("data_hash")
            except (OSError, ValueError, KeyError):
                return False
        return True

    def stamp(self, stage: str, info: dict, seconds: float) -> None:
        doc = {"stage": stage, "key": self.keys[stage], "seconds": round(seconds, 2),
               "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **info}
        atomic_write_json(self.stamp_path(stage), doc)

    def read_stamp(self, stage: str) -> dict:
        p = self.stamp_path(stage)
        return json.loads(p.read_text()) if p.is_file() else {}






def tiny_config(name: str = "tiny-smoke", build: str = "tiny") -> BuildConfig:
    """The `tiny` recipe (tools/train/recipes/tiny.toml) as one BuildConfig: the minutes-long smoke run of
    the whole chain for tests and CI (analytic twin physics — never the physics of a shipped model)."""
    from .recipe import load_recipe

    recipe = load_recipe("tiny")
    cfg = config_from_dict(recipe.config(recipe.steps()[-1]), recipe.source)
    cfg.name, cfg.build = name, build
    return cfg


def config_from_dict(d: dict, where: str) -> BuildConfig:
    """BuildConfig from a recipe step's fields, checked before anything runs: unknown fields, every
    field by its type in BuildConfig / SessionSpec and its range in BUILD_LIMITS / SESSION_LIMITS,
    the words of CHOICES, each session's trajectory ranges, its units against the evaluation protocol's
    sets (tools/train/protocol.py). Any problem is one RecipeError line."""
    from dataclasses import fields

    from ...contracts.schema import SchemaError, check_depth, check_fields
    from .recipe import RecipeError

    if not isinstance(d, dict):
        raise RecipeError(f"{where}: the build fields must be a table, got {type(d).__name__}")
    known = {f.name for f in fields(BuildConfig)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise RecipeError(f"{where}: unknown build field(s) {unknown}; expected some of {sorted(known)}")
    spec_keys = {f.name for f in fields(SessionSpec)}
    from .protocol import ProtocolError, check_recipe_sessions, expand_recipe_sessions, load_protocol

    try:    # sessions named by a protocol set (tools/train/protocol.py), then checked as any others
        protocol = load_protocol()
        d = {**d, **expand_recipe_sessions(protocol, {k: d[k] for k in ("train", "heldout") if k in d}, where)}
    except ProtocolError as exc:
        raise RecipeError(str(exc)) from None
    try:
        check_depth(d, where)
        for k, allowed in CHOICES.items():
            if k in d and d[k] not in allowed:
                raise SchemaError(f"{k} = {d[k]!r}; expected one of {', '.join(allowed)}")
        check_fields(BuildConfig, {k: v for k, v in d.items() if k not in ("train", "heldout")}, "", BUILD_LIMITS)
        for k in ("train", "heldout"):
            specs = d.get(k) or []
            if not isinstance(specs, list):
                raise SchemaError(f"sessions.{k} is {specs!r}, expected a list of tables")
            for i, spec in enumerate(specs):
                if isinstance(spec, SessionSpec):
                    continue
                if not isinstance(spec, dict) or not {"serial", "seed", "pokes"} <= set(spec) or set(spec) - spec_keys:
                    got = sorted(spec) if isinstance(spec, dict) else repr(spec)
                    raise SchemaError(f"sessions.{k}[{i}] needs serial, seed, pokes (and optionally "
                                      f"{sorted(spec_keys - {'serial', 'seed', 'pokes'})}), got {got}")
                check_fields(SessionSpec, spec, f"sessions.{k}[{i}]", SESSION_LIMITS)
                if spec.get("trajectory"):
                    _check_trajectory(spec["trajectory"], f"sessions.{k}[{i}].trajectory")
    except SchemaError as exc:
        raise RecipeError(f"{where}: {exc}") from None
    try:    # the evaluation protocol's unit sets: train units train, validation units are held out, sealed unseen
        check_recipe_sessions(protocol, {k: d.get(k) for k in ("train", "heldout")}, where)
    except ProtocolError as exc:
        raise RecipeError(str(exc)) from None
    return BuildConfig.from_dict(d)


def _check_trajectory(ranges: dict, path: str) -> None:
    """A session's plan ranges: TrajectoryConfig fields (tools/twin/trajectory.py), finite numbers."""
    from ...contracts.schema import Range, SchemaError, number
    from ..twin.trajectory import TrajectoryConfig, with_ranges

    try:
        with_ranges(TrajectoryConfig(), ranges, path)
    except ValueError as exc:
        raise SchemaError(str(exc)) from None
    for k, v in ranges.items():
        for i, x in enumerate(v if isinstance(v, (list, tuple)) else [v]):
            if not isinstance(x, str):
                number(x, f"{path}.{k}" + (f"[{i}]" if isinstance(v, (list, tuple)) else ""), Range(0, 1000),
                       what="a plan range (mm, s, rad or a probability)")


# build fields that take one of a few words
CHOICES = {"fe": ("resolve", "twin"), "tables": ("gpr", "truth"), "crop": ("nominal", "rim"), "label_frames": ("interpolated", "checked", "fe", "keypoint"),
           "label_sigma": ("pose+ft", "pose"),
           "physics": ("fe", "hertz-fallback"), "arch": ("hiera_qup", "unet", "vit", "convnet"),
           "device": ("auto", "cpu", "cuda"), "quantization_pick": ("spread", "first"),
           "quantization_scheme": ("hybrid", "static", "full")}


def _ranges():
    from ...contracts.schema import SEED_RANGE, Range

    def above0(hi):
        return Range(0, hi, lo_open=True)

    build = {"size": Range(16, 1024), "max_bulk_ratio": Range(0, 1000), "contact_stride": Range(1, 10_000),
             "contact_force_n": above0(1000), "detach_force_n": above0(1000), "rest_fraction": Range(0, 100),
             "val_fraction": Range(0, 0.9), "pretrain_epochs": Range(0, 100_000), "epochs": Range(1, 100_000),
             "batch": Range(1, 65_536), "lr": above0(10), "fg_weight": Range(0, 1e6), "force_weight": Range(0, 1e6),
             "pixel_force_weight": Range(0, 1e6), "measured_force_weight": Range(0, 1e6), "light_weight": Range(0, 10), "fit_seed": Range(*SEED_RANGE), "photometric": Range(0, 1),
             "threads": Range(1, 1024), "quantization_samples": Range(1, 1_000_000),
             "threshold_sessions": Range(1, 10_000), "support_px": Range(0, 4096), "latency_runs": Range(1, 1_000_000),
             "eval_contact_n": above0(1000), "distill_copies": Range(0, 100), "crop_scale_jitter": Range(0, 0.5),
             "crop_center_jitter_px": Range(0, 100)}
    session = {"seed": Range(*SEED_RANGE), "pokes": Range(1, 10_000), "quality": Range(1, 100),
               "frames": ("ffv1", "mjpg", "png"), "physics": ("", "fe", "hertz-fallback")}
    return build, session


# the declared range of every numeric build and session field (contracts/schema.py Range, inclusive)
BUILD_LIMITS, SESSION_LIMITS = _ranges()





def recipe_build(ref: str, sets: list[str] | tuple = (), root: str | Path | None = None) -> Build:
    """The build folder of a recipe's last step, for the tools that read a build (budget, crosseval,
    resolve-check): its sessions, calibrations and dataset."""
    from .recipe import load_recipe

    recipe = load_recipe(ref, sets)
    steps = recipe.steps()
    cfg = config_from_dict(recipe.config(steps[-1]), recipe.source)
    cfg.build = recipe.name
    return Build(cfg, Path(root) if root else None, step=steps[-1].name if len(steps) > 1 else "")


def unit_meta(b, serial: str) -> dict:
    """The unit's current calibration metadata (gel design geometry `gel`, camera) — what a real rig's
    calibration store holds before any training stage runs."""
    from ...contracts.store import CalibrationStore

    return CalibrationStore(b.store_root).load(serial).meta


def unit_calibration(b, serial: str):
    """The calibration the dataset and evaluation use for a unit (stage 3's choice)."""
    from ...contracts.store import CalibrationStore

    info = json.loads((b.root / "correspondence" / f"{serial}.json").read_text())
    return CalibrationStore(b.store_root).load(serial, info["version"])


def pretrain_dir(b) -> Path:
    """Run folder of the MAE pretraining (one per configuration, so a changed budget starts anew)."""
    return b.root / "runs" / f"pretrain-{b.keys['pretrain']}"


def fit_dir(b) -> Path:
    return b.root / "runs" / f"fit-{b.keys['fit']}"
