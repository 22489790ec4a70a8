"""`tensortouch train all --recipe NAME`: the one-command build of a model package from nothing.

    (0) sessions → (1) keypoints → (2) FE labels → (3) 2D–3D correspondence → (4) sim-to-real ratios
    → (5) dataset → (6) [MAE pretrain] + fit → (7) export → exported_models/<name>/ → (8) evaluation

Every stage writes under `<cache>/train/<build>/` (runtime.paths.cache_dir()) and finishes with a
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

from runtime.files import atomic_write_json

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

    @property
    def name(self) -> str:
        return f"{self.serial}-s{self.seed}"

    def record_config(self, physics: str, size: int):
        """The twin RecordConfig that records (and, for labels, re-plans) this session."""
        from tools.twin.record import RecordConfig
        from tools.twin.trajectory import with_ranges

        rcfg = RecordConfig(serial=self.serial, pokes=self.pokes, seed=self.seed, physics=physics,
                            frame_format=self.frames, mjpg_quality=self.quality, model_size=size)
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
    tables: str = "gpr"                           # θ/φ tables of the targets: gpr (stage 3 pokes) | truth (twin)
    contact_stride: int = 2                       # every n-th in-contact frame becomes a sample
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
    init_from: str = ""                           # fine-tune the fit from this state dict (FitConfig.init_from)
    init_bounds: str = ""                         # the bounds init_from was trained with (FitConfig.init_bounds)
    threads: int = 2
    device: str = "auto"                          # training device auto | cpu | cuda (not in any stage key)
    fe_cluster: str = ""                          # stage 2 FE batch on this Dask scheduler (tcp://host:8786); "" = local
    quantization_samples: int = 128                # inputs that set the int8 ranges (ExportConfig)
    quantization_pick: str = "spread"              # spread over the train split | "first" (ExportConfig)
    threshold_sessions: int = 6                   # training sessions the package's contact threshold is measured on
    support_px: float = 0.0                       # a fixed cluster support radius (px, floor 0); 0 = the runtime default
    latency_runs: int = 50
    eval_contact_n: float = 1.5                   # stage 8: measured |F| above this = contact (seed §III.C)
    eval_demo: bool = True                        # also evaluate on runtime/demo (held out: own unit/plan)
    models_dir: str = ""                          # default runtime.paths.models_dir()
    figures: bool = True                          # write docs/ figures (Fig. 10/11 style) after evaluation

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
        return d


def stage_keys(cfg: BuildConfig) -> dict[str, str]:
    """Config key per stage: the fields that stage (and the stages before it) depend on."""
    d = cfg.to_dict()
    deps = {"sessions": ["train", "heldout", "physics", "size"],
            "keypoints": ["contact_force_n", "detach_force_n"], "fe": ["fe"], "correspondence": ["tables"], "simreal": [],
            "dataset": ["tables", "contact_stride", "rest_fraction", "val_fraction"],
            "pretrain": ["arch", "pretrain_epochs", "batch", "lr"],
            "fit": ["arch", "epochs", "batch", "lr", "fg_weight", "force_weight", "light_weight", "init_from",
                    "init_bounds"],
            "export": ["name", "quantization_samples", "quantization_pick", "threshold_sessions", "support_px"],
            "evaluate": ["eval_demo", "eval_contact_n"]}
    # in the key only when not these values (older stamps stay valid; builds before the thresholds were
    # configurable ran stage 1 with the seed's 1.5 / 1.1 N)
    optional = {"force_weight": 0.0, "light_weight": 0.0, "init_from": "", "init_bounds": "", "contact_force_n": 1.5,
                "detach_force_n": 1.1, "threshold_sessions": 6, "quantization_pick": "first", "support_px": 0.0}
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
        from runtime.paths import cache_dir

        self.cfg = cfg
        self.root = Path(root) if root else cache_dir() / "train" / cfg.build
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
        return self.root / "sessions" / spec.name

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


# ------------------------------------------------------------------------------------------ stages

def stage_sessions(b: Build) -> dict:
    """Record the twin sessions (FE physics, cached per poke) and write each unit's TRUE calibration
    into the build's store (the twin truth the correspondence stage is checked against)."""
    from tools.progress import stage_progress
    from tools.twin.record import Recorder
    from tools.twin.unit import write_true_calibration

    out = {}
    for i, spec in enumerate(b.all_sessions()):
        path = b.session(spec)
        rec = Recorder(spec.record_config(b.cfg.physics, b.cfg.size), path, progress=stage_progress(spec.name))
        version = write_true_calibration(rec.unit, b.store_root, b.cfg.size)
        if (path / "session.json").is_file():
            log.info("[sessions %d/%d] %s already recorded", i + 1, len(b.all_sessions()), spec.name)
        else:
            log.info("[sessions %d/%d] recording %s (unit %s, seed %d, %d pokes)", i + 1, len(b.all_sessions()),
                     spec.name, spec.serial, spec.seed, spec.pokes)
            rec.run()
        out[spec.name] = {"path": str(path), "true_calibration": version}
    return {"sessions": out}


