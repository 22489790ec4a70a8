"""Convergence and cross-solver study of tools.fe against CalculiX 2.20 (docs/BENCHMARKS.md).

`run_study(name, work_dir)` runs one study on the standard dome (sphere R 5 mm at the apex) and
returns rows of {case, solver, settings, depth or slide, RF, seconds}; `tensortouch fe study NAME
--work-dir DIR [--json out.json]` prints them. Studies:
- press:     frictionless press 0.5/1/2/3 mm, P1 mesh 0.7 mm, same bulk modulus in both solvers;
- slide:     press 1 mm then slide 0.5/1 mm in x, mu 2.2, same mesh and bulk modulus;
- mupress:   mu 2.2 press 1/2/3 mm at increments 0.5/0.25/0.1/0.05 mm (tools.fe, first-touch
             anchor on and off) and 0.5/0.1 mm (ccx);
- locking:   frictionless press 0.5-3 mm: ccx C3D10 and tools.fe P2/P0 at the true D1 (P2 mesh
             1.4/3.0 mm) against tools.fe P1 (0.7/2.0 mm) with the bulk cap at 3, 4, 5 x mu0;
- mesh:      frictionless press 2 mm at top sizes 1.0/0.7/0.5 mm in both solvers.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .scenario import Keypoint, standard_dome

STUDIES = ("press", "slide", "mupress", "locking", "mesh")
GAP = 0.05  # mm: the standard dome's indenter starts this far above the apex


def _press(depths, mu=0.0, **mesh):
    sc = standard_dome(depth=1.0, slide=(0.0, 0.0), n_keypoints=1, **mesh)
    sc.indenters[0].keypoints = [Keypoint([0.0, 0.0, -(d + GAP)], [0.0, 0.0, 0.0]) for d in depths]
    sc.friction = mu
    return sc


def _ours(sc, label, **extra):
    from .solver import solve

    t0 = time.time()
    res = solve(sc)
    return {"solver": "tensortouch.tools.fe", "settings": label, "RF": res.RF[:, 0].round(5).tolist(),
            "seconds": round(time.time() - t0, 1), **extra}


def _ccx(sc, work: Path, label, bulk="solver", **extra):
    from .ccx import read_reactions, run_ccx
    from .inp import export_inp_ccx

    deck = export_inp_ccx(sc, work / f"{label}.inp", bulk=bulk)
    seconds = run_ccx(deck)
    rf = read_reactions(deck.with_suffix(".dat"), sc.n_keypoints)["IND1_REF"]
    return {"solver": "ccx", "settings": label, "RF": rf.round(5).tolist(), "seconds": round(seconds, 1), **extra}


def run_study(name: str, work_dir, emit=print) -> list[dict]:
    from . import solver as fs

    if name not in STUDIES:
        raise ValueError(f"study {name!r}: expected one of {STUDIES}")
    work = Path(work_dir) / name
    work.mkdir(parents=True, exist_ok=True)
    rows = []

    def add(row):
        row["case"] = name
        rows.append(row)
        emit(row)

    if name == "press":
        depths = [0.5, 1.0, 2.0, 3.0]
        sc = _press(depths)
        add(_ours(sc, "P1 0.7mm cap5 inc0.5", depths=depths))
        add(_ccx(sc, work, "C3D4_0.7mm_cap5_inc0.5", depths=depths))
    elif name == "slide":
        sc = _press([1.0, 1.0, 1.0], mu=2.2)
        for j, dx in ((1, 0.5), (2, 1.0)):
            sc.indenters[0].keypoints[j].translation = [dx, 0.0, -(1.0 + GAP)]
        add(_ours(sc, "P1 0.7mm cap5 inc0.5", slide=[0.0, 0.5, 1.0]))
        add(_ccx(sc, work, "C3D4_0.7mm_cap5_inc0.5", slide=[0.0, 0.5, 1.0]))
    elif name == "mupress":
        depths = [1.0, 2.0, 3.0]
        for inc in (0.5, 0.25, 0.1, 0.05):
            sc = _press(depths, mu=2.2)
            sc.solver.max_increment_mm = inc
            add(_ours(sc, f"P1 inc{inc} first-touch", depths=depths))
            if inc in (0.5, 0.05):
                fs.FIRST_TOUCH_ANCHOR = False
                try:
                    add(_ours(sc, f"P1 inc{inc} closest-point (before)", depths=depths))
                finally:
                    fs.FIRST_TOUCH_ANCHOR = True
            if inc in (0.5, 0.1):
                add(_ccx(sc, work, f"C3D4_inc{inc}", depths=depths))
        sc = _press(depths, mu=0.0)
        add(_ours(sc, "P1 inc0.5 frictionless", depths=depths))
    elif name == "locking":
        depths = [0.5, 1.0, 2.0, 3.0]
        p2 = _press(depths, order=2, size_top=1.4, size_inside=3.0)
        add(_ccx(p2, work, "C3D10_1.4mm_trueD1", bulk="material", depths=depths))
        add(_ours(p2, "P2/P0 1.4mm trueD1", depths=depths))
        for cap in (3.0, 4.0, 5.0):
            sc = _press(depths)
            sc.solver.max_bulk_ratio = cap
            add(_ours(sc, f"P1 0.7mm cap{cap:g}", depths=depths))
    elif name == "mesh":
        for top, inside in ((1.0, 2.5), (0.7, 2.0), (0.5, 2.0)):
            sc = _press([2.0], size_top=top, size_inside=inside)
            add(_ours(sc, f"P1 {top}mm cap5", depths=[2.0]))
            add(_ccx(sc, work, f"C3D4_{top}mm_cap5", depths=[2.0]))
    return rows


def fz_table(rows) -> str:
    """Markdown-ish text table of |Fz| per row (for the log)."""
    out = []
    for r in rows:
        fz = np.abs(np.asarray(r["RF"])[:, 2])
        out.append(f"{r['case']:8s} {r['solver']:8s} {r['settings']:36s} " + " ".join(f"{v:7.4f}" for v in fz)
                   + f"   {r['seconds']:6.1f} s")
    return "\n".join(out)
