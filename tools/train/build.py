"""`tensortouch train all`: the one-command build of a shipped model package from nothing.

    twin sessions → (1) keypoints → (2) FE labels → (3) 2D–3D correspondence → (5) sim-to-real ratios
    → (4) dataset → (6) [MAE pretrain] + fit → (7) export → exported_models/<name>/ → (8) evaluation

Every stage writes under `<cache>/train/<build>/` (runtime.paths.cache_dir()) and finishes with a
stamp file `stamps/<stage>.json` (config key, outputs, wall time); a rerun skips stamped stages whose
configuration is unchanged, and the long stages (recording, fitting) resume inside themselves.
The build configuration is one dataclass (`BuildConfig`) whose defaults are the shipped recipe.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

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
    calibration_samples: int = 128                # int8 calibration inputs (ExportConfig)
    calibration_pick: str = "spread"              # spread over the train split | "first" (ExportConfig)
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
            "export": ["name", "calibration_samples", "calibration_pick", "threshold_sessions", "support_px"],
            "evaluate": ["eval_demo", "eval_contact_n"]}
    # in the key only when not these values (older stamps stay valid; builds before the thresholds were
    # configurable ran stage 1 with the seed's 1.5 / 1.1 N)
    optional = {"force_weight": 0.0, "light_weight": 0.0, "init_from": "", "init_bounds": "", "contact_force_n": 1.5,
                "detach_force_n": 1.1, "threshold_sessions": 6, "calibration_pick": "first", "support_px": 0.0}
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

    def __init__(self, cfg: BuildConfig, root: Path | None = None, command: str = ""):
        from runtime.paths import cache_dir

        self.cfg = cfg
        self.root = Path(root) if root else cache_dir() / "train" / cfg.build
        self.command = command
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
        tmp = self.stamp_path(stage).with_suffix(".tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        os.replace(tmp, self.stamp_path(stage))

    def read_stamp(self, stage: str) -> dict:
        p = self.stamp_path(stage)
        return json.loads(p.read_text()) if p.is_file() else {}


# ------------------------------------------------------------------------------------------ stages

def stage_sessions(b: Build) -> dict:
    """Record the twin sessions (FE physics, cached per poke) and write each unit's TRUE calibration
    into the build's store (the twin truth the correspondence stage is checked against)."""
    from tools.twin.cli import _Bar
    from tools.twin.record import Recorder
    from tools.twin.unit import write_true_calibration

    out = {}
    for i, spec in enumerate(b.all_sessions()):
        path = b.session(spec)
        rec = Recorder(spec.record_config(b.cfg.physics, b.cfg.size), path, progress=_Bar())
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
              force: list[str] | None = None) -> Build:
    """Run (or resume) the build; stages already stamped with the same configuration are skipped."""
    b = Build(cfg, root, command)
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
    """A minutes-long configuration of the whole chain for the smoke test / CI: analytic twin physics
    (hertz-fallback — never the physics of a shipped model), 64² model, one short training session."""
    return BuildConfig(name=name, build=build, size=64, physics="hertz-fallback", tables="truth",
                       train=[SessionSpec("TWIN-S01", 11, 2, "png", 90)],
                       heldout=[SessionSpec("TWIN-S02", 12, 1, "png", 90)], contact_stride=3,
                       epochs=1, pretrain_epochs=1, batch=4, calibration_samples=4, latency_runs=5,
                       eval_demo=False, figures=False,
                       eval_contact_n=0.2)


def read_recipe(path: str | Path) -> dict:
    """A recipe's BuildConfig fields. `"include": [FILE, ...]` (paths beside the recipe) puts the
    included recipes' training sessions first, each (serial, seed) once, then the recipe's own."""
    path = Path(path)
    d = json.loads(path.read_text())
    if "include" in d:
        train, seen = [], set()
        for spec in [s for inc in d.pop("include") for s in read_recipe(path.parent / inc).get("train", [])] \
                + d.get("train", []):
            if (spec["serial"], spec["seed"]) not in seen:
                seen.add((spec["serial"], spec["seed"]))
                train.append(spec)
        d["train"] = train
    return d


def config_from_args(args) -> BuildConfig:
    cfg = tiny_config() if args.tiny else BuildConfig()
    if args.config:
        cfg = BuildConfig.from_dict({**cfg.to_dict(), **read_recipe(args.config)})
    for k in ("name", "build", "size", "epochs", "batch", "tables", "fe", "threads", "device", "fe_cluster", "models_dir", "arch", "lr",
              "contact_stride", "force_weight", "light_weight", "init_from", "init_bounds", "contact_force_n", "detach_force_n",
              "calibration_samples", "calibration_pick", "support_px"):
        v = getattr(args, k, None)
        if v is not None:
            setattr(cfg, k, v)
    if args.pretrain_epochs is not None:
        cfg.pretrain_epochs = args.pretrain_epochs
    if args.no_demo:
        cfg.eval_demo = False
    if args.no_figures:
        cfg.figures = False
    return cfg


def _command(argv: list[str] | None) -> str:
    import shlex

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] != ["train"]:
        argv = ["train", *argv]
    return shlex.join(["tensortouch", *argv])


