"""The deployed network as the workbench's model: the session's frames through the runtime's own code.

Two stages, so that changing effects or the correction never re-runs the network:

1. **Frame pass** (expensive, cached): every camera frame of the session goes through
   `runtime.pipeline.SensorPipeline` -- preprocess, dynamic baseline, onnxruntime, contact clustering,
   stable contact ids -- with the enabled effects and the correction switched off, so what is kept
   is the *raw* network result per frame: every cluster (id, centroid px/mm, normal, area, force, ...).
   Cached under `cache/workbench/net/<key>.npz`, key = (frames' content hash, model package file
   hash + precision, calibration geometry: gel circle, model size, θ/φ tables, gel cap, pipeline
   configuration). A new calibration version that only adds an effect or a correction keeps the key.
2. **Replay** (cheap, every compare): the cached clusters frame by frame through the runtime's
   `EffectStage` (the sensor's enabled effects, per-contact state, the session's temperature as the
   sensor's thermistor reading) and then the runtime's `ForceCorrection`, in the order and with the
   arithmetic of `SensorPipeline.process` -- the numbers the runtime would publish.

Line-up (`build_table`): one row per (frame, indenter). The measurements (F/T in the sensor frame,
mocap geometry, temperature, brightness) come from the session's mocap sample table (samples.py),
interpolated to the frame times. Each indenter gets the cluster nearest its mocap tip (greedy,
within `match_mm`; each cluster used once). For matched rows the *effect covariates are the
runtime's* (depth, θ, φ, normal, rim distance, max depth and track id from the cluster, as
`EffectStage` computes them), so what diagnosis fits is what the runtime will apply. Position
residual = cluster centroid − mocap tip (mm). Sign: the table holds the load of the gel on the
indenter (what the F/T reads), the runtime publishes the force on the gel: model = −cluster force.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from runtime.calibration import sha256_file
from runtime.errors import SessionError, TensorTouchError
from tools.workbench.table import SampleTable, nearest_index

log = logging.getLogger(__name__)

CLUSTER_FIELDS = ("id", "centroid_px", "centroid_mm", "normal", "area_mm2", "force_n", "force_mag_n",
                  "pixels", "perimeter_px", "circularity", "priority", "age", "indentation_mm")
WIDTH = {"centroid_px": 2, "centroid_mm": 3, "normal": 3, "force_n": 3}
PASS_MODULES = ("pipeline.py", "preprocess.py", "baseline.py", "model.py", "contacts.py", "geometry.py")
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


def frames_hash(session) -> str:
    """Content hash of the session's camera frames (what the network sees)."""
    kind, src = session.image_source()
    h = hashlib.sha256((session.path / "frames.csv").read_bytes())
    if kind == "video":
        h.update(sha256_file(Path(src)).encode())
    else:
        for p in sorted(Path(src).glob("*.png")):
            h.update(p.name.encode() + sha256_file(p).encode())
    return h.hexdigest()[:20]


def geometry_key(cal) -> dict:
    """What the network pass depends on in a calibration (not its effects or correction)."""
    files = cal.meta.get("files", {})
    return {"gel_center_px": cal.meta.get("gel_center_px"), "gel_radius_px": cal.meta.get("gel_radius_px"),
            "model_size": cal.meta.get("model_size"), "gel": cal.meta.get("gel"),
            "tables": {k: files.get(v) for k, v in sorted(cal.meta.get("tables", {}).items())}}


def runtime_code_hash() -> str:
    """Hash of the runtime modules the frame pass runs (a code change re-runs the network)."""
    import runtime

    h = hashlib.sha256()
    for name in PASS_MODULES:
        h.update((Path(runtime.__file__).parent / name).read_bytes())
    return h.hexdigest()[:16]


# ----- stage 1: the frame pass ------------------------------------------------------------------
def pack_clusters(frames: list[tuple[int, float, str, list]]) -> dict[str, np.ndarray]:
    """Per-frame results [(frame index, t, state, clusters)] -> flat arrays (npz-able)."""
    out = {"frame_index": np.array([f[0] for f in frames], dtype=np.int64),
           "frame_t": np.array([f[1] for f in frames], dtype=np.float64),
           "frame_state": np.array([f[2] for f in frames], dtype="U16"),
           "cl_frame": np.array([j for j, f in enumerate(frames) for _ in f[3]], dtype=np.int64)}
    rows = [c for f in frames for c in f[3]]
    for name in CLUSTER_FIELDS:
        w = WIDTH.get(name, 1)
        arr = np.array([getattr(c, name) for c in rows], dtype=np.float64).reshape(len(rows), w)
        out[f"cl_{name}"] = arr if w > 1 else arr[:, 0]
    return out