def _import_stage(name: str):
    from tools.train import stages

    return getattr(stages, f"stage_{name}")


def run_build(cfg: BuildConfig, stages: list[str] | None = None, root: Path | None = None, command: str = "",
              force: list[str] | None = None, step: str = "") -> Build:
    """Run (or resume) the build; stages already stamped with the same configuration are skipped."""
    b = Build(cfg, root, command, step)
    wanted = stages or list(STAGES)
    t_build = time.monotonic()
    for st in STAGES:
        if st not in wanted:
            continue
        if b.done(st) and st not in (force or []):
            log.info("stage %-14s done (stamp %s) — skipped", st, b.stamp_path(st).name)
            continue
        log.info("stage %-14s start", st)
        t0 = time.monotonic()
        fn = stage_sessions if st == "sessions" else _import_stage(st)
        info = fn(b) or {}
        b.stamp(st, info, time.monotonic() - t0)
        log.info("stage %-14s finished in %.0f s", st, time.monotonic() - t0)
    log.info("build %s: %.0f s this run", b.root, time.monotonic() - t_build)
    return b


def tiny_config(name: str = "tiny-smoke", build: str = "tiny") -> BuildConfig:
    """The `tiny` recipe (tools/train/recipes/tiny.toml) as one BuildConfig: the minutes-long smoke run of
    the whole chain for tests and CI (analytic twin physics — never the physics of a shipped model)."""
    from tools.train.recipe import load_recipe

    recipe = load_recipe("tiny")
    cfg = config_from_dict(recipe.config(recipe.steps()[-1]), recipe.source)
    cfg.name, cfg.build = name, build
    return cfg


