"""Convergence and cross-solver study of tools.fe against CalculiX 2.20 (docs/BENCHMARKS.md "CalculiX cross-check and FE convergence study").

`run_study(name, work_dir)` runs one study on the standard dome (sphere R 5 mm at the apex) and
returns rows of {case, solver, settings, depth or slide, RF, seconds}; `tensortouch fe study NAME
--work-dir DIR [--json out.json]` prints them. Studies:
- press:     frictionless press 0.5/1/2/3 mm, P1 mesh 0.7 mm, same bulk modulus in both solvers;
- slide:     press 1 mm then slide 0.5/1 mm in x, mu 2.2, same mesh and bulk modulus;
- mupress:   mu 2.2 press 1/2/3 mm at increments 0.5/0.25/0.1/0.05 mm (tools.fe, first-touch
             anchor on and off) and 0.5/0.1 mm (ccx);
- locking:   frictionless press 0.5-3 mm: ccx C3D10 (0.25 mm increments) and tools.fe P2/P0 at
             the true D1 (P2 mesh 1.4/3.0 mm) against tools.fe P1 (0.7/2.0 mm) with the bulk cap at 3, 4, 5 x mu0;
- mesh:      frictionless press 2 mm at top sizes 1.0/0.7/0.5 mm in both solvers;
- agreement: the cross-check table on the top 1.2 mm mesh (frictionless press 1.5 mm; press 1 mm
             then slide 1 mm, mu 2.2; mu-press 2 mm, mu 2.2): ccx at increments AGREEMENT_CCX_INCREMENTS
             (its frictional forces move with the increment), their Richardson extrapolation
             (`richardson`, the finest level where not monotone) as ccx's converged answer, tools.fe at
             its own 0.5 mm and at the finest of those increments; each tools.fe row carries
             `ratio_to_ccx` (RF_z and, for the slide, RF_x of the last frame) and `speedup_vs_ccx`
             (ccx's wall time at the increment whose forces are within AGREEMENT_TOL of its converged
             answer, over ours);
- c3d10:     the reference for the locking cap: frictionless press 0.5-3 mm at the true D1, ccx
             C3D10 on P2 meshes top 1.4/1.0/0.7 mm (inside 3.0 mm, increments 0.25 mm), its
             Richardson extrapolation to h -> 0 (`richardson`), and tools.fe P1 (0.7/2.0 mm) with
             the bulk cap at 3-7 x mu0 and tools.fe P2/P0 on the 1.4 and 1.0 mm meshes, each with
             its ratio to the extrapolated value; and both quadratic formulations on the 1.4 mm
             mesh at bulk/shear 5 (no volumetric locking there) to tell element from mesh effects.
ccx runs are reused when the same deck was solved before in the same work folder (`<label>.json`
next to the deck holds the deck's hash, the reactions and the wall time); in `c3d10` tools.fe
solves are reused by scenario hash (`fe_<hash>_anchor<0|1>.json`).
"""
from __future__ import annotations

import copy
import hashlib
import json
import time
from pathlib import Path

import numpy as np

from .scenario import Keypoint, standard_dome

STUDIES = ("press", "slide", "mupress", "locking", "mesh", "c3d10", "agreement")
AGREEMENT_CCX_INCREMENTS = (0.5, 0.25, 0.125)  # mm, coarse to fine
AGREEMENT_SIZE_TOP = 1.2   # mm (the cross-check mesh of docs/BENCHMARKS.md)
AGREEMENT_TOL = 0.02       # ccx's increment counts as converged when its forces are this close to the extrapolation
C3D10_LEVELS = ((1.4, 3.0), (1.0, 3.0), (0.7, 3.0))  # P2 mesh (top, inside) in mm, coarse to fine
C3D10_P2P0_LEVELS = C3D10_LEVELS[:2]  # tools.fe P2/P0 on the same meshes (not 0.7 mm: 30k nodes, too slow here)
GAP = 0.05  # mm: the standard dome's indenter starts this far above the apex


