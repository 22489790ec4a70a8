"""`tensortouch train ...` — thin shells over the train-side stages (docs/train.md).

    tensortouch train keypoints SESSION [--out FILE]       stage 1: contact periods + keypoints → JSON
    tensortouch train synth --out DIR [--n N --size S]     synthetic dataset (tests/benchmarks; not physics)
    tensortouch train pretrain --data DIR --out RUN        stage 6a: MAE pretraining of the Hiera encoder
    tensortouch train fit --data DIR --out RUN             stage 6b: supervised training (resumes)
    tensortouch train export --run RUN --data DIR --name N stage 7: ONNX + int8 + parity → exported_models/N/
    tensortouch train bench                                network benchmark (params, samples/s, latency)

Heavy libraries (torch, onnx) are imported inside the handlers.
"""
from __future__ import annotations

import json
import logging
import shlex
import time
from pathlib import Path

from ...contracts.files import atomic_write_json
from ..command_group import LazySubcommands

ARCH_CHOICES = ("hiera_qup", "unet", "vit", "convnet")    # tools.train.model.ARCHS (kept literal: no import at CLI start)

log = logging.getLogger(__name__)

# Tools on built packages and builds: each module exposes add_arguments(parser) and run(args).
TOOLS = (
    ("threshold", "tensortouch.tools.train.threshold",
     "measure a package's contact thresholds, light-touch rule and merging on sessions (--write), or --check them"),
    ("crosseval", "tensortouch.tools.train.crosseval",
     ("packages side by side on held-out sessions or a protocol unit set through the runtime: detection, "
     "phantoms, |F| MAE and direction with bootstrap CIs")),
    ("curve", "tensortouch.tools.train.curve",
     "learning curve: a recipe on the first N train units for several N and fit seeds, scored on the validation units"),
    ("units", "tensortouch.tools.train.units",
     "the evaluation protocol's train / validation / sealed unit sets: check them and the recipes, list, record"),
    ("resolve-check", "tensortouch.tools.train.resolve_check",
     "twin-only check of stage 2: FE re-solved from measured keypoints against the twin's own solves"),
    ("rig-estimate", "tensortouch.tools.train.rig_estimate",
     "a session's F/T bias, clock offsets (cross-correlation) and mocap extrinsic shift from its own data"),
)



def cmd_keypoints(args) -> int:
    from ...contracts.paths import cache_dir
    from ...contracts.session import load_session
    from .keypoints import KeypointConfig, extract_keypoints, keypoints_doc

    ses = load_session(args.session, check_frames=False)
    cfg = KeypointConfig(image_rate_hz=args.image_rate, max_keypoints=args.max_keypoints)
    frames = ses.table("frames") if ses.has("frames") else None
    kps = extract_keypoints(ses.table("poses"), ses.table("wrench"), frames, cfg)
    doc = keypoints_doc(ses, kps, cfg, str(Path(args.session).resolve()))
    out = Path(args.out) if args.out else cache_dir() / "keypoints" / f"{Path(args.session).name}.json"
    atomic_write_json(out, doc)
    print(f"{len(kps)} contact period(s), {sum(len(k.t) for k in kps)} keypoints → {out}")
    return 0


def cmd_synth(args) -> int:
    from .model.data import write_synthetic_dataset

    h = write_synthetic_dataset(args.out, args.n, args.size, args.seed, min_contacts=args.min_contacts)
    print(f"synthetic dataset ({args.n} samples, {args.size}²) → {args.out}  data hash {h}")
    return 0


def cmd_pretrain(args) -> int:
    from .model.train import PretrainConfig, pretrain

    cfg = PretrainConfig(epochs=args.epochs, batch_size=args.batch, threads=args.threads, lr=args.lr,
                         device=args.device)
    res = pretrain(args.data, args.out, cfg)
    print(f"pretrained encoder → {Path(args.out) / 'encoder.pt'}  ({res.get('samples_per_s') or 0:.1f} samples/s)")
    return 0


def cmd_fit(args) -> int:
    from .model.train import FitConfig, fit

    cfg = FitConfig(arch=args.arch, epochs=args.epochs, batch_size=args.batch, threads=args.threads, lr=args.lr,
                    device=args.device)
    res = fit(args.data, args.out, cfg, encoder_init=args.encoder)
    m = res["metrics"]["mean"]
    print(f"{args.arch}: {res['params']:,} params, val PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}, "
          f"AUC_rel {m['auc_rel']:.4f}, FPR_rel {m['fpr_rel']:.4f} → {args.out}")
    return 0


