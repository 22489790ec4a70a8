"""The deployed network as the workbench's model: the session's frames through the runtime's own code.

Two stages, so that changing effects or the correction never re-runs the network:

1. **Frame pass** (expensive, cached): every camera frame of the session through the runtime's
   network pass (`runtime.offline.network_passes`: preprocess, dynamic baseline, onnxruntime, contact
   clustering, stable contact ids) with the enabled effects and the correction switched off, so what
   is kept is the *raw* network result per frame: every cluster (id, centroid px/mm, normal, area,
   force, ...). Cached by the runtime under `cache/workbench/net/<key>.npz` with its one key (frames'
   content hash, model hash + precision, calibration geometry, pipeline configuration, runtime
   version). A new calibration version that only adds an effect or a correction keeps the key.
2. **Replay** (cheap, every compare): the kept passes through the runtime's own finish
   (`runtime.offline.finish_passes`: `SensorPipeline.finish` of the pipeline `open_pipeline` builds
   with the calibration -- the sensor's enabled effects with per-contact state and the session's
   temperature as the sensor's thermistor reading, then the correction, with the baseline's
   force-band check) -- the numbers the runtime would publish.

Line-up (`build_table`): one row per (frame, indenter). The measurements (F/T in the sensor frame,
mocap geometry, temperature, brightness) come from the session's mocap sample table (samples.py,
measured through tools/scoring.py), interpolated to the frame times. Each indenter gets the cluster
nearest its mocap tip (tools.scoring.match_contacts: greedy, within `match_mm`; each cluster used once). For matched rows the *effect covariates are the
runtime's* (depth, θ, φ, normal, rim distance, max depth and track id from the cluster, as
`EffectStage` computes them), so what diagnosis fits is what the runtime will apply. Position
residual = cluster centroid − mocap tip (mm). Sign: the table holds the load of the gel on the
indenter (what the F/T reads), the runtime publishes the force on the gel: model = −cluster force.
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ...contracts.errors import SessionError, TensorTouchError
from ...runtime.offline import cache_key, network_passes, pack_clusters, unpack_clusters
from ..scoring import match_contacts
from .table import SampleTable, nearest_index

log = logging.getLogger(__name__)

RUNTIME_COVARIATES = ("depth", "max_depth", "theta", "phi", "rim_distance", "force_n", "force_t")


LINEUP_VERSION = 2     # part of the cached line-up table's name: bump when lineup() changes


@dataclass(frozen=True)
class NetworkConfig:
    precision: str = "int8"
    threads: int = 1
    match_mm: float = 6.0          # a cluster further than this from an indenter's tip is not its contact


def model_sha(package, precision: str) -> str:
    """SHA-256 of the package's model file of that precision (a clear error when it has none)."""
    try:
        return package.sha256(precision)
    except KeyError:
        raise TensorTouchError(f"{package.folder / 'manifest.json'}: no {precision} model file in package "
                               f"{package.name} (has {sorted(package.manifest['files'])})") from None


# ----- stage 1: the frame pass ------------------------------------------------------------------
def pack_passes(passes: list) -> dict[str, np.ndarray]:
    """Network passes (runtime.pipeline.NetworkPass) -> flat arrays (runtime.offline.pack_clusters
    plus the frame index, time and state; "no_baseline" before the baseline exists)."""
    out = pack_clusters([p.clusters for p in passes])
    out["passes"] = passes      # kept in memory for the runtime's finish (not stored)
    out.update(frame_index=np.arange(len(passes), dtype=np.int64), frame_t=np.array([p.t for p in passes], dtype=np.float64),
               frame_state=np.array(["no_baseline" if p.state == "STARTUP" else p.state for p in passes], dtype="U16"))
    n = len(passes)
    out["_starts"] = np.searchsorted(out["cl_frame"], np.arange(n + 1))
    return out


def unpack_frame(passed: dict, j: int) -> list:
    """The clusters of frame j of packed passes, as runtime Cluster objects."""
    return unpack_clusters(passed, range(passed["_starts"][j], passed["_starts"][j + 1]))