def _press(depths, mu=0.0, **mesh):
    sc = standard_dome(depth=1.0, slide=(0.0, 0.0), n_keypoints=1, **mesh)
    sc.indenters[0].keypoints = [Keypoint([0.0, 0.0, -(d + GAP)], [0.0, 0.0, 0.0]) for d in depths]
    sc.friction = mu
    return sc


def _ours(sc, label, work: Path | None = None, **extra):
    """tools.fe's RF for `sc`; with `work`, reused from `<work>/fe_<scenario hash>.json` when solved before."""
    from ...contracts.files import atomic_write_json
    from . import solver as fs

    done = None if work is None else work / f"fe_{sc.hash()}_anchor{int(fs.FIRST_TOUCH_ANCHOR)}.json"
    if done is not None and done.exists():
        prev = json.loads(done.read_text())
        return {"solver": "tensortouch.tools.fe", "settings": label, "RF": prev["RF"], "seconds": prev["seconds"],
                "reused": True, **extra}
    t0 = time.time()
    res = fs.solve(sc)
    rf, seconds = res.RF[:, 0].round(5).tolist(), round(time.time() - t0, 2)
    if done is not None:
        atomic_write_json(done, {"RF": rf, "seconds": seconds}, indent=None)
    return {"solver": "tensortouch.tools.fe", "settings": label, "RF": rf, "seconds": seconds, **extra}


def _ccx(sc, work: Path, label, bulk="solver", max_increment_mm=None, **extra):
    from ...contracts.files import atomic_write_json
    from .ccx import read_reactions, run_ccx
    from .inp import export_inp_ccx

    deck = export_inp_ccx(sc, work / f"{label}.inp", bulk=bulk, max_increment_mm=max_increment_mm)
    digest = hashlib.sha256(deck.read_bytes()).hexdigest()
    done = deck.with_suffix(".json")
    if done.exists():
        prev = json.loads(done.read_text())
        if prev.get("deck_sha256") == digest:
            return {"solver": "ccx", "settings": label, "RF": prev["RF"], "seconds": prev["seconds"],
                    "reused": True, **extra}
    seconds = run_ccx(deck, timeout=3 * 3600.0)
    rf = read_reactions(deck.with_suffix(".dat"), sc.n_keypoints)["IND1_REF"].round(5).tolist()
    atomic_write_json(done, {"deck_sha256": digest, "RF": rf, "seconds": round(seconds, 1)}, indent=None)
    return {"solver": "ccx", "settings": label, "RF": rf, "seconds": round(seconds, 1), **extra}


def richardson(h, f) -> dict:
    """Extrapolate f(h) -> h = 0 from three levels h1 > h2 > h3 (any ratios) with an observed order p.

    Solves (f2 - f1) / (f3 - f2) = (h1^p - h2^p) / (h2^p - h3^p) for p (bisection on 0.05..8);
    f0 = f3 + (f3 - f2) h3^p / (h2^p - h3^p). Returns {"f0", "p", "monotone"}; when the three values
    do not converge monotonically, f0 and p are None (then only the spread of the levels is known)."""
    h1, h2, h3 = (float(x) for x in h)
    f1, f2, f3 = (float(x) for x in f)
    d1, d2 = f2 - f1, f3 - f2
    if d1 == 0.0 or d2 == 0.0 or (d1 > 0) != (d2 > 0):
        return {"f0": None, "p": None, "monotone": False}

    def g(p):
        return (h1 ** p - h2 ** p) / (h2 ** p - h3 ** p) - d1 / d2

    lo, hi = 0.05, 8.0
    if g(lo) * g(hi) > 0:
        return {"f0": None, "p": None, "monotone": False}
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if g(lo) * g(mid) <= 0:
            hi = mid
        else:
            lo = mid
    p = 0.5 * (lo + hi)
    f0 = f3 + d2 * h3 ** p / (h2 ** p - h3 ** p)
    return {"f0": f0, "p": p, "monotone": True}


