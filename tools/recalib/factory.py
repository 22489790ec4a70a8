"""Factory correction: the model's own systematic force error over the gel, fitted once per model.

A network reads some places and loads consistently high or low on every unit (the same pokes of two
units differ mostly by one number, the unit's gain: docs/BENCHMARKS.md "Factory correction"). Five
field pokes cannot map that shape, but twin sessions of a nominal unit (no manufacturing variation) can:
every frame with one contact and a reference force of at least `min_force_n` is a sample of the gain
|F_ref| / |F_pred| at the contact's position and |F|. A forest of that gain (the runtime's
"random_forest_gain" correction, ONNX) is the nominal calibration's correction; field recalibration
then refits one scale on top of it (tools.recalib.fit `fit_correction(..., active=...)`).

    python -m tools.recalib.factory --model PKG --session DIR [DIR ...] --out FOLDER

Pure core (`frame_samples`, `fit_factory`) and a thin shell (`main`). The held-out error is measured
with one fold per session (a session's frames are not independent of each other).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from runtime.errors import CalibrationError
from runtime.geometry import sample_bilinear
from tools.recalib.fit import FitConfig, PokeSet, corrected_magnitude, error_stats, fit_forest, to_onnx

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FactoryConfig:
    inputs: tuple[str, ...] = ("fmag", "theta", "u", "v")  # |F| and position (runtime FEATURES names)
    min_force_n: float = 0.3          # = PokeRules.min_force_n: lighter frames carry more noise than gain
    contact_floor_n: float = 0.05     # clusters below this are not contacts (PokeRules.contact_floor_n)
    merge_radius_mm: float = 4.0      # parts of one contact (PokeRules.merge_radius_mm)
    n_estimators: int = 50
    max_depth: int = 6                # thousands of frames support deeper trees than 5–7 pokes do
    min_samples_leaf: int = 25        # ~1 s of frames of one contact: a leaf is never one poke's noise
    min_frames: int = 200
    min_gain: float = 0.02            # store only if the held-out MAE falls by this fraction or more


def frame_samples(frames: list, ref_t: np.ndarray, ref_mag: np.ndarray, cal, cfg: FactoryConfig = FactoryConfig()) -> PokeSet:
    """Samples of one replayed session: frames [(t, clusters)] with raw model forces, the reference |F|
    stream (t, |F|) (one indenter at a time). A frame counts when the sensor shows one contact (its
    strongest cluster plus the parts within merge_radius_mm; no other cluster above the floor) and the
    reference, interpolated at the frame time, is at least min_force_n."""
    from tools.recalib.pokes import merge_main

    h, w = cal.model_size
    pf, ref, uv, tp = [], [], [], []
    for t, clusters in frames:
        strong = sorted((c for c in clusters if c.force_mag_n >= cfg.contact_floor_n),
                        key=lambda c: c.force_mag_n, reverse=True)
        if not strong:
            continue
        force, cuv, _, mag, other = merge_main(strong, cfg.merge_radius_mm)
        r = float(np.interp(t, ref_t, ref_mag))
        if other > 0 or r < cfg.min_force_n or mag <= 1e-3:
            continue
        pf.append(force)
        ref.append(r)
        uv.append(np.asarray(cuv, float) / np.array([w, h]))
        tp.append([sample_bilinear(cal.theta, cuv[0] - 0.5, cuv[1] - 0.5), sample_bilinear(cal.phi, cuv[0] - 0.5, cuv[1] - 0.5)])
    return PokeSet(np.array(pf).reshape(-1, 3), np.array(ref), np.array(uv).reshape(-1, 2), np.array(tp).reshape(-1, 2))


def _fit_cfg(cfg: FactoryConfig) -> FitConfig:
    return FitConfig(inputs=tuple(cfg.inputs), candidates=(), n_estimators=cfg.n_estimators, max_depth=cfg.max_depth,
                     min_samples_leaf=cfg.min_samples_leaf)


def _concat(parts: list) -> PokeSet:
    return PokeSet(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("pred_force", "ref_force", "uv", "theta_phi")))


def fit_factory(sessions: list, cfg: FactoryConfig = FactoryConfig()) -> dict:
    """sessions: [(name, PokeSet)] of nominal-unit sessions. Returns {"spec", "onnx", "heldout"} where
    heldout = per-fold and pooled |F| MAE before/after (one session left out at a time); onnx is None
    when the forest does not beat the raw model by cfg.min_gain held out (the model then needs none)."""
    sessions = [(n, p) for n, p in sessions if len(p)]
    pokes = _concat([p for _, p in sessions]) if sessions else None
    if pokes is None or len(pokes) < cfg.min_frames:
        raise CalibrationError(f"factory correction: {0 if pokes is None else len(pokes)} usable contact frames "
                               f"in {len(sessions)} sessions, need {cfg.min_frames} (one contact, reference "
                               f">= {cfg.min_force_n} N)")
    if len(sessions) < 2:
        raise CalibrationError("factory correction: need at least 2 sessions (one held out at a time)")
    fc = _fit_cfg(cfg)
    held = np.empty(len(pokes))
    start, folds = 0, []
    for k, (name, p) in enumerate(sessions):
        rest = _concat([q for j, (_, q) in enumerate(sessions) if j != k])
        g = fit_forest(rest, fc).predict(p.features(fc.inputs))
        held[start:start + len(p)] = corrected_magnitude(p.pred_mag, g, fc)
        folds.append({"session": name, "frames": len(p),
                      "before_mae_n": error_stats(p.pred_mag, p.ref_force)["mae_n"],
                      "after_mae_n": error_stats(held[start:start + len(p)], p.ref_force)["mae_n"]})
        start += len(p)
    before, after = error_stats(pokes.pred_mag, pokes.ref_force), error_stats(held, pokes.ref_force)
    heldout = {"before": before, "after": after, "folds": folds}
    if after["mae_n"] > (1.0 - cfg.min_gain) * before["mae_n"]:
        return {"spec": None, "onnx": None, "heldout": heldout, "config": asdict(cfg)}
    rf = fit_forest(pokes, fc)
    onnx = to_onnx(rf, len(fc.inputs), fc)
    spec = {"file": "correction.onnx", "inputs": list(fc.inputs), "output": "gain", "kind": "random_forest_gain",
            "n_estimators": fc.n_estimators, "max_depth": fc.max_depth, "source": "factory correction",
            "frames": int(len(pokes)), "sessions": [n for n, _ in sessions],
            "heldout_mae_n": [round(before["mae_n"], 5), round(after["mae_n"], 5)]}
    return {"spec": spec, "onnx": onnx, "heldout": heldout, "config": asdict(cfg)}


def session_samples(session_dir: Path, cal, package, precision: str = "int8", cache: Path | None = None,
                    cfg: FactoryConfig = FactoryConfig()) -> PokeSet:
    """frame_samples of a recorded session replayed through the runtime (raw model force)."""
    from runtime.session import load_session
    from tools.recalib.replay import collect_frames
    from tools.recalib.session import StreamReference

    frames = collect_frames(Path(session_dir), cal, package, precision, cache)
    ref = StreamReference.from_session(load_session(Path(session_dir)))
    if len(np.unique(ref.ind)) > 1:
        raise CalibrationError(f"{session_dir}: factory sessions need one indenter at a time "
                               f"(wrench.csv has indenters {np.unique(ref.ind).tolist()})")
    return frame_samples(frames, ref.t, ref.mag, cal, cfg)


def write(out: Path, fit: dict) -> None:
    """FOLDER/factory.json (spec + held-out numbers) and FOLDER/correction.onnx, each written atomically."""
    out.mkdir(parents=True, exist_ok=True)
    if fit["onnx"] is not None:
        tmp = out / ".correction.onnx.tmp"
        tmp.write_bytes(fit["onnx"])
        tmp.replace(out / "correction.onnx")
    tmp = out / ".factory.json.tmp"
    tmp.write_text(json.dumps({k: v for k, v in fit.items() if k != "onnx"}, indent=1, default=float))
    tmp.replace(out / "factory.json")


def main(argv=None) -> int:
    from runtime.calibration import CalibrationStore
    from runtime.model import find_package

    p = argparse.ArgumentParser(prog="python -m tools.recalib.factory", description=__doc__.splitlines()[0])
    p.add_argument("--model", help="model package (default: newest installed)")
    p.add_argument("--precision", default="int8", choices=("int8", "fp32"))
    p.add_argument("--store", required=True, help="calibration store holding the nominal unit's calibration")
    p.add_argument("--sensor", required=True, help="the nominal unit's serial in --store")
    p.add_argument("--session", nargs="+", required=True, help="recorded sessions of that unit (>= 2)")
    p.add_argument("--out", required=True, help="folder for factory.json and correction.onnx")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    package = find_package(args.model)
    cal = CalibrationStore(args.store).load(args.sensor)
    cfg = FactoryConfig()
    fit = fit_factory([(Path(s).name, session_samples(Path(s), cal, package, args.precision, cfg=cfg)) for s in args.session], cfg)
    write(Path(args.out), fit)
    h = fit["heldout"]
    print(f"factory correction: {sum(f['frames'] for f in h['folds'])} frames, held-out |F| MAE "
          f"{h['before']['mae_n']:.4f} -> {h['after']['mae_n']:.4f} N (one session left out at a time); "
          f"{'stored' if fit['onnx'] else 'not worth storing'} in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