def cmd_export(args) -> int:
    from ...contracts.paths import models_dir
    from .export import ExportConfig, export_run

    t0 = time.monotonic()
    root = Path(args.models_dir) if args.models_dir else models_dir()
    cfg = ExportConfig(quantization_samples=args.quantization_samples, quantization_pick=args.quantization_pick,
                       latency_runs=args.latency_runs,
                       with_fp32=getattr(args, "with_fp32", False))
    command = args.command_line or shlex.join(
        ["tensortouch", "train", "export", "--run", str(args.run), "--data", str(args.data), "--name", args.name,
         "--models-dir", str(root), "--quantization-samples", str(args.quantization_samples), "--quantization-pick", args.quantization_pick,
         "--latency-runs", str(args.latency_runs)]
        + (["--with-fp32"] if getattr(args, "with_fp32", False) else []))
    man = export_run(args.run, args.data, args.name, root, command, cfg, wall_time_s=args.wall_time)
    m = man["metrics"]
    print(f"{root / args.name}: PSNR fp32 {m['fp32']['psnr']:.2f} / int8 {m['int8']['psnr']:.2f} dB, "
          f"latency fp32 {m['latency_ms']['fp32']:.2f} / int8 {m['latency_ms']['int8']:.2f} ms "
          f"({time.monotonic() - t0:.0f} s)")
    return 0


def cmd_weights(args) -> int:
    from .from_package import write_init

    path = write_init(args.package, args.out, args.precision)
    info = json.loads((path.parent / "from_package.json").read_text())
    print(f"{info['package']} ({info['file']}, {info['params']:,} weights) → {path}; fine-tune with "
          f"`tensortouch train all ... --init-from {path}` (bounds.json beside it: heads rescaled)")
    return 0


def cmd_bench(args) -> int:
    from .bench import run_bench

    res = run_bench(sizes=args.sizes, archs=args.archs, threads=args.threads, steps=args.steps,
                    latency_runs=args.runs)
    text = json.dumps(res, indent=1)
    if args.out:
        atomic_write_json(Path(args.out), res)
    print(text)
    return 0


