"""The runtime run offline: a recorded session through the same pipeline `tensortouch run` builds.

`replay_session(session, package, calibration)` yields, frame by frame, the `FrameResult` that
`tensortouch run --source replay:SESSION` publishes (same replay camera, same pipeline, the session's
own temperature stream for the effects). Evaluation, threshold measurement, the workbench,
recalibration and the benchmarks all replay through it and differ only in what they score.

The cache keeps network passes (`SensorPipeline.network_pass`: clusters with raw model forces, no
fields), not results, so a calibration that changes only effects or the correction re-finishes them
without running the network. Its one key: the frames' content hash, the model file hash and
precision, the calibration geometry, the pipeline configuration and the runtime version. A pass also
records the force band its baseline saw (`force_band`); when a different finish would feed the
baseline another band, the cached passes are not what the runtime would compute and the session is run
again. Stored as .npz (no pickle), written atomically.

`finish_passes` is the one finish of kept passes (the cache's, the workbench's): the pipeline's own
`SensorPipeline.finish`, with the force-band check. What the rig measured and how clusters are matched
to indenters belong to the tools that score (tools/scoring.py), not to the runtime.
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Iterator
from dataclasses import asdict, fields, replace
from pathlib import Path

import numpy as np

from ..contracts.files import atomic_write
from ..contracts.session import load_session
from ..contracts.store import Calibration, sha256_file
from ..drivers.camera import camera_from_uri
from ..drivers.camera.camera import EndOfStream
from .pipeline import (
    FrameResult,
    NetworkPass,
    PipelineConfig,
    SensorPipeline,
    force_band,
    open_pipeline,
)
from .stages.contacts import Cluster
from .stages.correction import ForceCorrection
from .stages.temperature import TemperatureTrack

log = logging.getLogger(__name__)

CLUSTER_FIELDS = tuple(f.name for f in fields(Cluster))
WIDTH = {"uv_px": 2, "position_mm": 3, "normal": 3, "force_n": 3}
INT_FIELDS = ("id", "pixels", "age_frames")
CACHE_FORMAT = 2


# ----- the cache key ------------------------------------------------------------------------------
def frames_hash(session) -> str:
    """Content hash of a session's camera frames (what the network sees) and their clock."""
    kind, src = session.image_source()
    h = hashlib.sha256((session.path / "frames.csv").read_bytes())
    if kind == "video":
        h.update(sha256_file(Path(src)).encode())
    else:
        for p in sorted(Path(src).glob("*.png")):
            h.update(p.name.encode() + sha256_file(p).encode())
    return h.hexdigest()[:20]


def geometry_key(cal: Calibration) -> dict:
    """What the network pass depends on in a calibration (not its effects or correction)."""
    files = cal.meta.get("files", {})
    return {"gel_center_px": cal.meta.get("gel_center_px"), "gel_radius_px": cal.meta.get("gel_radius_px"),
            "model_size": cal.meta.get("model_size"), "gel": cal.meta.get("gel"),
            "tables": {k: files.get(v) for k, v in sorted(cal.meta.get("tables", {}).items())}}


def runtime_version() -> str:
    """The runtime's version and a hash of its sources and of the contracts it reads (field channels,
    session format): a change to any stage re-runs the network."""
    from .. import contracts, runtime

    h = hashlib.sha256(runtime.__version__.encode())
    for pkg in (runtime, contracts):
        root = Path(pkg.__file__).parent
        for f in sorted(root.rglob("*.py")):
            h.update(f"{pkg.__name__}/{f.relative_to(root)}".encode())
            h.update(f.read_bytes())
    return f"{runtime.__version__}+{h.hexdigest()[:12]}"


def cache_key(session, package, calibration: Calibration, precision: str) -> str:
    """The one key of a cached network pass."""
    src = {"format": CACHE_FORMAT, "frames": frames_hash(session), "model": package.sha256(precision),
           "precision": precision, "geometry": geometry_key(calibration),
           "pipeline": asdict(PipelineConfig.for_package(package)), "runtime": runtime_version()}
    return hashlib.sha256(json.dumps(src, sort_keys=True, default=str).encode()).hexdigest()[:16]


# ----- one serialization of clusters and passes ---------------------------------------------------
def pack_clusters(frames: list[list[Cluster]]) -> dict[str, np.ndarray]:
    """Per-frame cluster lists → flat arrays (`cl_frame` = the frame's index in `frames`, `cl_<field>`)."""
    rows = [c for f in frames for c in f]
    out = {"cl_frame": np.array([j for j, f in enumerate(frames) for _ in f], dtype=np.int64)}
    for name in CLUSTER_FIELDS:
        w = WIDTH.get(name, 1)
        arr = np.array([getattr(c, name) for c in rows], dtype=np.float64).reshape(len(rows), w)
        out[f"cl_{name}"] = arr if w > 1 else arr[:, 0]
    return out


def unpack_clusters(packed: dict, rows) -> list[Cluster]:
    """The clusters at rows `rows` of packed arrays, as runtime Cluster objects."""
    out = []
    for i in rows:
        kw = {}
        for name in CLUSTER_FIELDS:
            v = packed[f"cl_{name}"][i]
            kw[name] = tuple(float(x) for x in v) if np.ndim(v) else float(v)
        for name in INT_FIELDS:
            kw[name] = int(kw[name])
        out.append(Cluster(**kw))
    return out


