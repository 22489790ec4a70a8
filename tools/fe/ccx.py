"""Run a CalculiX deck written by `tools.fe.inp.export_inp_ccx` and read the indenter reactions.

`run_ccx(deck)` calls the `ccx` executable (Debian package `calculix-ccx`, 2.20) in the deck's folder
and returns the wall time; `read_reactions(dat)` parses the `*NODE PRINT` blocks of the `.dat` file
(one per converged increment) into the reaction at each indenter's reference node at the end of
every step. Same sign as tools.fe's `RF`: the force the indenter applies to the gel (pressing gives
RF_z < 0). `crosscheck(scenario, workdir)` solves one scenario in both solvers from the deck as
written (the `tensortouch fe crosscheck` command and tests/test_fe_ccx.py use it).
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

from .errors import FEError

_BLOCK = re.compile(r"forces \(fx,fy,fz\) for set (\S+) and time\s+(\S+)")


class CalculiXError(FEError):
    """ccx is missing, failed, or wrote no reactions."""


def find_ccx() -> str | None:
    """Path of the ccx executable, or None."""
    return shutil.which("ccx") or shutil.which("ccx_2.20")


def run_ccx(deck, threads: int = 1, timeout: float = 3600.0) -> float:
    """Solve `deck` (.inp) with ccx in its folder; returns the wall time (s). Output: <stem>.dat etc."""
    exe = find_ccx()
    if exe is None:
        raise CalculiXError("ccx not found on PATH (Debian: apt-get install -y calculix-ccx)")
    deck = Path(deck)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "CCX_NPROC_EQUATION_SOLVER": str(threads)}
    t0 = time.time()
    with open(deck.with_suffix(".log"), "w") as log:
        proc = subprocess.run([exe, "-i", deck.stem], check=False, cwd=deck.parent, stdout=log, stderr=subprocess.STDOUT,
                              env=env, timeout=timeout)
    seconds = time.time() - t0
    text = deck.with_suffix(".log").read_text(errors="replace")
    if proc.returncode != 0 or "*ERROR" in text:
        err = next((ln.strip() for ln in text.splitlines() if "ERROR" in ln), f"exit code {proc.returncode}")
        raise CalculiXError(f"{deck}: ccx failed: {err} (log {deck.with_suffix('.log')})")
    return seconds


def read_reactions(dat, n_steps: int) -> dict[str, np.ndarray]:
    """Reference-node reactions per node set at the end of each step: {set: (n_steps, 3)}.

    ccx prints one block per converged increment, stamped with the total time (step j ends at
    total time j + 1, each step having period 1)."""
    lines = Path(dat).read_text().splitlines()
    found: dict[str, dict[int, np.ndarray]] = {}
    for i, line in enumerate(lines):
        m = _BLOCK.search(line)
        if not m:
            continue
        name, t = m.group(1), float(m.group(2))
        vals = next(ln.split() for ln in lines[i + 1:] if ln.strip())
        step = round(t) - 1
        if abs(t - round(t)) < 1e-6 and 0 <= step < n_steps:
            found.setdefault(name, {})[step] = np.array([float(v) for v in vals[1:4]])
    out = {}
    for name, steps in found.items():
        missing = [j + 1 for j in range(n_steps) if j not in steps]
        if missing:
            raise CalculiXError(f"{dat}: no reaction for {name} at the end of steps {missing}")
        out[name] = np.stack([steps[j] for j in range(n_steps)])
    if not out:
        raise CalculiXError(f"{dat}: no *NODE PRINT reaction blocks")
    return out


def crosscheck(scenario, workdir, bulk: str = "solver", threads: int = 1,
               max_increment_mm: float | None = None) -> dict:
    """Solve `scenario` with tools.fe and with ccx from the exported deck on the same mesh.

    Returns {"ours", "ccx": RF (F,K,3) N; "ours_moment", "ccx_moment": (F,K,3) N·mm about the
    reference point (ccx: the reaction at the rotation node); "seconds_ours", "seconds_ccx", "deck"}."""
    from .inp import export_inp_ccx
    from .solver import build_mesh, solve

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    gm = build_mesh(scenario)
    deck = export_inp_ccx(scenario, workdir / "deck.inp", mesh=gm, bulk=bulk, max_increment_mm=max_increment_mm)
    t0 = time.time()
    ours = solve(scenario, mesh=gm)
    seconds_ours = time.time() - t0
    seconds_ccx = run_ccx(deck, threads=threads)
    reac = read_reactions(deck.with_suffix(".dat"), scenario.n_keypoints)
    ccx = np.stack([reac[f"IND{k + 1}_REF"] for k in range(len(scenario.indenters))], axis=1)
    ccx_m = np.stack([reac[f"IND{k + 1}_ROT"] for k in range(len(scenario.indenters))], axis=1)
    return {"ours": ours.RF, "ccx": ccx, "ours_moment": ours.RM, "ccx_moment": ccx_m, "seconds_ours": seconds_ours, "seconds_ccx": seconds_ccx,
            "deck": str(deck), "nodes": len(gm.nodes)}
