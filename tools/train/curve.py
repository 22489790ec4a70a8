"""Learning curve: one recipe trained on the first N units of the protocol's train set, for several N and fit
seeds, every package scored on the validation units by `train crosseval` (one scoring path).

    tensortouch train curve --recipe hiera-qup-128-rim --train-units 3 6 12 [--fit-seed 0 1 2] [--json OUT]

The recipe must take its training sessions from the train set by name (`train = { set = "train", ... }`);
each point replaces `first` with N (and the build's `fit_seed`), builds in its own folder
`<cache>/train/curve/<name>-u<N>-s<seed>/` and exports its package there (`package/`), so a point never
replaces a shipped package. The point that is the recipe itself (its own `first` and fit seed) is the
recipe's own build and package, as `train all --recipe R` makes them. Recording, FE labels and tables are cached (`<cache>/fe` and the twin's FE
cache), so the points after the first pay mostly for their fits; a point whose package is already
exported from the same recipe (its manifest's recipe hash) is scored as it is, not rebuilt. Packages of one N that differ only in
`fit_seed` share a recipe key, so crosseval prints their mean ± spread.
"""
from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--recipe", required=True, help="a recipe whose sessions.train is a train-set reference")
    ap.add_argument("--train-units", type=int, nargs="+", required=True, metavar="N",
                    help="numbers of train units, each the set's first N")
    ap.add_argument("--fit-seed", type=int, nargs="+", default=[0], help="fit seeds per point (default 0)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a build field for every point")
    ap.add_argument("--units", default="validation", help="the protocol set that scores (validation; never sealed)")
    ap.add_argument("--units-root", help="where recorded sets live (default <cache>/units)")
    ap.add_argument("--build-only", action="store_true", help="build the points, score nothing")
    ap.add_argument("--json", help="write crosseval's summaries, scorecards and the curve here")


def point_recipe(recipe, n: int, seed: int):
    """The recipe of one point: its train-set reference taking the first n units, fit_seed = seed, named
    `<name>-u<n>-s<seed>` (the package and build folder name)."""
    from .recipe import Recipe, RecipeError, validate

    doc = copy.deepcopy(recipe.doc)
    ref = (doc.get("sessions") or {}).get("train")
    if not isinstance(ref, dict) or ref.get("set") != "train":
        raise RecipeError(f"{recipe.source}: sessions.train is not a train-set reference "
                          f"(train = {{ set = \"train\", first = N, pokes = P }}); a learning curve needs one")
    if n < 1:
        raise RecipeError(f"--train-units {n}: expected a number of units ≥ 1")
    ref["first"] = int(n)
    doc.setdefault("build", {})["fit_seed"] = int(seed)
    doc["name"] = f"{recipe.name}-u{n}-s{seed}"
    validate(doc, f"{recipe.source} (curve point u{n} s{seed})")
    return Recipe(doc["name"], recipe.source, doc)


def package_dir(cfg) -> Path:
    """Where a build config's package is exported (BuildConfig.models_dir, else the repository's)."""
    from ...contracts.paths import models_dir

    return (Path(cfg.models_dir) if cfg.models_dir else models_dir()) / cfg.name


def built_from(package: Path, recipe) -> bool:
    """True when `package` holds a manifest whose recorded recipe hash is `recipe`'s: the point is built
    (a curve resumed in a fresh cache does not rebuild what it already exported)."""
    try:
        doc = json.loads((Path(package) / "manifest.json").read_text())
        return ((doc.get("training") or {}).get("recipe") or {}).get("hash") == recipe.hash
    except (OSError, ValueError, AttributeError):
        return False


def curve_rows(cards: dict, points: list[tuple[int, int, str]]) -> list[dict]:
    """Per N: the points' headline numbers (crosseval scorecards by package), mean and spread over fit seeds."""
    from .scorecard import fit_seed_spread, headline

    rows = []
    for n in sorted({p[0] for p in points}):
        pks = [pk for m, _, pk in points if m == n and pk in cards]
        if pks:
            rows.append({"train_units": n, "packages": pks, **fit_seed_spread([headline(cards[p]) for p in pks])})
    return rows


def format_rows(rows: list[dict]) -> str:
    def cell(r, k, scale=1.0, unit=""):
        v = r.get(k)
        if not v:
            return "—"
        return f"{v['mean'] * scale:.3g}{unit} ± {v['sd'] * scale:.2g}" if v["n"] > 1 else f"{v['mean'] * scale:.3g}{unit}"
    head = "| train units | fits | \\|F\\| MAE, detected ≥ 0.2 N | missed ≥ 0.2 N | phantoms | direction |"
    out = [head, "|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['train_units']} | {len(r['packages'])} | {cell(r, 'force_mae_n', 1, ' N')} | "
                   f"{cell(r, 'miss_rate', 100, ' %')} | {cell(r, 'phantom_rate', 100, ' %')} | "
                   f"{cell(r, 'direction_error_deg', 1, '°')} |")
    return "\n".join(out)


def run(args: argparse.Namespace) -> int:
    from ...contracts.errors import TensorTouchError
    from ...contracts.paths import cache_dir
    from . import crosseval
    from .recipe import load_recipe
    from .runner import run_recipe, step_configs

    if args.units == "sealed":
        print("train curve: --units sealed: the sealed set is never used for a choice")
        return 2
    try:
        recipe = load_recipe(args.recipe, args.set)
        points = []
        own = ((recipe.doc.get("sessions") or {}).get("train") or {}).get("first"), \
            int((recipe.doc.get("build") or {}).get("fit_seed", 0))
        for n in args.train_units:
            for seed in args.fit_seed:
                r = point_recipe(recipe, n, seed)
                if (n, seed) == own:     # the recipe itself: its own build and package (`train all --recipe R`)
                    pk = package_dir(step_configs(recipe)[-1])
                    if not built_from(pk, recipe):
                        pk = package_dir(run_recipe(recipe, command=getattr(args, "command_line", "")).cfg)
                    points.append((n, seed, str(pk)))
                    continue
                root = cache_dir() / "train" / "curve" / r.name
                pk = root / "package" / r.name
                if not built_from(pk, r):
                    run_recipe(r, root=root, command=getattr(args, "command_line", ""),
                               overrides={"models_dir": str(root / "package"), "eval_demo": False, "figures": False})
                points.append((n, seed, str(pk)))
    except TensorTouchError as exc:
        print(f"train curve: {exc}")
        return 2
    if args.build_only:
        return 0
    ap = argparse.ArgumentParser()
    crosseval.add_arguments(ap)
    out = Path(args.json) if args.json else cache_dir() / "train" / "curve" / f"{recipe.name}.json"
    argv = [x for _, _, pk in points for x in ("--package", pk)] + ["--units", args.units, "--json", str(out)]
    if args.units_root:
        argv += ["--units-root", args.units_root]
    rc = crosseval.run(ap.parse_args(argv))
    if rc:
        return rc
    doc = json.loads(out.read_text())
    rows = curve_rows(doc["scorecards"], points)
    from ...contracts.files import atomic_write_json

    atomic_write_json(out, {**doc, "curve": rows})
    print(f"learning curve of {recipe.name} on the {args.units} units ({out}):\n{format_rows(rows)}")
    return 0
