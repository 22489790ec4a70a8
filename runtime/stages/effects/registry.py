"""Effect registry: the built-in library, plugin folders and the `tensortouch.effects` entry points.

A plugin is any `Effect` subclass with a `name`, defined in a `.py` file of a plugin folder
(`Registry.load_directory`, or every folder in the TENSORTOUCH_EFFECTS_PATH environment variable,
separated by os.pathsep) or exported by an entry point of the group `tensortouch.effects`
(the entry point may name the class itself or a module holding such classes). A plugin may not
reuse a library name.
"""
from __future__ import annotations

import importlib.util
import inspect
import logging
import os
import sys
from importlib import metadata
from pathlib import Path

from .base import COVARIATES, STAGES, Effect, EffectError
from .builtin import BUILTIN
from .flexible import FLEXIBLE

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "tensortouch.effects"
PATH_ENV = "TENSORTOUCH_EFFECTS_PATH"


def check_effect_class(cls) -> None:
    """Raise ValueError naming what a plugin class gets wrong."""
    where = getattr(cls, "__module__", "?") + "." + getattr(cls, "__name__", "?")
    if not (inspect.isclass(cls) and issubclass(cls, Effect)):
        raise EffectError(f"{where}: not a subclass of runtime.stages.effects.Effect")
    if not cls.name or not isinstance(cls.name, str):
        raise EffectError(f"{where}: class attribute `name` must be a non-empty string")
    if cls.stage not in STAGES:
        raise EffectError(f"{where}: stage {cls.stage!r} not in {STAGES}")
    if not cls.params:
        raise EffectError(f"{where}: needs at least one Param in `params`")
    for p in cls.params:
        if not (p.lo <= p.default <= p.hi):
            raise EffectError(f"{where}: parameter {p.name} default {p.default} outside [{p.lo}, {p.hi}]")
    unknown = [c for c in cls.covariates if c not in COVARIATES]
    if unknown:
        raise EffectError(f"{where}: unknown covariates {unknown} (known: {sorted(COVARIATES)})")
    if cls.forward is Effect.forward:
        raise EffectError(f"{where}: forward() not written")
    cls().resolve(cls.off)  # the identity values must be within bounds


class Registry:
    """Name -> Effect instance. `Registry.default()` = library + env folders + entry points."""

    def __init__(self):
        self._effects: dict[str, Effect] = {}
        self.origin: dict[str, str] = {}
        self.problems: list[str] = []

    def add(self, cls, origin: str = "library") -> Effect:
        check_effect_class(cls)
        if cls.name in self._effects and self.origin[cls.name] != origin:
            raise EffectError(f"effect name {cls.name!r} from {origin} is already taken "
                             f"(by {self.origin[cls.name]})")
        self._effects[cls.name] = cls()
        self.origin[cls.name] = origin
        return self._effects[cls.name]

    def get(self, name: str) -> Effect:
        if name not in self._effects:
            raise EffectError(f"unknown effect {name!r}; known: {', '.join(self.names())}")
        return self._effects[name]

    def __contains__(self, name: str) -> bool:
        return name in self._effects

    def names(self) -> list[str]:
        return list(self._effects)

    def effects(self) -> list[Effect]:
        return list(self._effects.values())

    # ----- discovery ---------------------------------------------------------------------------
    def load_builtins(self) -> "Registry":
        for cls in BUILTIN + FLEXIBLE:
            self.add(cls, "library")
        return self

    def load_file(self, path: str | Path) -> list[str]:
        """Import one plugin file and add every Effect subclass defined in it."""
        path = Path(path)
        mod_name = f"tensortouch_effect_plugin_{path.stem}_{abs(hash(str(path.resolve()))) % 10**8}"
        spec = importlib.util.spec_from_file_location(mod_name, path)
        if spec is None or spec.loader is None:
            raise EffectError(f"{path}: cannot import as a Python module")
        module = importlib.util.module_from_spec(spec)
        sys.modules[mod_name] = module
        try:
            spec.loader.exec_module(module)
        except Exception as exc:
            sys.modules.pop(mod_name, None)
            raise EffectError(f"{path}: plugin failed to import ({type(exc).__name__}: {exc})") from None
        return self._add_module_classes(module, str(path))

    def _add_module_classes(self, module, origin: str) -> list[str]:
        added = []
        for _, obj in inspect.getmembers(module, inspect.isclass):
            if issubclass(obj, Effect) and obj is not Effect and obj.__module__ == module.__name__ \
                    and getattr(obj, "name", ""):
                self.add(obj, origin)
                added.append(obj.name)
        return added

    def load_directory(self, folder: str | Path) -> list[str]:
        """Add the effects of every `*.py` file in `folder` (files starting with '_' skipped)."""
        folder = Path(folder)
        if not folder.is_dir():
            raise EffectError(f"{folder}: effect plugin folder does not exist")
        added = []
        for path in sorted(folder.glob("*.py")):
            if path.name.startswith("_"):
                continue
            added += self.load_file(path)
        log.info("effect plugins from %s: %s", folder, ", ".join(added) or "none")
        return added

    def load_entry_points(self) -> list[str]:
        added = []
        for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
            try:
                obj = ep.load()
                if inspect.isclass(obj):
                    self.add(obj, f"entry point {ep.name}")
                    added.append(obj.name)
                else:
                    added += self._add_module_classes(obj, f"entry point {ep.name}")
            except Exception as exc:  # a broken plugin must not take the library down
                self.problems.append(f"entry point {ep.name}: {exc}")
                log.warning("effect entry point %s skipped: %s", ep.name, exc)
        return added

    @classmethod
    def default(cls, plugin_dirs: list[str | Path] | None = None, entry_points: bool = True) -> "Registry":
        reg = cls().load_builtins()
        dirs = [d for d in os.environ.get(PATH_ENV, "").split(os.pathsep) if d]
        for d in dirs + [str(x) for x in plugin_dirs or []]:
            reg.load_directory(d)
        if entry_points:
            reg.load_entry_points()
        return reg