def run_study(name: str, work_dir, emit=print) -> list[dict]:
    from . import solver as fs
    from .inp import C3D10_MAX_INCREMENT_MM

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
        add(_ccx(p2, work, f"C3D10_1.4mm_trueD1_inc{C3D10_MAX_INCREMENT_MM}", bulk="material",
                 max_increment_mm=C3D10_MAX_INCREMENT_MM, depths=depths))
        add(_ours(p2, "P2/P0 1.4mm trueD1", depths=depths))
        for cap in (3.0, 4.0, 5.0):
            sc = _press(depths)
            sc.solver.max_bulk_ratio = cap
            add(_ours(sc, f"P1 0.7mm cap{cap:g}", depths=depths))
    elif name == "c3d10":
        depths = [0.5, 1.0, 2.0, 3.0]
        levels = []
        for top, inside in C3D10_LEVELS:
            p2 = _press(depths, order=2, size_top=top, size_inside=inside)
            add(_ccx(p2, work, f"C3D10_{top}mm_trueD1_inc{C3D10_MAX_INCREMENT_MM}", bulk="material",
                     max_increment_mm=C3D10_MAX_INCREMENT_MM, depths=depths, size_top=top))
            levels.append(np.abs(np.asarray(rows[-1]["RF"])[:, 2]))
        ext = [richardson([t for t, _ in C3D10_LEVELS], [lv[i] for lv in levels]) for i in range(len(depths))]
        ref = np.array([e["f0"] if e["monotone"] else levels[-1][i] for i, e in enumerate(ext)])
        add({"solver": "ccx", "settings": "C3D10 extrapolated h->0 (finest level where not monotone)",
             "RF": [[0.0, 0.0, -round(float(v), 5)] for v in ref], "seconds": 0.0, "depths": depths,
             "order": [None if e["p"] is None else round(e["p"], 2) for e in ext]})
        for cap in (3.0, 4.0, 5.0, 6.0, 7.0):
            sc = _press(depths)
            sc.solver.max_bulk_ratio = cap
            row = _ours(sc, f"P1 0.7mm cap{cap:g}", work=work, depths=depths)
            row["ratio_to_reference"] = (np.abs(np.asarray(row["RF"])[:, 2]) / ref).round(4).tolist()
            add(row)
        # element, not mesh: both quadratic formulations on the 1.4 mm mesh with a compressible gel
        # (bulk/shear 5, no volumetric locking): what remains of their gap is not C3D10 locking
        top, inside = C3D10_LEVELS[0]
        soft = _press(depths, order=2, size_top=top, size_inside=inside)
        soft.material.D1 = 2.0 / (5.0 * soft.material.shear_modulus)
        add(_ccx(soft, work, f"C3D10_{top}mm_bulk5_inc{C3D10_MAX_INCREMENT_MM}", bulk="material",
                 max_increment_mm=C3D10_MAX_INCREMENT_MM, depths=depths, size_top=top))
        add(_ours(soft, f"P2/P0 {top}mm bulk5", work=work, depths=depths, size_top=top))
        for top, inside in C3D10_P2P0_LEVELS:   # ours, locking-free, on ccx's meshes (slow: last)
            row = _ours(_press(depths, order=2, size_top=top, size_inside=inside), f"P2/P0 {top}mm trueD1",
                        work=work, depths=depths, size_top=top)
            row["ratio_to_reference"] = (np.abs(np.asarray(row["RF"])[:, 2]) / ref).round(4).tolist()
            add(row)
    elif name == "agreement":
        for row in _agreement(work):
            add(row)
    elif name == "mesh":
        for top, inside in ((1.0, 2.5), (0.7, 2.0), (0.5, 2.0)):
            sc = _press([2.0], size_top=top, size_inside=inside)
            add(_ours(sc, f"P1 {top}mm cap5", depths=[2.0]))
            add(_ccx(sc, work, f"C3D4_{top}mm_cap5", depths=[2.0]))
    return rows