def load_or_run_pass(session, package, cal, cfg: NetworkConfig, cache_dir: Path | None, progress=None) -> tuple[dict, dict]:
    """The raw network pass (runtime.offline.network_passes with effects and correction off, its cache
    in `cache_dir`) and its provenance {key, seconds, cached}."""
    from ...runtime.stages.correction import ForceCorrection

    if tuple(cal.model_size) != tuple(package.size):
        raise TensorTouchError(f"{cal.folder / 'calibration.json'}: model_size {list(cal.model_size)} does not "
                               f"match the model package {package.name} ({list(package.size)}); the network "
                               "path needs a calibration made for this model size")
    model_sha(package, cfg.precision)
    key = cache_key(session, package, cal, cfg.precision)
    t0 = time.perf_counter()
    passes, cached = network_passes(session, package, cal, cache=cache_dir, precision=cfg.precision, threads=cfg.threads,
                                    correction=ForceCorrection(None, None), effects=False, progress=progress)
    seconds = 0.0 if cached else time.perf_counter() - t0
    if not cached:
        log.info("network pass of %s: %d frames in %.1f s", session.path, len(passes), seconds)
    return dict(pack_passes(passes), precision=cfg.precision), {"key": key, "cached": cached, "seconds": seconds}


# ----- stage 2: replay (the runtime's finish over the kept passes) --------------------------
def replay(passed: dict, package, cal, temperature=None, correction=None, covariates: bool = False,
           model=None) -> dict:
    """The kept passes through the runtime's finish (runtime.offline.finish_passes: SensorPipeline.finish
    of the pipeline `tensortouch run` builds with `cal` — its enabled effects, then `correction` or the
    calibration's — with `temperature(t)` as the sensor's thermistor reading), frame by frame.

    Returns per cluster row: "force" (N,3) as published (force on the gel, N), "flags" per frame and
    "stale_at": the time from which the finish feeds the baseline another force band than the raw pass
    saw (None: every number is what the runtime publishes); with covariates=True also the runtime's
    effect covariates per cluster row, the correction inputs (uv, θ/φ) and the raw force. `model`: a loaded
    FieldModel of `package` to build the pipeline with (the finish never runs it; saves loading it again)."""
    from ...runtime.offline import finish_passes
    from ...runtime.pipeline import correction_inputs, open_pipeline
    from ...runtime.stages.effects.stage import EffectStage

    pipe = open_pipeline(package, cal, precision=passed.get("precision", "int8"), correction=correction, model=model)
    results, stale = finish_passes(passed["passes"], pipe, temperature)
    if stale is not None:
        log.warning("%s: with calibration %s the runtime's baseline would read other forces from %.3f s on than "
                    "the raw network pass; the deployed numbers from there are approximate", cal.sensor_id,
                    cal.version, stale)
    n_rows = len(passed["cl_frame"])
    force = np.zeros((n_rows, 3))
    cov_rows: dict[str, np.ndarray] = {}
    if covariates:
        cov_rows = {k: np.full(n_rows, np.nan) for k in RUNTIME_COVARIATES}
        cov_rows.update(normal=np.full((n_rows, 3), np.nan), uv=np.zeros((n_rows, 2)), theta_phi=np.zeros((n_rows, 2)))
        probe = EffectStage(cal)
    flags = []
    for j, (t, res) in enumerate(zip(passed["frame_t"], results)):
        rows = np.arange(passed["_starts"][j], passed["_starts"][j + 1])
        flags.append(list(res.flags))
        if passed["frame_state"][j] == "no_baseline":   # the runtime runs no stage before the baseline
            continue
        if covariates:
            clusters = unpack_frame(passed, j)
            if temperature is not None:
                probe.temperature = float(temperature(t))
            if clusters:
                cov = probe.frame_covariates(clusters, float(t))
                for k in RUNTIME_COVARIATES + ("normal",):
                    cov_rows[k][rows] = cov[k]
                cov_rows["uv"][rows], cov_rows["theta_phi"][rows] = correction_inputs(clusters, cal)
            else:
                probe.frame_covariates([], float(t))
        force[rows] = [c.force_n for c in res.clusters] if res.clusters else np.zeros((0, 3))
    return {"force": force, "flags": flags, "stale_at": stale, **cov_rows}


