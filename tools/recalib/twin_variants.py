"""Variants of the twin recalibration bench: geometry first (two-stage recalibration) and other
correction inputs. Called by tools.recalib.twin_bench.evaluate_unit; see docs/recalibration.md."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .fit import set_name
from .replay import collect_frames, corrected_frames, held_out_pokes, mae

log = logging.getLogger(__name__)


def geometry_stage(unit, cfg, package, fit_dir, held, pokes, base, row, rules, eval_rules, work: Path, say,
                   tables: dict, meta: dict) -> dict:
    """Two-stage recalibration: θ/φ tables + gel centre from the accepted pokes with their true 3D
    points (recalibrate --geometry; twin truth/contact.csv, or mocap/jig positions in the field),
    stored first; then the fit session replayed through the re-centred crop and the force
    correction fitted on those forces (5/6/7 pokes). Held-out errors vs the nominal 'before'."""
    from ...contracts.session import load_session
    from ...contracts.store import CalibrationStore
    from .session import SessionConfig, StreamReference, analyse, run_guided, session_truth_xyz
    from .store_ops import store_recalibration

    session = load_session(fit_dir)
    truth = session_truth_xyz(session, pokes)
    an = analyse(pokes, base, SessionConfig(pokes=len(pokes), rules=rules), force=True, truth_xyz=truth)
    g = an.geometry
    st = CalibrationStore(work / "geometry")
    if cfg.geometry == "center":      # keep the nominal tables, re-centre the crop on the fitted centre
        meta = {**meta, "gel_center_px": [float(v) for v in g.center]}
        st.write(unit.serial, tables, meta)
        geo = None
    else:                              # the full refresh of recalibrate --geometry (GPR θ/φ tables)
        st.write(unit.serial, tables, meta)
        geo = {"gel_center_px": g.center, "theta": g.theta, "phi": g.phi}
        store_recalibration(st, st.load(unit.serial), {"pokes": len(pokes), "source": f"replay:{fit_dir}"},
                            geometry=geo)
    cal_g = st.load(unit.serial)
    fc = cfg.folder() / "frames"
    raw = {k: collect_frames(d, cal_g, package, cfg.precision, fc) for k, d in held.items()}
    refs = {k: StreamReference.from_session(load_session(d), eval_rules) for k, d in held.items()}
    frames = collect_frames(fit_dir, cal_g, package, cfg.precision, fc)
    reference = StreamReference.from_session(session, rules)
    true_c = np.array(true_center(unit))
    out = {"center_px": list(g.center), "center_true_px": true_c.tolist(),
           "center_error_px": float(np.linalg.norm(np.array(g.center) - true_c)),
           "center_error_nominal_px": float(np.linalg.norm(np.array(base.gel_center_px) - true_c)),
           "held_out": {}, "by_pokes": {}}
    for k in held:
        b = held_out_pokes(raw[k], refs[k], eval_rules)
        out["held_out"][k] = {"pokes": len(b["ref"]), "geometry_only_mae_n": mae(b),
                              "reduction": 1 - mae(b) / row["held_out"][k]["before_mae_n"], "after": {}}
    for n in cfg.poke_counts:
        scfg = SessionConfig(pokes=n, rules=rules)
        oc = run_guided(iter(frames), cal_g, reference, scfg, say=lambda m: None)
        e = {"accepted": len(oc.accepted)}
        out["by_pokes"][str(n)] = e
        if len(oc.accepted) < scfg.fit.min_pokes:
            continue
        an = analyse(oc.accepted, cal_g, scfg, force=True)
        e.update(loo_before_mae_n=an.fit.loo["before"]["mae_n"], loo_after_mae_n=an.fit.loo["after"]["mae_n"],
                 stored=bool(an.fit.loo["after"]["mae_n"] < an.active["mae_n"]))
        st2 = CalibrationStore(work / f"geometry-n{n}")
        st2.write(unit.serial, tables, meta)
        store_recalibration(st2, st2.load(unit.serial), {"pokes": n}, correction=(an.fit.spec, an.fit.onnx_bytes),
                            geometry=geo)
        cal_n = st2.load(unit.serial)
        for k in held:
            h = out["held_out"][k]
            a = held_out_pokes(corrected_frames(raw[k], cal_n), refs[k], eval_rules)
            after = mae(a) if e["stored"] else h["geometry_only_mae_n"]
            h["after"][str(n)] = {"pokes": len(a["ref"]), "after_forced_mae_n": mae(a), "after_mae_n": after,
                                  "reduction": 1 - after / row["held_out"][k]["before_mae_n"],
                                  "reduction_forced": 1 - mae(a) / row["held_out"][k]["before_mae_n"]}
            say(f"  {unit.serial}, geometry + {n} pokes, held-out {k}: MAE {row['held_out'][k]['before_mae_n']:.3f} -> "
                f"{after:.3f} N ({h['after'][str(n)]['reduction']:.0%}; geometry only {h['reduction']:.0%}; "
                f"forced {h['after'][str(n)]['reduction_forced']:.0%}); centre error {out['center_error_nominal_px']:.1f} "
                f"-> {out['center_error_px']:.1f} px")
    return out


def true_center(unit) -> tuple:
    """The unit's true gel centre in camera px (image of the apex)."""
    from ..twin.unit import TwinUnit

    return TwinUnit(unit.serial, override=unit.override()).gel_center_px


def input_variants(pokes, cal, scfg, raw, refs, row, rules, variants, work: Path) -> dict:
    """Held-out MAE after a correction on other inputs (stored regardless of the LOO decision)."""
    from dataclasses import replace as dc_replace

    from ...runtime.stages.correction import ForceCorrection
    from .session import analyse

    out = {}
    for inputs in variants:
        vcfg = dc_replace(scfg, fit=dc_replace(scfg.fit, inputs=tuple(inputs), candidates=()))
        an = analyse(pokes, cal, vcfg, force=True)
        path = work / f"variant-{set_name(inputs).replace('+', '-')}.onnx"
        path.write_bytes(an.fit.onnx_bytes)
        corr = ForceCorrection(path, an.fit.spec)
        name = set_name(inputs)
        out[name] = {"loo_after_mae_n": an.fit.loo["after"]["mae_n"]}
        for k in raw:
            a = held_out_pokes(corrected_frames(raw[k], cal, corr), refs[k], rules)
            out[name][k] = {"after_mae_n": mae(a), "reduction": 1 - mae(a) / row["held_out"][k]["before_mae_n"]}
    return out