def cmd_all(args, upto: str | None = None, only: list[str] | None = None, force: list[str] | None = None) -> int:
    cfg = config_from_args(args)
    stages = only or args.stages
    if upto:
        stages = list(STAGES[:STAGES.index(upto) + 1])
    b = run_build(cfg, stages, Path(args.root) if args.root else None, _command(None),
                  force=list(args.force or []) + list(force or []))
    ex = b.read_stamp("export")
    if ex and (not stages or "export" in stages):
        print(f"model package {ex['package']}: PSNR fp32 {ex['psnr_fp32']:.2f} / int8 {ex['psnr_int8']:.2f} dB, "
              f"latency int8 {ex['latency_ms']['int8']:.2f} ms, build wall time {ex['wall_time_s']:.0f} s")
    ev = b.read_stamp("evaluate")
    if ev and (not stages or "evaluate" in stages):
        print(json.dumps(ev.get("summary", {}), indent=1))
    return 0


def register_build(ts) -> None:
    """`train all`, `train dataset`, `train evaluate` under the `train` subparsers."""
    def common(q):
        q.add_argument("--build", help="build folder under <cache>/train/ (default: main)")
        q.add_argument("--root", help="explicit build folder (overrides --build)")
        q.add_argument("--name", help="model package name (default: hiera-qup-128)")
        q.add_argument("--config", help="JSON file with BuildConfig fields to override")
        q.add_argument("--tiny", action="store_true", help="minutes-long smoke configuration (hertz-fallback twin)")
        q.add_argument("--size", type=int)
        q.add_argument("--epochs", type=int)
        q.add_argument("--pretrain-epochs", type=int)
        q.add_argument("--batch", type=int)
        q.add_argument("--lr", type=float, help="fit learning rate (default 1e-3)")
        q.add_argument("--contact-stride", type=int, help="every n-th in-contact frame becomes a sample (default 2)")
        q.add_argument("--contact-force", dest="contact_force_n", type=float,
                       help="stage 1: contact starts above this measured |F| in N (default 0.5; seed 1.5)")
        q.add_argument("--detach-force", dest="detach_force_n", type=float,
                       help="stage 1: contact ends below this |F| in N (default 0.37; seed 1.1)")
        q.add_argument("--force-weight", type=float, help="total-force loss term per N (default 0 = off)")
        q.add_argument("--light-weight", type=float,
                       help="light-contact emphasis: sample weight (1 N / |F|)^W, clipped to [1, 3] (default 0 = off)")
        q.add_argument("--init-from", help="fine-tune: start the fit from this state dict (a run's best.pt)")
        q.add_argument("--init-bounds", help="fine-tune: the output bounds --init-from was trained with (a bounds.json "
                                             "or a model package's manifest.json; default: the bounds.json beside it); "
                                             "the heads are rescaled to this dataset's bounds")
        q.add_argument("--threads", type=int)
        q.add_argument("--device", choices=("auto", "cpu", "cuda"),
                       help="training device (default auto: CUDA with mixed precision when present, else CPU)")
        q.add_argument("--cluster", dest="fe_cluster", metavar="tcp://HOST:8786",
                       help="stage 2: solve the FE labels on this Dask.distributed scheduler (default: local processes)")
        q.add_argument("--calibration-samples", type=int, help="int8 calibration inputs (default 128)")
        q.add_argument("--calibration-pick", choices=("spread", "first"),
                       help="int8 calibration inputs spread over the train split (default) or its first ones "
                            "(packages exported before session 10)")
        q.add_argument("--support-px", type=float,
                       help="export: a fixed cluster support radius in px (floor 0 N) in the package's manifest "
                            "(default: the runtime's 10 px)")
        q.add_argument("--arch", choices=("hiera_qup", "unet", "vit"))
        q.add_argument("--tables", choices=("gpr", "truth"), help="θ/φ tables of the targets: gpr = stage 3 GPR from detected pokes (default); truth = the twin's true tables")
        q.add_argument("--fe", choices=("resolve", "twin"),
                       help="stage 2 FE labels: resolve = FE re-solved from the measured keypoints (default); "
                            "twin = the twin's own solves of its plan")
        q.add_argument("--models-dir", help="root of model packages (default: exported_models/)")
        q.add_argument("--force", nargs="+", choices=STAGES, default=[], help="rerun these stages even if stamped")
        q.add_argument("--no-demo", action="store_true", help="do not evaluate on runtime/demo")
        q.add_argument("--no-figures", action="store_true", help="do not write the docs/ figures")
    a = ts.add_parser("all", help="build the shipped model from nothing: twin → FE → dataset → train → export → eval")
    common(a)
    a.add_argument("--stages", nargs="+", choices=STAGES, help="run only these stages")
    a.set_defaults(func=cmd_all)
    d = ts.add_parser("dataset", help="the build's stages up to the dataset (twin sessions, keypoints, FE, "
                                      "correspondence, sim-to-real, field images)")
    common(d)
    d.set_defaults(func=lambda args: cmd_all(args, upto="dataset"), stages=None)
    e = ts.add_parser("evaluate", help="stage 8: held-out twin sessions through the runtime (reruns it)")
    common(e)
    e.set_defaults(func=lambda args: cmd_all(args, only=["evaluate"], force=["evaluate"]), stages=None)


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m tools.train.build")
    register_build(ap.add_subparsers(dest="cmd", required=True))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