def unpack_frame(passed: dict, j: int) -> list:
    """The clusters of frame j of a packed pass, as runtime Cluster objects."""
    from runtime.contacts import Cluster

    idx = np.flatnonzero(passed["cl_frame"] == j) if "_starts" not in passed else \
        np.arange(passed["_starts"][j], passed["_starts"][j + 1])
    out = []
    for i in idx:
        kw = {}
        for name in CLUSTER_FIELDS:
            v = passed[f"cl_{name}"][i]
            kw[name] = tuple(float(x) for x in v) if np.ndim(v) else float(v)
        for name in ("id", "pixels", "age"):
            kw[name] = int(kw[name])
        out.append(Cluster(**kw))
    return out


def _index(passed: dict) -> dict:
    n = len(passed["frame_t"])
    passed["_starts"] = np.searchsorted(passed["cl_frame"], np.arange(n + 1))
    return passed


def run_frame_pass(session, package, cal, cfg: NetworkConfig, progress=None) -> dict:
    """Every frame through SensorPipeline with effects and correction off (the raw network result)."""
    import cv2

    from runtime.correction import ForceCorrection
    from runtime.effects import EffectChain
    from runtime.model import FieldModel
    from runtime.pipeline import SensorPipeline
    from tools.sessions.writer import read_frames

    if tuple(cal.model_size) != tuple(package.size):
        raise TensorTouchError(f"{cal.folder / 'calibration.json'}: model_size {list(cal.model_size)} does not "
                               f"match the model package {package.name} ({list(package.size)}); the network "
                               "path needs a calibration made for this model size")
    pipe = SensorPipeline(session.sensor_id, FieldModel(package, cfg.precision, cfg.threads), cal,
                          correction=ForceCorrection(None, None))
    pipe.effects.chain = EffectChain()        # raw clusters: effects are replayed later
    times = session.table("frames")[:, 0]
    out, t0 = [], time.perf_counter()
    for i, img in read_frames(session):
        res = pipe.process(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), float(times[i]))
        out.append((i, float(times[i]), res.state if res.fields is not None else "no_baseline", res.clusters))
        if progress and (i % 200 == 0 or i == len(times) - 1):
            progress(i + 1, len(times), time.perf_counter() - t0)
    return pack_clusters(out)


def load_or_run_pass(session, package, cal, cfg: NetworkConfig, cache_dir: Path | None, progress=None) -> tuple[dict, dict]:
    """The (cached) frame pass and its provenance {key, seconds, cached}."""
    from runtime.pipeline import PipelineConfig

    key_src = {"frames": frames_hash(session), "model": model_sha(package, cfg.precision), "precision": cfg.precision,
               "geometry": geometry_key(cal), "pipeline": asdict(PipelineConfig.for_package(package)), "code": runtime_code_hash()}
    key = hashlib.sha256(json.dumps(key_src, sort_keys=True, default=str).encode()).hexdigest()[:16]
    path = cache_dir / f"{key}.npz" if cache_dir else None
    if path is not None and path.is_file():
        with np.load(path, allow_pickle=False) as z:
            return _index({k: z[k] for k in z.files}), {"key": key, "cached": True, "seconds": 0.0}
    t0 = time.perf_counter()
    passed = run_frame_pass(session, package, cal, cfg, progress)
    seconds = time.perf_counter() - t0
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, **passed)
        tmp.replace(path)
    log.info("network pass of %s: %d frames in %.1f s", session.path, len(passed["frame_t"]), seconds)
    return _index(passed), {"key": key, "cached": False, "seconds": seconds}


# ----- stage 2: replay (the runtime's effect stage + correction over cached clusters) ----------
def correction_inputs(clusters: list, cal) -> tuple[np.ndarray, np.ndarray]:
    """(uv (N,2) in [0,1], θ/φ (N,2) rad) of cluster centroids, as SensorPipeline.process computes them."""
    from runtime.geometry import sample_bilinear

    h, w = cal.model_size
    uv = np.array([c.centroid_px for c in clusters], dtype=np.float64).reshape(-1, 2) * np.array([1.0 / w, 1.0 / h])
    tp = np.array([[sample_bilinear(cal.theta, u - 0.5, v - 0.5), sample_bilinear(cal.phi, u - 0.5, v - 0.5)]
                   for u, v in (c.centroid_px for c in clusters)], dtype=np.float64).reshape(-1, 2)
    return uv, tp


