"""A recipe is the whole description of a model: one TOML file, `tools/train/recipes/<name>.toml`.

    name = "hiera-qup-128"                 # the package it builds (exported_models/<name>/)
    about = "…"                            # one line for people
    [sessions]
    train = [ { serial = "TWIN-T01", seed = 101, pokes = 5, frames = "mjpg", quality = 65 }, … ]
    heldout = [ … ]                        # recorded, never trained on: the build's own evaluation
    [build]                                # BuildConfig fields (tools/train/build.py), e.g.
    fe = "resolve"                         #   labels from FE solved at the measured keypoints
    tables = "gpr"                         #   θ/φ tables by GPR from detected pokes
    epochs = 30
    [[steps]]                              # optional lineage, run in order; without it one step "main"
    name = "base"
    [[steps]]
    name = "light"
    after = "base"                         # fine-tunes the fit of the step named here
    build = { epochs = 2, lr = 1e-4 }

A package's manifest records the resolved recipe (its text as parsed, its hash), so
`tensortouch train all --recipe exported_models/<name>/manifest.json` rebuilds it. Options that are
not in the recipe are given as `--set key=value` (a `build` field, or `steps.<step>.<field>`); a set
value changes the recipe and so its hash.

This module reads and resolves recipes only: of the project it imports only contracts (errors, schema).
"""
from __future__ import annotations

import copy
import hashlib
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ...contracts.errors import TensorTouchError
from ...contracts.names import check_name

RECIPES_DIR = Path(__file__).resolve().parent / "recipes"
TOP_KEYS = {"name", "about", "sessions", "build", "steps"}
SESSION_KEYS = {"train", "heldout"}
STEP_KEYS = {"name", "after", "build"}


class RecipeError(TensorTouchError, ValueError):
    """A recipe file or a --set is not what the recipe format expects (one line, names the place)."""


@dataclass(frozen=True)
class Step:
    name: str
    after: str | None
    build: dict = field(default_factory=dict)


@dataclass
class Recipe:
    name: str
    source: str               # the file it was read from (a recipe .toml or a package manifest)
    doc: dict                 # the parsed recipe, with every --set applied

    @property
    def hash(self) -> str:
        """SHA-256 (16 hex) of the canonical JSON of the resolved recipe."""
        return hashlib.sha256(json.dumps(self.doc, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:16]

    def steps(self) -> list[Step]:
        raw = self.doc.get("steps") or [{"name": "main"}]
        return [Step(s["name"], s.get("after"), dict(s.get("build") or {})) for s in raw]

    def config(self, step: Step) -> dict:
        """BuildConfig fields of one step: the recipe's build table, then the step's own fields."""
        d = {**(self.doc.get("build") or {}), **step.build}
        sessions = self.doc.get("sessions") or {}
        for k in SESSION_KEYS:
            if k in sessions:
                d[k] = copy.deepcopy(sessions[k])
        d["name"] = self.name
        return d

    def record(self) -> dict:
        """What a package's manifest keeps of its recipe."""
        return {"name": self.name, "source": self.source, "hash": self.hash, "doc": self.doc}


def recipe_path(ref: str | Path) -> Path:
    """A recipe name (tools/train/recipes/<name>.toml), a .toml path, or a package manifest.json."""
    p = Path(ref)
    if p.suffix in (".toml", ".json") or p.is_file():
        return p
    return RECIPES_DIR / f"{ref}.toml"


def load_recipe(ref: str | Path, sets: list[str] | tuple = ()) -> Recipe:
    path = recipe_path(ref)
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in RECIPES_DIR.glob("*.toml")))
        raise RecipeError(f"recipe {ref!r}: no file {path} (recipes here: {known})")
    try:
        if path.suffix == ".json":
            man = json.loads(path.read_text(encoding="utf-8"))
            doc = man["training"]["recipe"]["doc"] if isinstance(man, dict) else None
            if not isinstance(doc, dict):
                raise KeyError
        else:
            doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (KeyError, TypeError):
        raise RecipeError(f"{path}: a package manifest without training.recipe (it was not built from a recipe)") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise RecipeError(f"{path}: not a readable recipe ({str(exc)[:200]})") from None
    except RecursionError:
        raise RecipeError(f"{path}: not a readable recipe (nested too deeply)") from None
    validate(doc, str(path))
    recipe = Recipe(doc["name"], str(path), doc)
    for s in sets:
        recipe = apply_set(recipe, s)
    return recipe