def save_passes(path: Path, passes: list[NetworkPass]) -> None:
    """Network passes (without fields) → one .npz, written atomically."""
    arrays = pack_clusters([p.clusters for p in passes])
    arrays.update(seq=np.array([p.seq for p in passes], dtype=np.int64),
                  t=np.array([p.t for p in passes], dtype=np.float64),
                  state=np.array([p.state for p in passes], dtype="U16"),
                  force_band=np.array([p.force_band for p in passes], dtype=np.int8),
                  flags=np.array([json.dumps(p.flags) for p in passes], dtype="U200"),
                  format=np.array(CACHE_FORMAT))
    atomic_write(path, lambda fh: np.savez(fh, **arrays))


def load_passes(path: Path) -> list[NetworkPass] | None:
    """Passes saved by `save_passes` (None when the file is unreadable or of another format)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        if int(a["format"]) != CACHE_FORMAT:
            return None
        starts = np.searchsorted(a["cl_frame"], np.arange(len(a["t"]) + 1))
        return [NetworkPass(int(a["seq"][j]), float(a["t"][j]), None,
                            unpack_clusters(a, range(starts[j], starts[j + 1])), str(a["state"][j]),
                            list(json.loads(str(a["flags"][j]))), {}, int(a["force_band"][j]))
                for j in range(len(a["t"]))]
    except (OSError, ValueError, KeyError) as exc:
        log.warning("%s: unreadable network-pass cache (%s); running the network again", path, exc)
        return None


# ----- the replay ---------------------------------------------------------------------------------
def _session(session):
    return load_session(session) if isinstance(session, (str, Path)) else session


def _temperature(session):
    """The session's temperature stream, as `tensortouch run` reads it for a replayed session."""
    return TemperatureTrack.from_session(session.path)


def _frames(session):
    """(image RGB, t) of every frame, through the replay camera `tensortouch run` uses."""
    with camera_from_uri(f"replay:{session.path}", realtime=False) as cam:
        while True:
            try:
                frame = cam.read()
            except EndOfStream:
                return
            yield frame.image, frame.t


def _raw(p: NetworkPass, keep_fields: bool) -> NetworkPass:
    return replace(p, fields=p.fields if keep_fields else None, clusters=[replace(c) for c in p.clusters],
                   flags=list(p.flags), timings=dict(p.timings))


def _replay(session, package, calibration, cache, precision, threads, correction, effects,
            progress=None) -> Iterator[tuple[NetworkPass, FrameResult]]:
    session = _session(session)
    temperature = _temperature(session)

    def pipeline():
        return open_pipeline(package, calibration, precision=precision, threads=threads, sensor_id=session.sensor_id,
                             correction=correction, effects=effects)

    path = Path(cache) / f"{cache_key(session, package, calibration, precision)}.npz" if cache else None
    passes = load_passes(path) if path is not None and path.is_file() else None
    if passes is not None:
        done, stale = finish_passes(passes, pipeline(), temperature)
        if stale is None:
            yield from zip(passes, done)
            return
        log.info("%s: the cached network pass saw other forces at %.3f s (another effect or correction); "
                 "running the network again", session.path, stale)
    pipe, kept = pipeline(), []
    n, t0 = len(session.table("frames")), time.perf_counter()
    for i, (image, t) in enumerate(_frames(session)):
        if temperature is not None:
            pipe.set_temperature(temperature(t))
        p = pipe.network_pass(image, t)
        raw = _raw(p, False)
        kept.append(raw)
        yield raw, pipe.finish(p, t)
        if progress is not None and (i % 200 == 0 or i == n - 1):
            progress(i + 1, n, time.perf_counter() - t0)
    if path is not None:
        save_passes(path, kept)


def finish_passes(passes: list[NetworkPass], pipe: SensorPipeline, temperature=None) -> tuple[list[FrameResult], float | None]:
    """Kept network passes (in frame order, no fields needed) through `pipe.finish` (a fresh pipeline
    from `open_pipeline`: its effects, correction and wrench), with `temperature(t)` (°C, or None) as
    the thermistor reading. The passes are not changed. Returns the results and the time of the first
    frame whose finish feeds the baseline another force band than the pass saw (None: every result is
    what the runtime publishes; otherwise the runtime's baseline would have run differently from there)."""
    done, stale = [], None
    for p in passes:
        if stale is None and force_band(pipe._last_force, pipe.cfg.baseline) != p.force_band:
            stale = p.t
        if temperature is not None:
            pipe.set_temperature(temperature(p.t))
        done.append(pipe.finish(_raw(p, False), p.t))
    return done, stale


def replay_session(session, package, calibration: Calibration, *, cache: Path | None = None,
                   precision: str = "int8", threads: int = 1, correction: ForceCorrection | None = None,
                   effects: bool = True) -> Iterator[FrameResult]:
    """What `tensortouch run --source replay:SESSION` publishes, one FrameResult per frame.

    session: a session folder or a loaded Session; package: a ModelPackage; calibration: the version
    to run with. `correction` replaces the calibration's (ForceCorrection(None, None): the raw model
    force, with effects); effects=False runs without its enabled effects. With `cache` (a folder) the
    network passes are kept there and reused; results from the cache carry no fields (None) but the
    same state, clusters, forces and flags."""
    for _, result in _replay(session, package, calibration, cache, precision, threads, correction, effects):
        yield result


def network_passes(session, package, calibration: Calibration, *, cache: Path | None = None,
                   precision: str = "int8", threads: int = 1, correction: ForceCorrection | None = None,
                   effects: bool = True, progress=None) -> tuple[list[NetworkPass], bool]:
    """Every frame's network pass (raw clusters, no fields) as `replay_session` with the same
    arguments runs it, and whether it came from the cache. `progress(frames done, frames, seconds)`
    is called while the network runs."""
    passes, ran = [], False
    gen = _replay(session, package, calibration, cache, precision, threads, correction, effects, progress)
    for p, _ in gen:
        passes.append(p)
        ran = ran or bool(p.timings)
    return passes, not ran