def replay(passed: dict, cal, temperature=None, correction=None, covariates: bool = False) -> dict:
    """Cached clusters through EffectStage(cal) and the correction, frame by frame.

    Returns per cluster row: "force" (N,3) as published (force on the gel, N), "flags" per frame;
    with covariates=True also the runtime's effect covariates per cluster row, the correction inputs
    (uv, θ/φ) and the raw force."""
    from runtime.correction import ForceCorrection
    from runtime.effect_stage import EffectStage

    stage = EffectStage(cal)
    corr = correction if correction is not None else ForceCorrection.from_calibration(cal)
    n_rows = len(passed["cl_frame"])
    force = np.zeros((n_rows, 3))
    cov_rows: dict[str, np.ndarray] = {}
    if covariates:
        cov_rows = {k: np.full(n_rows, np.nan) for k in RUNTIME_COVARIATES}
        cov_rows.update(normal=np.full((n_rows, 3), np.nan), uv=np.zeros((n_rows, 2)), theta_phi=np.zeros((n_rows, 2)))
        probe = EffectStage(cal)
    flags = []
    for j, t in enumerate(passed["frame_t"]):
        if passed["frame_state"][j] == "no_baseline":   # the runtime runs no stage before the baseline
            flags.append([])
            continue
        clusters = unpack_frame(passed, j)
        rows = np.arange(passed["_starts"][j], passed["_starts"][j + 1])
        if temperature is not None:
            stage.temperature = float(temperature(t))
        if covariates and clusters:
            cov = probe.frame_covariates(clusters, float(t))
            for k in RUNTIME_COVARIATES + ("normal",):
                cov_rows[k][rows] = cov[k]
            cov_rows["uv"][rows], cov_rows["theta_phi"][rows] = correction_inputs(clusters, cal)
        elif covariates:
            probe.frame_covariates([], float(t))
        flags.append(stage.apply(clusters, float(t)))
        if clusters and corr.enabled:
            f = np.array([c.force_n for c in clusters])
            uv, tp = correction_inputs(clusters, cal)
            for c, g in zip(clusters, corr(f, uv, tp)):
                c.force_n = tuple(map(float, g))
        force[rows] = [c.force_n for c in clusters] if clusters else np.zeros((0, 3))
    return {"force": force, "flags": flags, **cov_rows}


# ----- line-up -------------------------------------------------------------------------------
def _interp_rows(t_src: np.ndarray, t_dst: np.ndarray, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    flat = a.reshape(len(a), -1)
    out = np.column_stack([np.interp(t_dst, t_src, flat[:, j]) for j in range(flat.shape[1])])
    return out.reshape((len(t_dst),) + a.shape[1:])


def match(tips: np.ndarray, centroids: np.ndarray, max_mm: float) -> np.ndarray:
    """Greedy nearest pairs tip k <-> cluster c within max_mm, each used once; (K,) cluster index or -1."""
    out = np.full(len(tips), -1)
    if len(tips) == 0 or len(centroids) == 0:
        return out
    d = np.linalg.norm(tips[:, None, :] - centroids[None, :, :], axis=2)
    for flat in np.argsort(d, axis=None):
        k, c = np.unravel_index(flat, d.shape)
        if d[k, c] > max_mm:
            break
        if out[k] < 0 and c not in out:
            out[k] = c
    return out


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
        got = match(tip[rows], passed["cl_centroid_mm"][cl], cfg.match_mm)
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
    pos[hit] = passed["cl_centroid_mm"][cl_row[hit]] - tip[hit]
    vec["position_residual"] = pos
    vec["tip"] = tip
    cols["cluster_row"] = cl_row.astype(np.float64)
    meta = dict(base.meta, model="network", unmatched_clusters=int(len(passed["cl_frame"]) - len(np.unique(cl_row[hit]))))
    return SampleTable(cols, meas, raw, vec, meta)


# ----- the ForceModel -----------------------------------------------------------------------
def temperature_of(session):
    """The session's temperature stream as a function of time (the sensor's thermistor), or None."""
    if not session.has("temperature"):
        return None
    tt = session.table("temperature")
    return lambda t: float(np.interp(t, tt[:, 0], tt[:, 1]))


class NetworkModel:
    """The deployed network (a model package) as the workbench's ForceModel."""

    name = "network"

    def __init__(self, package, cfg: NetworkConfig | None = None):
        self.package, self.cfg = package, cfg or NetworkConfig()
        self.source = str(package.folder)
        self._passes: dict = {}
        self.info: dict = {}

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
        runtime = replay(passed, cal, temperature_of(session), covariates=True)
        table = lineup(base, passed, runtime, self.cfg)
        if path is not None:
            table.save(path)
        return table

    def deployed(self, session, table: SampleTable, cal) -> tuple[np.ndarray, dict]:
        """What the runtime publishes for each row (table sign), and the replay's status flags."""
        passed = self._passes[str(session.path)]
        out = replay(passed, cal, temperature_of(session))
        rows = table.cols["cluster_row"].astype(int)
        pred = np.zeros_like(table.meas)
        pred[rows >= 0] = -out["force"][rows[rows >= 0]]
        flags = sorted({f for fl in out["flags"] for f in fl})
        return pred, {"flags": flags}
