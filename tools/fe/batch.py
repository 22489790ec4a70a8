"""Batch runner: many scenarios, both cores or a cluster, progress, on-disk cache keyed by scenario
hash, resume.

Executors: the local process pool (default, `workers` processes) or an existing Dask.distributed
cluster (`cluster="tcp://host:8786"`, extra `cluster`; docs/decisions/2026-11-25-distributed-fe.md).
Both run the same job, `solve_payload`: the client packs the scenario as JSON plus the bytes of
the files it references (mesh indenters, STL gels), the worker solves it in a scratch folder and
returns the result file's bytes, and the client writes them into the cache. So a remote worker
needs the package installed but no shared filesystem, and cache, index and resume are the same.

Layout of the cache folder (default contracts.paths.cache_dir()/fe):
    <hash>.npz            the result (written atomically, so an interrupted run leaves no half file)
    <hash>.failed.json    the error of a scenario that failed (skipped on resume unless retry_failed)
    index.json            scenario file -> hash, status, seconds (rewritten atomically after each job)
A rerun skips every hash whose .npz exists: killing the batch and starting it again resumes it.
"""
from __future__ import annotations

import json
import logging
import multiprocessing
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from ...contracts.files import atomic_write, atomic_write_json
from ..progress import stage_progress
from .errors import FEError, ScenarioError
from .scenario import load_scenario

log = logging.getLogger(__name__)
CONNECT_TIMEOUT = "30s"  # to reach a Dask scheduler


def default_dir() -> Path:
    from ...contracts.paths import cache_dir

    return cache_dir() / "fe"


def _expand(items) -> list[Path]:
    paths = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            paths += sorted(q for q in p.iterdir() if q.suffix.lower() in (".json", ".toml"))
        elif p.is_file():
            paths.append(p)
        else:
            raise ScenarioError(f"{p}: scenario file or folder not found")
    return paths



def make_payload(scenario) -> dict:
    """Everything a worker without our filesystem needs: the scenario (referenced files renamed
    ref<i>_<name>) and those files' bytes, plus the original JSON and hash stored in the result."""
    data = scenario.to_dict()
    files = {}

    def ship(path_str: str) -> str:
        src = scenario.resolve(path_str)
        name = f"ref{len(files)}_{src.name}"
        files[name] = src.read_bytes()
        return name

    for ind in data["indenters"]:
        if ind["shape"] == "mesh":
            ind["mesh_path"] = ship(ind["mesh_path"])
    if data["gel"]["kind"] == "stl":
        data["gel"]["stl_path"] = ship(data["gel"]["stl_path"])
    return {"scenario": data, "files": files, "scenario_json": scenario.to_json(), "hash": scenario.hash()}


def solve_payload(payload: dict) -> dict:
    """The job (local pool process or cluster worker): solve one packed scenario; returns
    {"status", "seconds", "npz": result file bytes} or {"status": "failed", "error", "seconds"}."""
    from .result import save_result
    from .scenario import scenario_from_dict
    from .solver import solve

    t0 = time.time()
    try:
        with tempfile.TemporaryDirectory(prefix="tt-fe-") as tmp:
            for name, data in payload["files"].items():
                (Path(tmp) / name).write_bytes(data)
            scenario = scenario_from_dict(payload["scenario"], base_dir=tmp, source=f"scenario {payload['hash']}")
            result = solve(scenario)
            result.scenario_json, result.scenario_hash = payload["scenario_json"], payload["hash"]
            out = save_result(result, Path(tmp) / "result.npz")
            return {"status": "solved", "seconds": round(time.time() - t0, 2), "npz": out.read_bytes()}
    except FEError as exc:
        return {"status": "failed", "error": f"{type(exc).__name__}: {exc}", "seconds": round(time.time() - t0, 2)}



def _local_pool(jobs, workers: int):
    """Yield (key, info) as the local process pool finishes `jobs` [(key, payload), ...]."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # one BLAS thread per worker process
    workers = max(1, min(workers, len(jobs) or 1))
    if workers > 1:  # one PARDISO thread per worker whatever the caller asked (the same bits, tools.fe.linsolve)
        os.environ["TENSORTOUCH_FE_THREADS"] = "1"
    # spawn, not fork: gmsh and BLAS thread pools deadlock in forked children
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(solve_payload, payload): key for key, payload in jobs}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()


def _dask_cluster(jobs, address: str):
    """Yield (key, info) as the Dask.distributed cluster at `address` finishes `jobs`."""
    try:
        from distributed import Client
        from distributed import as_completed as dask_completed
    except ImportError as exc:
        from ...contracts.extras import hint

        raise FEError(f"--cluster {hint('cluster', exc.name)}") from None
    try:
        client = Client(address, timeout=CONNECT_TIMEOUT)
    except (OSError, TimeoutError) as exc:
        raise FEError(f"--cluster {address}: cannot connect to a Dask scheduler ({exc})") from exc
    with client:
        futures = {client.submit(solve_payload, payload, key=f"tt-fe-{h}", pure=False): (p, h)
                   for (p, h), payload in jobs}
        for fut in dask_completed(list(futures)):
            key = futures[fut]
            info = fut.result()
            fut.release()
            yield key, info


def run_batch(scenarios, out_dir=None, workers: int = 2, retry_failed: bool = False,
              cluster: str | None = None) -> dict:
    """Solve every scenario not yet in the cache; returns counts and the cache folder.
    `cluster`: address of a Dask.distributed scheduler (tcp://host:8786); None = local process pool."""
    out = Path(out_dir) if out_dir else default_dir()
    out.mkdir(parents=True, exist_ok=True)
    paths = _expand(scenarios)
    index_path = out / "index.json"
    index = json.loads(index_path.read_text()) if index_path.is_file() else {}
    todo, cached, scenarios_by_path = [], 0, {}
    for p in paths:
        sc = load_scenario(p)
        h = sc.hash()
        scenarios_by_path[p] = sc
        npz, failed = out / f"{h}.npz", out / f"{h}.failed.json"
        if npz.is_file():
            cached += 1
            index[str(p)] = {**index.get(str(p), {}), "hash": h, "status": "solved"}
        elif failed.is_file() and not retry_failed:
            index[str(p)] = {"hash": h, "status": "failed", **json.loads(failed.read_text())}
        else:
            todo.append((p, h))
    solved = 0
    where = f"cluster {cluster}" if cluster else f"{workers} local workers"
    log.info("batch: %d scenarios, %d cached, %d to solve on %s", len(paths), cached, len(todo), where)
    jobs = [((p, h), make_payload(scenarios_by_path[p])) for p, h in todo]
    done = _dask_cluster(jobs, cluster) if cluster else _local_pool(jobs, workers)
    bar = stage_progress("fe batch", "scenario")
    for n, ((p, h), info) in enumerate(done, 1):
        npz = info.pop("npz", None)
        if info["status"] == "failed":
            atomic_write_json(out / f"{h}.failed.json", info, indent=2, sort_keys=True)
        else:
            atomic_write(out / f"{h}.npz", npz)
            (out / f"{h}.failed.json").unlink(missing_ok=True)
            solved += 1
        index[str(p)] = {"hash": h, **info}
        atomic_write_json(index_path, index, indent=2, sort_keys=True)
        bar("", n, len(todo))
    failed = sum(index[str(p)]["status"] == "failed" for p in paths)
    return {"solved": solved, "cached": cached, "failed": failed, "out_dir": str(out), "index": str(index_path)}