def ccx_converged(last_rf, seconds, axes, increments=AGREEMENT_CCX_INCREMENTS, tol=AGREEMENT_TOL):
    """ccx's converged answer over its increment sizes and what it costs.

    last_rf: per increment (coarse to fine) the last frame's RF (3,); seconds: ccx's wall time per
    increment; axes: the RF components compared. Returns ({axis: |RF| extrapolated to increment 0 by
    `richardson`, or the finest level's where not monotone}, seconds of the coarsest increment whose
    |RF| on every axis is within `tol` of that answer, or of the finest)."""
    if not (len(last_rf) == len(seconds) == len(increments) == 3):
        raise ValueError(f"ccx_converged: expected 3 increments, got {len(last_rf)} forces, {len(seconds)} times, "
                         f"{len(increments)} increments")
    ref = {}
    for ax in axes:
        v = [abs(float(rf[ax])) for rf in last_rf]
        e = richardson(increments, v)
        ref[ax] = e["f0"] if e["monotone"] else v[-1]
    for rf, t in zip(last_rf, seconds):
        if all(abs(abs(float(rf[ax])) / ref[ax] - 1.0) <= tol for ax in axes):
            return ref, t
    return ref, seconds[-1]


def _agreement_cases():
    press = _press([1.5], size_top=AGREEMENT_SIZE_TOP)
    slide = _press([1.0, 1.0], mu=2.2, size_top=AGREEMENT_SIZE_TOP)
    slide.indenters[0].keypoints[1].translation = [1.0, 0.0, -(1.0 + GAP)]
    mupress = _press([2.0], mu=2.2, size_top=AGREEMENT_SIZE_TOP)
    return {"press 1.5 mm, mu 0": (press, (2,)), "press 1 mm + slide 1 mm, mu 2.2": (slide, (2, 0)),
            "mu-press 2 mm, mu 2.2": (mupress, (2,))}


def _agreement(work: Path) -> list[dict]:
    rows = []
    for case, (sc, axes) in _agreement_cases().items():
        tag = case.split(",")[0].replace(" ", "_").replace("+", "")
        ccx = [_ccx(sc, work, f"{tag}_C3D4_inc{inc}", max_increment_mm=inc, case_name=case, increment_mm=inc)
               for inc in AGREEMENT_CCX_INCREMENTS]
        ref, t_ccx = ccx_converged([r["RF"][-1] for r in ccx], [r["seconds"] for r in ccx], axes)
        rows += ccx
        rows.append({"solver": "ccx", "settings": "extrapolated to increment 0 (finest where not monotone)",
                     "case_name": case, "RF_last_abs": {str(ax): round(v, 5) for ax, v in ref.items()},
                     "seconds": 0.0, "RF": []})
        import felupe  # noqa: F401  (imported, compiled and meshed before timing ours: ccx's time has no start-up either)

        from .assembly import compile_kernels
        from .solver import GelModel, build_mesh
        compile_kernels()
        GelModel(sc, build_mesh(sc))   # the mesh's assembly pattern and MKL, once per mesh and process (as `bench fe`)
        for inc in (sc.solver.max_increment_mm, AGREEMENT_CCX_INCREMENTS[-1]):
            s2 = copy.deepcopy(sc)
            s2.solver.max_increment_mm = inc
            row = _ours(s2, f"P1 {AGREEMENT_SIZE_TOP}mm inc{inc}", case_name=case, increment_mm=inc)
            row["ratio_to_ccx"] = {str(ax): round(abs(row["RF"][-1][ax]) / ref[ax], 4) for ax in axes}
            row["speedup_vs_ccx"] = round(t_ccx / max(row["seconds"], 1e-3), 1)
            row["ccx_seconds_converged"] = t_ccx
            rows.append(row)
    return rows


def fz_table(rows) -> str:
    """Markdown-ish text table of |Fz| per row (for the log)."""
    out = []
    for r in rows:
        fz = np.abs(np.asarray(r["RF"]).reshape(-1, 3)[:, 2])
        out.append(f"{r['case']:8s} {r['solver']:8s} {r['settings']:36s} " + " ".join(f"{v:7.4f}" for v in fz)
                   + f"   {r['seconds']:6.1f} s")
    return "\n".join(out)
