"""The runtime's physical-effect stage: enabled effects (calibration store) on cluster forces.

Runs between contact clustering and the force correction (DESIGN §4). Per contact it derives the
covariates the workbench uses (runtime/stages/effects/base.py COVARIATES) from what the runtime knows:
the cluster's deformed 3D centroid against the calibrated gel cap (θ, φ, normal, distance to the
rim), its deepest inward displacement (depth), time since start, the largest depth reached so far
in the session (docs/effects.md: Mullins damage outlasts the contact that made it; tracked on every
frame with contacts, effects enabled or not, and kept across a calibration swap by the pipeline),
normal/tangential force, and the temperature when a sensor provides one. An effect whose covariate is
not available here (e.g. temperature without a thermistor) is skipped with a status flag instead of
failing the frame.
"""
from __future__ import annotations

import logging

import numpy as np

from . import EffectChain, EffectError, MissingCovariate

log = logging.getLogger(__name__)


class EffectStage:
    def __init__(self, calibration):
        self.flags: list[str] = []
        self.chain = EffectChain()
        try:
            self.chain = EffectChain.from_calibration(calibration)
        except EffectError as exc:
            log.error("%s/%s: enabled effects not usable (%s); running without them",
                      calibration.sensor_id, calibration.version, exc)
            self.flags.append("effects_invalid")
        gel = calibration.meta.get("gel") or {}
        self.radius = float(gel.get("radius_mm", 0.0))
        self.center_z = float(gel.get("center_z_mm", 0.0))
        self.skirt = float(gel.get("skirt_mm", 0.0))
        self.tracks: dict = {}
        self.max_depth = 0.0          # the largest contact depth so far in the session (mm)
        self.t0: float | None = None
        self.temperature: float | None = None

    @property
    def enabled(self) -> bool:
        return bool(self.chain.items)

    def _geometry(self, clusters) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centroid offsets from the cap centre, their distances, each contact's depth in mm)."""
        p = np.array([c.position_mm for c in clusters], dtype=np.float64).reshape(-1, 3)
        v = p - np.array([0.0, 0.0, self.center_z])
        dist = np.linalg.norm(v, axis=1)
        depth = np.clip(self.radius - dist, 0.0, None) if self.radius > 0 else np.zeros(len(p))
        # the indenter's depth: the cluster's deepest point (its force-weighted centroid sits shallower,
        # on the flank of the dent); the centroid's depth when no displacement field was clustered
        return v, dist, np.maximum(depth, [c.indentation_mm for c in clusters])

    def covariates(self, clusters, t: float) -> dict:
        v, dist, depth = self._geometry(clusters)
        f = np.array([c.force_n for c in clusters], dtype=np.float64).reshape(-1, 3)
        n = v / np.maximum(dist, 1e-9)[:, None]
        theta = np.arccos(np.clip(n[:, 2], -1.0, 1.0))
        theta_rim = float(np.arccos(np.clip((self.skirt - self.center_z) / self.radius, -1, 1))) if self.radius else 0.0
        ids = [c.id for c in clusters]
        # the largest depth so far in the session (earlier frames, any contact; the runtime cannot tell
        # indenters apart), or this contact's own depth when deeper
        maxd = np.maximum(self.max_depth, depth)
        fn = np.abs(np.sum(f * n, axis=1))
        cov = {"time": t - self.t0, "depth": depth, "max_depth": maxd, "normal": n, "theta": theta,
               "phi": np.arctan2(n[:, 1], n[:, 0]),
               "rim_distance": self.radius * np.clip(theta_rim - theta, 0.0, None) + self.skirt,
               "gel_height": np.full(len(v), self.center_z + self.radius), "force_n": fn,
               "force_t": np.sqrt(np.maximum(np.sum(f * f, axis=1) - fn ** 2, 0.0)),
               "series": np.array(ids)}
        if self.temperature is not None:
            cov["temperature"] = np.full(len(v), float(self.temperature))
        return cov

    def frame_covariates(self, clusters, t: float) -> dict:
        """The covariates of this frame's clusters, advancing the per-contact state exactly as
        `apply` does (the workbench uses it to see the runtime's covariates)."""
        if self.t0 is None:
            self.t0 = t
        if not clusters:
            return {}
        cov = self.covariates(clusters, t)
        self.max_depth = max(self.max_depth, float(np.max(cov["depth"])))
        return cov

    def apply(self, clusters, t: float) -> list[str]:
        """Correct the clusters' forces in place; returns status flags for this frame."""
        if self.t0 is None:
            self.t0 = t
        if not self.enabled:
            if clusters:      # the gel's memory (max_depth) is kept even while no effect uses it
                self.max_depth = max(self.max_depth, float(np.max(self._geometry(clusters)[2])))
            return list(self.flags)
        cov = self.frame_covariates(clusters, t)
        if not clusters:
            self.chain.stream(self.tracks, [], t, np.zeros((0, 3)), {})
            return list(self.flags)
        try:
            forces = np.array([c.force_n for c in clusters], dtype=np.float64)
            out = self.chain.stream(self.tracks, [c.id for c in clusters], t, forces, cov)
        except MissingCovariate as exc:
            if "effect_covariate_missing" not in self.flags:
                log.warning("enabled effects skipped: %s", exc)
            return self.flags + ["effect_covariate_missing"]
        for c, f in zip(clusters, out):
            c.force_n = tuple(map(float, f))
            c.force_mag_n = float(np.linalg.norm(f))
        return list(self.flags)