def validate(doc: dict, where: str) -> None:
    """Shape of a recipe (the BuildConfig fields, by name, type and range, are checked where BuildConfig
    lives: tools/train/build.py config_from_dict)."""
    from ...contracts.schema import SchemaError, check_depth

    if not isinstance(doc, dict):
        raise RecipeError(f"{where}: expected a table of recipe fields, got {type(doc).__name__}")
    try:
        check_depth(doc, where)
    except SchemaError as exc:
        raise RecipeError(str(exc)) from None
    unknown = set(doc) - TOP_KEYS
    if unknown:
        raise RecipeError(f"{where}: unknown top-level key(s) {sorted(unknown)}; expected some of {sorted(TOP_KEYS)}")
    check_name(doc.get("name"), f"{where}: 'name' (the package name)", RecipeError)   # it names folders
    sessions = doc.get("sessions", {})
    if not isinstance(sessions, dict) or set(sessions) - SESSION_KEYS:
        raise RecipeError(f"{where}: [sessions] takes only {sorted(SESSION_KEYS)}")
    for k, v in sessions.items():      # a list of sessions, or one table naming a protocol set (build.py expands it)
        if not (isinstance(v, dict) or isinstance(v, list) and all(isinstance(s, dict) for s in v)):
            raise RecipeError(f"{where}: sessions.{k} must be a list of tables or a table naming a protocol set")
    if not isinstance(doc.get("build", {}), dict):
        raise RecipeError(f"{where}: [build] must be a table")
    steps = doc.get("steps", [])
    if not isinstance(steps, list):
        raise RecipeError(f"{where}: [[steps]] must be an array of tables")
    seen: list[str] = []
    for i, s in enumerate(steps):
        if not isinstance(s, dict) or set(s) - STEP_KEYS or not isinstance(s.get("name"), str):
            raise RecipeError(f"{where}: steps[{i}] must be a table with a 'name' and optionally 'after', 'build'")
        if s["name"] in seen:
            raise RecipeError(f"{where}: steps[{i}]: the name {s['name']!r} is used twice")
        after = s.get("after")
        if after is not None and after not in seen:
            raise RecipeError(f"{where}: steps[{i}] ({s['name']}): after = {after!r} names no earlier step")
        if not isinstance(s.get("build", {}), dict):
            raise RecipeError(f"{where}: steps[{i}].build must be a table")
        seen.append(s["name"])


def parse_value(text: str):
    """A --set value as TOML reads it (1e-4, true, "x", [1, 2]); a bare word is a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text
    except RecursionError:
        raise RecipeError(f"--set value {text[:40]!r}...: nested too deeply") from None


def apply_set(recipe: Recipe, item: str) -> Recipe:
    """`key=value` into the build table, or `steps.<step>.<key>=value` into one step's build."""
    key, eq, text = item.partition("=")
    key = key.strip()
    if not eq or not key:
        raise RecipeError(f"--set {item!r}: expected key=value")
    doc = copy.deepcopy(recipe.doc)
    parts = key.split(".")
    if parts[0] == "steps":
        if len(parts) != 3:
            raise RecipeError(f"--set {item!r}: expected steps.<step>.<field>=value")
        step = next((s for s in doc.get("steps", []) if s.get("name") == parts[1]), None)
        if step is None:
            raise RecipeError(f"--set {item!r}: the recipe has no step {parts[1]!r}")
        step.setdefault("build", {})[parts[2]] = parse_value(text)
    elif parts[0] == "build" and len(parts) == 2:
        doc.setdefault("build", {})[parts[1]] = parse_value(text)
    elif len(parts) == 1 and parts[0] not in TOP_KEYS:
        doc.setdefault("build", {})[parts[0]] = parse_value(text)
    else:
        raise RecipeError(f"--set {item!r}: expected a build field (key=value) or steps.<step>.<field>=value")
    validate(doc, f"--set {item!r}")
    return Recipe(recipe.name, recipe.source, doc)