def config_from_dict(d: dict, where: str) -> BuildConfig:
    """BuildConfig from a recipe step's fields; an unknown field or a bad session entry is one line."""
    from dataclasses import fields

    from tools.train.recipe import RecipeError

    known = {f.name for f in fields(BuildConfig)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise RecipeError(f"{where}: unknown build field(s) {unknown}; expected some of {sorted(known)}")
    spec_keys = {f.name for f in fields(SessionSpec)}
    for k in ("train", "heldout"):
        for i, spec in enumerate(d.get(k) or []):
            if not {"serial", "seed", "pokes"} <= set(spec) or set(spec) - spec_keys:
                raise RecipeError(f"{where}: sessions.{k}[{i}] needs serial, seed, pokes (and optionally "
                                  f"{sorted(spec_keys - {'serial', 'seed', 'pokes'})}), got {sorted(spec)}")
    return BuildConfig.from_dict(d)


def git_commit() -> str | None:
    """The commit of the checkout the build runs from (+ "-dirty" with uncommitted changes), if any."""
    import subprocess

    repo = Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("-dirty" if dirty else "")


def check_replace(package: Path, recipe_hash: str, data_hash: str | None, replace: bool) -> None:
    """Export never silently replaces a package made from another recipe or other data."""
    from tools.train.recipe import RecipeError

    man_path = package / "manifest.json"
    if replace or not man_path.is_file():
        return
    try:
        training = json.loads(man_path.read_text()).get("training") or {}
    except (OSError, ValueError, AttributeError):
        training = {}
    old_recipe = (training.get("recipe") or {}).get("hash")
    if old_recipe != recipe_hash or training.get("data_hash") != data_hash:
        what = (f"recipe {old_recipe or 'none recorded'}" if old_recipe != recipe_hash
                else f"data {str(training.get('data_hash'))[:12]}")
        raise RecipeError(f"{package} was built from {what}; this build would replace it: give --replace, "
                          f"or --set models_dir=DIR to export elsewhere")


def run_recipe(recipe, stages: list[str] | None = None, root: Path | None = None, command: str = "",
               force: list[str] | None = None, replace: bool = False, overrides: dict | None = None) -> Build:
    """Run (or resume) every step of a recipe in order; the last step exports the package.

    All steps share one build folder (`<cache>/train/<recipe name>/`): the stages before the fit are
    run once when the steps agree on them; each step's pretrain/fit/export/evaluate stamps are its own.
    A step with `after = "<step>"` starts its fit from that step's best weights."""
    from runtime.paths import cache_dir
    from tools.train.stages import fit_dir, update_manifest

    root = Path(root) if root else cache_dir() / "train" / recipe.name
    steps = recipe.steps()
    fits: dict[str, Path] = {}
    lineage: list[dict] = []
    b = None
    for i, step in enumerate(steps):
        last = i == len(steps) - 1
        cfg = config_from_dict({**recipe.config(step), **(overrides or {})}, f"{recipe.source} (step {step.name})")
        cfg.build = recipe.name
        if step.after:
            cfg.init_from = str(fits[step.after] / "best.pt")
        wanted = list(stages or STAGES) if last else [s for s in (stages or STAGES) if STAGES.index(s) <= STAGES.index("fit")]
        before_export = [s for s in wanted if STAGES.index(s) < STAGES.index("export")]
        b = Build(cfg, root, command, step.name if len(steps) > 1 else "")
        if before_export:
            b = run_build(cfg, before_export, root, command, force, step=b.step)
        fits[step.name] = fit_dir(b)
        lineage.append({"step": step.name, "after": step.after, "fit_run": str(fits[step.name].relative_to(root)),
                        "fit_key": b.keys["fit"]})
        after = [s for s in wanted if s not in before_export] if last else []
        if "export" in after:
            package = (Path(cfg.models_dir) if cfg.models_dir else _models_dir()) / cfg.name
            check_replace(package, recipe.hash, b.read_stamp("dataset").get("data_hash"), replace)
        if after:
            exported = "export" in after and not (b.done("export") and "export" not in (force or []))
            b = run_build(cfg, after, root, command, force, step=b.step)
            if exported:
                update_manifest(package, lambda man: man["training"].update(
                    recipe=recipe.record(), git_commit=git_commit(), lineage=lineage))
    return b


def recipe_build(ref: str, sets: list[str] | tuple = (), root: str | Path | None = None) -> Build:
    """The build folder of a recipe's last step, for the tools that read a build (budget, crosseval,
    resolve-check): its sessions, calibrations and dataset."""
    from tools.train.recipe import load_recipe

    recipe = load_recipe(ref, sets)
    steps = recipe.steps()
    cfg = config_from_dict(recipe.config(steps[-1]), recipe.source)
    cfg.build = recipe.name
    return Build(cfg, Path(root) if root else None, step=steps[-1].name if len(steps) > 1 else "")


def _models_dir() -> Path:
    from runtime.paths import models_dir

    return models_dir()


def cmd_all(args, upto: str | None = None, only: list[str] | None = None, force: list[str] | None = None) -> int:
    from tools.train.recipe import load_recipe

    recipe = load_recipe(args.recipe, args.set or [])
    stages = only or getattr(args, "stages", None)
    if upto:
        stages = list(STAGES[:STAGES.index(upto) + 1])
    overrides = {k: v for k, v in (("threads", args.threads), ("models_dir", args.models_dir),
                                    ("device", args.device), ("fe_cluster", args.fe_cluster)) if v}
    b = run_recipe(recipe, stages, Path(args.root) if args.root else None, args.command_line,
                   force=list(args.force or []) + list(force or []), replace=args.replace, overrides=overrides)
    ex = b.read_stamp("export")
    if ex and (not stages or "export" in stages):
        print(f"model package {ex['package']} (recipe {recipe.name} {recipe.hash}): PSNR fp32 {ex['psnr_fp32']:.2f} / "
              f"int8 {ex['psnr_int8']:.2f} dB, latency int8 {ex['latency_ms']['int8']:.2f} ms, "
              f"build wall time {ex['wall_time_s']:.0f} s")
    ev = b.read_stamp("evaluate")
    if ev and (not stages or "evaluate" in stages):
        print(json.dumps(ev.get("summary", {}), indent=1))
    return 0


def register_build(ts) -> None:
    """`train all`, `train dataset`, `train evaluate` under the `train` subparsers."""
    def common(q):
        q.add_argument("--recipe", default="hiera-qup-128",
                       help="recipe name (tools/train/recipes/NAME.toml), a .toml file, or a package's manifest.json "
                            "to rebuild it (default: hiera-qup-128)")
        q.add_argument("--set", action="append", metavar="KEY=VALUE",
                       help="change one recipe field: a build field (epochs=2) or steps.STEP.FIELD=VALUE (repeat)")
        q.add_argument("--root", help="build folder (default: <cache>/train/<recipe name>/)")
        q.add_argument("--models-dir", help="where the package is exported (default: exported_models/)")
        q.add_argument("--threads", type=int, help="torch threads for training (default: the recipe's)")
        q.add_argument("--device", choices=("auto", "cpu", "cuda"),
                       help="training device (default auto: CUDA with mixed precision when present, else CPU)")
        q.add_argument("--cluster", dest="fe_cluster", metavar="tcp://HOST:8786",
                       help="stage 2: solve the FE labels on this Dask.distributed scheduler (default: local processes)")
        q.add_argument("--force", nargs="+", choices=STAGES, default=[], metavar="STAGE",
                       help="rerun these stages even if stamped (" + ", ".join(STAGES) + ")")
        q.add_argument("--replace", action="store_true",
                       help="let export replace a package built from another recipe or other data")
    a = ts.add_parser("all", help="build a model package from its recipe, from nothing: twin → FE → dataset → "
                                  "train → export → eval (resumes)")
    common(a)
    a.add_argument("--stages", nargs="+", choices=STAGES, metavar="STAGE", help="run only these stages")
    a.set_defaults(func=cmd_all)
    d = ts.add_parser("dataset", help="a recipe's stages up to the dataset (twin sessions, keypoints, FE, "
                                      "correspondence, sim-to-real, field images)")
    common(d)
    d.set_defaults(func=lambda args: cmd_all(args, upto="dataset"), stages=None)
    e = ts.add_parser("evaluate", help="held-out twin sessions of a recipe through the runtime (reruns it)")
    common(e)
    e.set_defaults(func=lambda args: cmd_all(args, only=["evaluate"], force=["evaluate"]), stages=None)