def register(sub) -> None:
    """Add `train` and its stage subcommands to the `tensortouch` parser."""
    p = sub.add_parser("train", help="train-side pipeline: keypoints, datasets, training, export",
                       description="Train-side stages (docs/train.md). Each reads and writes documented files.")
    p.set_defaults(extra="train")
    ts = p.add_subparsers(dest="train_cmd", metavar="STAGE", required=True, action=LazySubcommands)

    k = ts.add_parser("keypoints", help="stage 1: contact detection and keypoints of a session")
    k.add_argument("session", help="session directory (docs/session.md)")
    k.add_argument("--out", help="output JSON (default: cache/keypoints/<session>.json)")
    k.add_argument("--image-rate", type=float, default=30.0, help="camera frame rate f_image (Hz)")
    k.add_argument("--max-keypoints", type=int, default=12, help="at most this many keypoints per contact period")
    k.set_defaults(func=cmd_keypoints)

    s = ts.add_parser("synth", help="write a synthetic (not physical) dataset for tests and benchmarks")
    s.add_argument("--out", required=True, help="folder for the synthetic dataset")
    s.add_argument("--n", type=int, default=200, help="number of samples")
    s.add_argument("--size", type=int, default=96, help="image size (px)")
    s.add_argument("--seed", type=int, default=0, help="random seed")
    s.add_argument("--min-contacts", type=int, default=0, help="contacts per sample at least (0..2)")
    s.set_defaults(func=cmd_synth)

    def common(q, epochs, batch):
        q.add_argument("--data", required=True, help="dataset directory (index.json, bounds.json, samples/)")
        q.add_argument("--out", required=True, help="run directory (resumes if it holds a checkpoint)")
        q.add_argument("--epochs", type=int, default=epochs, help="passes over the training set")
        q.add_argument("--batch", type=int, default=batch, help="samples per step")
        q.add_argument("--lr", type=float, default=1e-3, help="AdamW learning rate")
        q.add_argument("--threads", type=int, default=2, help="torch CPU threads")
        q.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                       help="auto (default): CUDA with mixed precision when present, else CPU")

    pr = ts.add_parser("pretrain", help="stage 6a: MAE pretraining (75 %% of mask units hidden)")
    common(pr, 10, 16)
    pr.set_defaults(func=cmd_pretrain)

    f = ts.add_parser("fit", help="stage 6b: supervised training, L1, AdamW, warmup + cosine")
    common(f, 20, 16)
    f.add_argument("--arch", default="hiera_qup", choices=ARCH_CHOICES, help="network architecture")
    f.add_argument("--encoder", help="encoder.pt from `train pretrain` (hiera_qup only)")
    f.set_defaults(func=cmd_fit, resume_hint="it continues from the run's last checkpoint")

    e = ts.add_parser("export", help="stage 7: ONNX + static int8 + parity → exported_models/<name>/")
    e.add_argument("--run", required=True, help="fit run directory")
    e.add_argument("--data", required=True, help="dataset (quantization samples, evaluation, bounds, hash)")
    e.add_argument("--name", required=True, help="package name")
    e.add_argument("--models-dir", help="root of model packages (default: exported_models/ or $TENSORTOUCH_MODELS)")
    e.add_argument("--quantization-samples", type=int, default=128,
                   help="training inputs that set the int8 activation ranges")
    e.add_argument("--quantization-pick", choices=("spread", "first"), default="spread",
                   help="which training inputs: spread evenly over the split (default) or the first ones")
    e.add_argument("--latency-runs", type=int, default=50, help="timed runs per precision for the latency figure")
    e.add_argument("--wall-time", type=float, default=0.0, help="wall time of the whole build to record (s)")
    e.add_argument("--command-line", help="command to record in the manifest when export is one step of a "
                                          "larger build (default: this export command)")
    e.add_argument("--with-fp32", action="store_true", help="also ship model.fp32.onnx in the package "
                   "(default: int8 only; the fp32 graph is left in <run>/export/<name>/)")
    e.set_defaults(func=cmd_export)

    w = ts.add_parser("weights", help="a model package's ONNX weights back into a training state dict "
                                       "(fine-tune from what ships when its build cache is gone)")
    w.add_argument("package", help="model package folder (manifest.json + model.int8.onnx [+ model.fp32.onnx])")
    w.add_argument("--out", required=True, help="folder for best.pt, bounds.json and from_package.json")
    w.add_argument("--precision", choices=("best", "fp32", "int8"), default="best",
                   help="graph to read: best = fp32 when the package ships it, else int8 (dequantized)")
    w.set_defaults(func=cmd_weights)

    b = ts.add_parser("bench", help="network benchmark: params, training samples/s, ORT fp32 vs int8 latency")
    b.add_argument("--sizes", type=int, nargs="+", default=[96, 128], help="input sizes (px) to time")
    b.add_argument("--archs", nargs="+", default=["hiera_qup", "unet", "vit"], help="architectures to time")
    b.add_argument("--threads", type=int, default=2, help="torch threads for the training measurement")
    b.add_argument("--steps", type=int, default=6, help="timed training steps per model")
    b.add_argument("--runs", type=int, default=60, help="latency runs per model")
    b.add_argument("--out", help="also write the JSON here")
    b.set_defaults(func=cmd_bench)
    register_build(ts)  # all, dataset, evaluate
    for name, module, helptext in TOOLS:
        ts.add_module(name, module, helptext)
    ts.add_module("budget", "tensortouch.tools.train.evaluate",
                  "error budget of a build: label and network error per stage, held out",
                  add="add_budget_arguments", run="run_budget_command")


def cmd_all(args, upto: str | None = None, only: list[str] | None = None, force: list[str] | None = None) -> int:
    from .build import STAGES
    from .recipe import load_recipe
    from .runner import run_recipe

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


RESUME = "stamped stages are skipped; recording, FE and fitting continue from what they wrote"


def register_build(ts) -> None:
    """`train all`, `train dataset`, `train evaluate` under the `train` subparsers."""
    from .build import STAGES

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
    a.set_defaults(func=cmd_all, resume_hint=RESUME)
    d = ts.add_parser("dataset", help="a recipe's stages up to the dataset (twin sessions, keypoints, FE, "
                                      "correspondence, sim-to-real, field images)")
    common(d)
    d.set_defaults(func=lambda args: cmd_all(args, upto="dataset"), stages=None, resume_hint=RESUME)
    e = ts.add_parser("evaluate", help="held-out twin sessions of a recipe through the runtime (reruns it)")
    common(e)
    e.set_defaults(func=lambda args: cmd_all(args, only=["evaluate"], force=["evaluate"]), stages=None)
