"""Batch runner: many scenarios, both cores, progress, on-disk cache keyed by scenario hash, resume.

Layout of the cache folder (default runtime.paths.cache_dir()/fe):
    <hash>.npz            the result (written atomically, so an interrupted run leaves no half file)
    <hash>.failed.json    the error of a scenario that failed (skipped on resume unless retry_failed)
    index.json            scenario file -> hash, status, seconds (rewritten atomically after each job)
A rerun skips every hash whose .npz exists: killing the batch and starting it again resumes it.
"""
from __future__ import annotations

import json
import logging
import os
import sys
import time
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from tools.fe.errors import FEError, ScenarioError
from tools.fe.scenario import load_scenario

log = logging.getLogger(__name__)


def default_dir() -> Path:
    from runtime.paths import cache_dir

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


def _write_json(path: Path, data) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True))
    tmp.replace(path)


def _job(scenario_path: str, out_path: str) -> dict:
    """Worker: solve one scenario file and store its result (runs in a child process)."""
    from tools.fe.result import save_result
    from tools.fe.solver import solve

    t0 = time.time()
    try:
        result = solve(load_scenario(scenario_path))
        save_result(result, out_path)
        return {"status": "solved", "seconds": round(time.time() - t0, 2)}
    except FEError as exc:
        return {"status": "failed", "error": f"{type(exc).__name__}: {exc}", "seconds": round(time.time() - t0, 2)}


def _bar(done: int, total: int, t0: float, label: str) -> None:
    width = 30
    fill = int(width * done / max(total, 1))
    eta = (time.time() - t0) / max(done, 1) * (total - done)
    print(f"\r[{'#' * fill}{'.' * (width - fill)}] {done}/{total} eta {eta:5.0f} s  {label[:40]:40s}",
          end="", file=sys.stderr, flush=True)


def run_batch(scenarios, out_dir=None, workers: int = 2, retry_failed: bool = False) -> dict:
    """Solve every scenario not yet in the cache; returns counts and the cache folder."""
    out = Path(out_dir) if out_dir else default_dir()
    out.mkdir(parents=True, exist_ok=True)
    paths = _expand(scenarios)
    index_path = out / "index.json"
    index = json.loads(index_path.read_text()) if index_path.is_file() else {}
    todo, cached = [], 0
    for p in paths:
        h = load_scenario(p).hash()
        npz, failed = out / f"{h}.npz", out / f"{h}.failed.json"
        if npz.is_file():
            cached += 1
            index[str(p)] = {**index.get(str(p), {}), "hash": h, "status": "solved"}
        elif failed.is_file() and not retry_failed:
            index[str(p)] = {"hash": h, "status": "failed", **json.loads(failed.read_text())}
        else:
            todo.append((p, h))
    solved = 0
    log.info("batch: %d scenarios, %d cached, %d to solve with %d workers", len(paths), cached, len(todo), workers)
    t0 = time.time()
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # one BLAS thread per worker process
    workers = max(1, min(workers, len(todo) or 1))
    # spawn, not fork: gmsh and BLAS thread pools deadlock in forked children
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(_job, str(p), str(out / f"{h}.npz")): (p, h) for p, h in todo}
        for n, fut in enumerate(as_completed(futures), 1):
            p, h = futures[fut]
            info = fut.result()
            index[str(p)] = {"hash": h, **info}
            if info["status"] == "failed":
                _write_json(out / f"{h}.failed.json", info)
            else:
                solved += 1
            _write_json(index_path, index)
            _bar(n, len(todo), t0, f"{p.name}: {info['status']}")
    if todo:
        print(file=sys.stderr)
    failed = sum(index[str(p)]["status"] == "failed" for p in paths)
    return {"solved": solved, "cached": cached, "failed": failed, "out_dir": str(out), "index": str(index_path)}
