"""The runner of `tensortouch train all`: the stage table in the order the stages run, and a recipe's
steps one after another (tools/train/build.py holds the build folder, tools/train/stages.py the stages)."""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from . import stages
from .build import STAGES, Build, BuildConfig, config_from_dict, fit_dir
from .package import repo_relative, update_manifest

log = logging.getLogger(__name__)

# (number, name, run(build) -> summary), in the order they run
STAGE_TABLE = (
    (0, "sessions", stages.stage_sessions),
    (1, "keypoints", stages.stage_keypoints),
    (2, "fe", stages.stage_fe),
    (3, "correspondence", stages.stage_correspondence),
    (4, "simreal", stages.stage_simreal),
    (5, "dataset", stages.stage_dataset),
    (6, "pretrain", stages.stage_pretrain),
    (6, "fit", stages.stage_fit),
    (7, "export", stages.stage_export),
    (8, "evaluate", stages.stage_evaluate),
)
assert tuple(name for _, name, _ in STAGE_TABLE) == STAGES


def run_build(cfg: BuildConfig, stages: list[str] | None = None, root: Path | None = None, command: str = "",
              force: list[str] | None = None, step: str = "") -> Build:
    """Run (or resume) the build; stages already stamped with the same configuration are skipped."""
    b = Build(cfg, root, command, step)
    wanted = stages or list(STAGES)
    t_build = time.monotonic()
    for number, st, fn in STAGE_TABLE:
        if st not in wanted:
            continue
        if b.done(st) and st not in (force or []):
            log.info("stage %-14s done (stamp %s) — skipped", st, b.stamp_path(st).name)
            continue
        log.info("stage %d %-14s start", number, st)
        t0 = time.monotonic()
        info = fn(b) or {}
        b.stamp(st, info, time.monotonic() - t0)
        log.info("stage %-14s finished in %.0f s", st, time.monotonic() - t0)
    log.info("build %s: %.0f s this run", b.root, time.monotonic() - t_build)
    return b


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
    from .recipe import RecipeError

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
    from ...contracts.names import confined
    from ...contracts.paths import cache_dir
    from .recipe import RecipeError

    root = Path(root) if root else confined(cache_dir() / "train", recipe.name, f"{recipe.source}: name", RecipeError)
    commit = git_commit()          # the code that runs the build (the export then rewrites the package's own files)
    steps = recipe.steps()
    fits: dict[str, Path] = {}
    lineage: list[dict] = []
    b = None
    cfgs = step_configs(recipe, overrides)    # every step checked before the first stage of any step runs
    for i, (step, cfg) in enumerate(zip(steps, cfgs)):
        last = i == len(steps) - 1
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
            package = confined(Path(cfg.models_dir) if cfg.models_dir else _models_dir(), cfg.name, "package name")
            check_replace(package, recipe.hash, b.read_stamp("dataset").get("data_hash"), replace)
        if after:
            exported = "export" in after and not (b.done("export") and "export" not in (force or []))
            b = run_build(cfg, after, root, command, force, step=b.step)
            if exported:
                update_manifest(package, lambda man: man["training"].update(
                    recipe={**recipe.record(), "source": repo_relative(Path(recipe.source))},
                    git_commit=commit, lineage=lineage))
    return b


def _models_dir() -> Path:
    from ...contracts.paths import models_dir

    return models_dir()


def step_configs(recipe, overrides: dict | None = None) -> list:
    """The BuildConfig of every step of `recipe` (with `overrides`), each field checked by its type and
    declared range (build.config_from_dict); a RecipeError names the first bad field."""
    return [config_from_dict({**recipe.config(step), **(overrides or {})}, f"{recipe.source} (step {step.name})")
            for step in recipe.steps()]