# ----- line-up -------------------------------------------------------------------------------
def _interp_rows(t_src: np.ndarray, t_dst: np.ndarray, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    flat = a.reshape(len(a), -1)
    out = np.column_stack([np.interp(t_dst, t_src, flat[:, j]) for j in range(flat.shape[1])])
    return out.reshape((len(t_dst),) + a.shape[1:])


def lineup(base: SampleTable, passed: dict, runtime: dict, cfg: NetworkConfig) -> SampleTable:
    """Pure core: the mocap table at the frame times + the matched clusters' raw forces and covariates."""
    ok = passed["frame_state"] != "no_baseline"
    tf, fidx = passed["frame_t"][ok], np.flatnonzero(ok)
    series = base.cols["series"]
    ids = np.unique(series)
    geom = base.meta.get("gel", {})
    center = np.array([0.0, 0.0, float(geom.get("center_z", 0.0))])
    parts = []
    for k in ids:
        m = np.flatnonzero(series == k)
        m = m[np.argsort(base.cols["t"][m])]
        tk = base.cols["t"][m]
        sel = (tf >= tk[0]) & (tf <= tk[-1])
        tq = tf[sel]
        part = {"cols": {c: _interp_rows(tk, tq, v[m]) for c, v in base.cols.items() if c not in ("series",)},
                "meas": _interp_rows(tk, tq, base.meas[m]), "frame": fidx[sel], "k": k}
        near = m[nearest_index(tk, tq)]   # the nearest row
        for c in ("brightness", "bright_ok"):   # frame measurements: nearest row, never blended
            if c in base.cols:
                part["cols"][c] = base.cols[c][near]
        vec = {}
        for c, v in base.vec.items():
            vec[c] = _interp_rows(tk, tq, v[m]) if c != "ft_rotation" else v[near]
        n = vec["normal"] / np.maximum(np.linalg.norm(vec["normal"], axis=1), 1e-12)[:, None]
        vec["normal"] = n
        part["tip"] = center + (float(geom.get("radius", 0.0)) - part["cols"]["depth"])[:, None] * n
        part["vec"] = vec
        parts.append(part)
    if not parts or not sum(len(p["frame"]) for p in parts):
        raise SessionError(f"{base.meta.get('session')}: no camera frame overlaps the measurements")
    cat = lambda get: np.concatenate([get(p) for p in parts])  # noqa: E731
    cols = {c: cat(lambda p, c=c: p["cols"][c]) for c in parts[0]["cols"]}
    vec = {c: cat(lambda p, c=c: p["vec"][c]) for c in parts[0]["vec"]}
    meas, frame, tip = cat(lambda p: p["meas"]), cat(lambda p: p["frame"]), cat(lambda p: p["tip"])
    indenter = cat(lambda p: np.full(len(p["frame"]), float(p["k"])))
    order = np.lexsort((indenter, cols["t"]))
    cols = {c: v[order] for c, v in cols.items()}
    vec = {c: v[order] for c, v in vec.items()}
    meas, frame, tip, indenter = meas[order], frame[order], tip[order], indenter[order]
    # match clusters to indenters frame by frame
    cl_row = np.full(len(frame), -1)
    starts = passed["_starts"]
    for j in np.unique(frame):
        rows = np.flatnonzero(frame == j)
        cl = np.arange(starts[j], starts[j + 1])
        got = match_contacts(tip[rows], passed["cl_position_mm"][cl], cfg.match_mm)
        cl_row[rows[got >= 0]] = cl[got[got >= 0]]
    hit = cl_row >= 0
    raw = np.zeros_like(meas)
    raw[hit] = -passed["cl_force_n"][cl_row[hit]]
    cols["mocap_depth"] = cols["depth"].copy()
    for c in RUNTIME_COVARIATES:       # the runtime's covariates where it sees the contact
        if c in runtime:
            if c not in cols:
                cols[c] = np.zeros(len(frame))
            cols[c][hit] = runtime[c][cl_row[hit]]
    vec["normal"][hit] = runtime["normal"][cl_row[hit]]
    cols["series"] = np.where(hit, passed["cl_id"][np.maximum(cl_row, 0)], -(indenter + 1))
    cols["indenter"] = indenter
    cols["frame"] = frame.astype(np.float64)
    cols["matched"] = hit.astype(np.float64)
    vec["corr_uv"] = np.where(hit[:, None], runtime["uv"][np.maximum(cl_row, 0)], 0.0)
    vec["corr_theta_phi"] = np.where(hit[:, None], runtime["theta_phi"][np.maximum(cl_row, 0)], 0.0)
    pos = np.full_like(meas, np.nan)
    pos[hit] = passed["cl_position_mm"][cl_row[hit]] - tip[hit]
    vec["position_residual"] = pos
    vec["tip"] = tip
    cols["cluster_row"] = cl_row.astype(np.float64)
    meta = dict(base.meta, model="network", unmatched_clusters=int(len(passed["cl_frame"]) - len(np.unique(cl_row[hit]))))
    return SampleTable(cols, meas, raw, vec, meta)


# ----- the ForceModel -----------------------------------------------------------------------
def temperature_of(session):
    """The session's temperature stream as the runtime reads it (runtime TemperatureTrack: the sensor's
    thermistor as a function of time), or None; from the loaded session's table (it may be changed
    in memory)."""
    from ...runtime.stages.temperature import TemperatureTrack

    if not session.has("temperature") or not len(tt := session.table("temperature")):
        return None
    return TemperatureTrack(tt[:, 0], tt[:, 1])


class NetworkModel:
    """The deployed network (a model package) as the workbench's ForceModel."""

    name = "network"

    def __init__(self, package, cfg: NetworkConfig | None = None):
        self.package, self.cfg = package, cfg or NetworkConfig()
        self.source = str(package.folder)
        self._passes: dict = {}
        self._field_model = None
        self.info: dict = {}

    def field_model(self):
        """The package's network, loaded once (the runtime's finish builds its pipeline around it)."""
        if self._field_model is None:
            from ...runtime.stages.model import FieldModel

            self._field_model = FieldModel(self.package, self.cfg.precision, self.cfg.threads)
        return self._field_model

    def fingerprint(self) -> str:
        text = json.dumps({"model": model_sha(self.package, self.cfg.precision), "cfg": asdict(self.cfg)}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def predict(self, table):  # the sample-table interface of the contact law does not apply
        raise TensorTouchError("the network model predicts from camera frames: use build_table()")

    def frame_pass(self, session, cal, cache_dir: Path | None, progress=None) -> dict:
        passed, info = load_or_run_pass(session, self.package, cal, self.cfg, cache_dir, progress)
        self._passes[str(session.path)] = passed
        self.info = info
        return passed

    def build_table(self, session, cal, base: SampleTable, folder: Path | None, cache_dir: Path | None,
                    progress=None) -> SampleTable:
        """The line-up table (raw network force in `model`), cached beside the session's table."""
        passed = self.frame_pass(session, cal, cache_dir, progress)
        path = folder / f"net{LINEUP_VERSION}-{self.info['key']}-{self.fingerprint()}.npz" if folder else None
        if path is not None and path.is_file():
            return SampleTable.load(path)
        runtime = replay(passed, self.package, cal, temperature_of(session), covariates=True, model=self.field_model())
        table = lineup(base, passed, runtime, self.cfg)
        if path is not None:
            table.save(path)
        return table

    def deployed(self, session, table: SampleTable, cal) -> tuple[np.ndarray, dict]:
        """What the runtime publishes for each row (table sign), and the replay's status flags."""
        passed = self._passes[str(session.path)]
        out = replay(passed, self.package, cal, temperature_of(session), model=self.field_model())
        rows = table.cols["cluster_row"].astype(int)
        pred = np.zeros_like(table.meas)
        pred[rows >= 0] = -out["force"][rows[rows >= 0]]
        flags = sorted({f for fl in out["flags"] for f in fl})
        return pred, {"flags": flags, "stale_at": out["stale_at"]}
