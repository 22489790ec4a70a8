"""Enabled effects of one sensor, in order, as stored in its calibration (`calibration.json`
field "effects": [{"name": ..., "params": {...}, "source": ..., "added": ...}, ...]).

The runtime applies the force-stage effects to every predicted contact force and the image-stage
gain to frames before inference; measurement-stage effects only matter when comparing with a
reference instrument (the workbench applies them to its side of the comparison).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from .base import Effect, EffectError
from .registry import Registry

log = logging.getLogger(__name__)


@dataclass
class EnabledEffect:
    effect: Effect
    params: dict

    def to_dict(self, source: str = "") -> dict:
        out = {"name": self.effect.name, "params": dict(self.params)}
        if source:
            out["source"] = source
            out["added"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        return out


class EffectChain:
    """An ordered list of enabled effects with resolved parameters."""

    def __init__(self, items: list[EnabledEffect] | None = None):
        self.items = list(items or [])

    @classmethod
    def from_list(cls, entries: list[dict], registry: Registry | None = None) -> "EffectChain":
        """From calibration.json's "effects" list; unknown names/parameters raise EffectError."""
        registry = registry or Registry.default()
        items = []
        for i, entry in enumerate(entries or []):
            name = entry.get("name") if isinstance(entry, dict) else None
            if name not in registry:
                raise EffectError(f"effects[{i}]: unknown effect {name!r} (known: {', '.join(registry.names())}; "
                                 "is its plugin installed?)")
            eff = registry.get(name)
            items.append(EnabledEffect(eff, eff.resolve(entry.get("params") or {})))
        return cls(items)

    @classmethod
    def from_calibration(cls, cal, registry: Registry | None = None) -> "EffectChain":
        return cls.from_list(cal.effects, registry)

    @property
    def names(self) -> list[str]:
        return [it.effect.name for it in self.items]

    def to_list(self) -> list[dict]:
        return [it.to_dict() for it in self.items]

    def apply(self, forces: np.ndarray, cov: dict, stages: tuple[str, ...] = ("force",)) -> np.ndarray:
        """Model forces (N,3) through every enabled effect of the given stages, in order."""
        x = np.asarray(forces, dtype=np.float64)
        for it in self.items:
            if it.effect.stage in stages:
                x = it.effect.apply(x, cov, it.params)
        return x

    def stream(self, tracks: dict, track_ids, t: float, forces: np.ndarray, cov: dict,
               stages: tuple[str, ...] = ("force",)) -> np.ndarray:
        """Frame-by-frame form for the runtime: forces (N,3) of the N contacts of one frame at time
        t, `track_ids` their stable ids, `tracks` a dict the caller keeps between frames (state of
        sequential effects per track; ids no longer present are dropped)."""
        x = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
        ids = list(track_ids)
        for k in [k for k in tracks if k not in ids]:
            del tracks[k]
        if len(x) == 0:
            return x
        for j, it in enumerate(self.items):
            if it.effect.stage not in stages:
                continue
            if it.effect.sequential:
                x = np.array([it.effect.step(tracks.setdefault(tid, {}).setdefault(j, {}), t, x[i], it.params)
                              for i, tid in enumerate(ids)]).reshape(-1, 3)
            else:
                x = it.effect.apply(x, cov, it.params)
        return x

    def image_gain(self, cov: dict, n: int) -> np.ndarray:
        """Product of the image-stage gains (n,) — divide frames by it before inference."""
        g = np.ones(n)
        for it in self.items:
            if it.effect.stage == "image":
                g = g * it.effect.gain(cov, it.params)
        return g
