"""Stage 8 — evaluation as seed §V-A on held-out twin sessions, through the runtime's own code path.

Every frame of a session goes through `runtime.offline.replay_session` (preprocess, dynamic baseline,
the shipped int8 model, contact clustering, effects, correction): what `tensortouch run` publishes. For frames where an
indenter's measured force (F/T rotated into the sensor frame) exceeds the seed's contact threshold,
the cluster nearest to that indenter's mocap tip is compared with it:
- position: cluster centroid (mm, sensor frame) − mocap tip position, per axis;
- force: cluster force − the force the indenter applies (= −F/T reading in the sensor frame), per
  axis and magnitude; a contact frame without any cluster counts as a miss (predicted force 0).
Rest frames (all measured |F| < `rest_n`) report the predicted total force (should be 0).

Pure core: `frame_errors`, `summarize`. Shell: `evaluate_session` (stage 8, `stages.stage_evaluate`, runs it on a build's held-out sessions).
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ...contracts.files import atomic_write_json
from ..scoring import contact_config, find_contacts, match_contacts, measured_at, split_at_tips
from .labels import at_fe_frames

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvalConfig:
    contact_n: float = 1.5        # seed §III.C contact threshold on the measured force
    rest_n: float = 0.2           # all indenters below this: a rest frame
    phantom_n: float = 0.05       # on a frame with one indenter in contact, another cluster above this is a phantom
    precision: str = "int8"
    threads: int = 1


def frame_errors(clusters: list, tips: np.ndarray, forces: np.ndarray, cfg: EvalConfig = EvalConfig()) -> list[dict]:
    """Match one frame's clusters (position_mm, force_n) to the indenters in contact (tips/forces (K, 3)):
    strongest indenter first, each takes its nearest free cluster (tools.scoring.match_contacts);
    one row per indenter in contact."""
    mags = np.linalg.norm(forces, axis=1)
    order = [k for k in np.argsort(-mags) if mags[k] >= cfg.contact_n]
    got = match_contacts(tips, [c.position_mm for c in clusters], order=order)
    rows = []
    for k in order:
        row = {"indenter": int(k), "meas_force": forces[k].tolist(), "tip": tips[k].tolist()}
        if got[k] < 0:
            row.update(miss=True, pred_force=[0.0, 0.0, 0.0], pred_pos=None)
        else:
            c = clusters[got[k]]
            row.update(miss=False, pred_force=list(map(float, c.force_n)), pred_pos=list(map(float, c.position_mm)))
        rows.append(row)
    return rows


def summarize(rows: list[dict], rest_forces: list[float], phantoms: list[bool] | None = None) -> dict:
    """Seed §V-A style numbers from matched rows: mean absolute errors per axis and of |F|; with
    `phantoms` (one flag per single-contact frame) the fraction of those frames with a phantom cluster."""
    if not rows:
        return {"contact_samples": 0}
    mf = np.array([r["meas_force"] for r in rows])
    pf = np.array([r["pred_force"] for r in rows])
    hit = np.array([not r["miss"] for r in rows])
    out = {"contact_samples": len(rows), "detected_fraction": float(hit.mean()),
           "force_mae_n": dict(zip("xyz", np.abs(pf - mf).mean(0).round(4).tolist())),
           "force_mag_mae_n": float(np.abs(np.linalg.norm(pf, axis=1) - np.linalg.norm(mf, axis=1)).mean()),
           "force_mag_mean_meas_n": float(np.linalg.norm(mf, axis=1).mean()),
           "force_mag_bias_n": float((np.linalg.norm(pf, axis=1) - np.linalg.norm(mf, axis=1)).mean())}
    if hit.any():
        pp = np.array([r["pred_pos"] for r in rows if not r["miss"]])
        tp = np.array([r["tip"] for r in rows if not r["miss"]])
        out["position_mae_mm"] = dict(zip("xyz", np.abs(pp - tp).mean(0).round(4).tolist()))
        out["position_bias_mm"] = dict(zip("xyz", (pp - tp).mean(0).round(4).tolist()))
    rf = np.asarray(rest_forces, float)
    out["rest_frames"] = int(len(rf))
    if len(rf):
        out["rest_force_mean_n"] = float(rf.mean())
        out["rest_false_contact_fraction"] = float((rf > 0.0).mean())
    if phantoms is not None:
        out["single_contact_frames"] = len(phantoms)
        out["phantom_fraction"] = float(np.mean(phantoms)) if phantoms else None
    return out


def has_phantom(clusters: list, frame_rows: list[dict], cfg: EvalConfig = EvalConfig()) -> bool:
    """On a frame with one indenter in contact: a cluster other than the matched one holds > phantom_n."""
    pos = next((r["pred_pos"] for r in frame_rows if not r["miss"]), None)
    return any(c.force_mag_n > cfg.phantom_n for c in clusters
               if pos is None or list(map(float, c.position_mm)) != pos)


def evaluate_session(session_dir, package, calibration, cfg: EvalConfig = EvalConfig(), keep_fields_at=None) -> dict:
    """Replay a session through the runtime (runtime.offline.replay_session); returns rows, rest
    forces, per-frame traces, per frame the measured |F| per indenter and the clusters' |F| ("frames",
    what tools.train.scorecard scores), and the indenter names by id. A row also holds `split_force`:
    the frame's field split at the measured tips of the indenters above `phantom_n`
    (tools.scoring.split_at_tips; the raw field, before effects and correction)."""
    from ...contracts.session import load_session
    from ...runtime.offline import replay_session
    from ...runtime.stages.contacts import pixel_forces
    from ..sessions.writer import read_frames

    ses = load_session(session_dir)
    frames = ses.table("frames")
    meas = measured_at(ses, frames[:, 0])
    ids = sorted(meas)
    rows, rest, trace, kept, phantoms, per_frame = [], [], [], None, [], []
    for i, res in enumerate(replay_session(ses, package, calibration, precision=cfg.precision, threads=cfg.threads)):
        t = res.t
        tips = np.array([meas[k]["tip"][i] for k in ids])
        forces = np.array([meas[k]["force"][i] for k in ids])
        trace.append({"t": t, "meas": forces.sum(0).tolist(), "pred": res.force_n.tolist(),
                      "state": res.state, "n_clusters": len(res.clusters)})
        per_frame.append({"frame": i, "t": t, "fields": res.fields is not None,
                          "meas_mags": np.linalg.norm(forces, axis=1).tolist(),
                          "cluster_forces": [float(c.force_mag_n) for c in res.clusters]})
        if res.fields is None:
            continue
        if keep_fields_at is not None and i == keep_fields_at:
            img = next(read_frames(ses, [i]))[1]
            kept = {"fields": res.fields.copy(), "frame": i, "image": img[:, :, ::-1].copy()}
        mags = np.linalg.norm(forces, axis=1)
        if np.all(mags < cfg.rest_n):
            rest.append(float(np.linalg.norm(res.force_n)))
        fr = frame_errors(res.clusters, tips, forces, cfg)
        if fr:
            near = np.flatnonzero(mags > cfg.phantom_n)
            split = split_at_tips(pixel_forces(res.fields, calibration.pixel_area), calibration.surface_xyz,
                                  calibration.mask, tips[near])
            for r in fr:
                r["split_force"] = split[int(np.flatnonzero(near == r["indenter"])[0])].tolist()
        if (mags >= cfg.contact_n).sum() == 1 and (mags >= cfg.rest_n).sum() == 1:
            phantoms.append(has_phantom(res.clusters, fr, cfg))
        for r in fr:
            r.update(t=t, frame=i)
            rows.append(r)
    return {"rows": rows, "rest": rest, "trace": trace, "kept": kept, "sensor": ses.sensor_id, "phantoms": phantoms,
            "frames": per_frame, "indenters": {int(k): v for k, v in (ses.streams.get("poses", {}).get("indenters") or {}).items()}}



# ------------------------------------------------------------------------------------ error budget
# Where the force error comes from (docs/BENCHMARKS.md "Shipped model", error budget):
#   label ceiling  — the ground-truth label fields of a session's frames pushed through the runtime's
#                    contact stage (tools.scoring.find_contacts, the unit's pixel area) with the scored
#                    package's own contact settings (manifest runtime.contacts) vs the F/T;
#   network        — a model's fields vs those labels on train / validation / held-out frames, by force
#                    level and number of indenters.

FORCE_BINS = (1.5, 3.0, 5.0, 7.0, np.inf)


def sample_forces(fields: np.ndarray, calibration, tips: np.ndarray, forces: np.ndarray, contacts,
                  cfg: EvalConfig = EvalConfig()) -> dict:
    """One frame's (15, S, S) physical fields → image-integral force (3,) N and the matched cluster rows
    (`frame_errors`) against the measured tips/forces (K, 3), with the runtime's contact stage and the
    contact settings `contacts` (the scored package's own: tools.scoring.contact_config)."""
    from ...runtime.stages.contacts import pixel_forces

    fp = pixel_forces(fields, calibration.pixel_area)
    cl = find_contacts(fields, calibration, contacts)
    return {"integral": fp.reshape(3, -1).sum(1), "rows": frame_errors(cl, tips, forces, cfg)}


def budget_table(items: list[dict], key: str = "label") -> dict:
    """items: per sample {'meas' (3,), 'n_contact', key: sample_forces(...)} → |F| errors of the image
    integral (vs the summed measured force) and of the matched clusters (vs each indenter), overall, per
    |F| bin (of the summed measured force) and per number of indenters in contact."""
    def block(sel):
        its = [it for it, s in zip(items, sel) if s]
        if not its:
            return {"n": 0}
        d = np.array([np.linalg.norm(it[key]["integral"]) - np.linalg.norm(it["meas"]) for it in its])
        out = {"n": len(its), "integral_mae_n": float(np.abs(d).mean()), "integral_bias_n": float(d.mean())}
        s = summarize([r for it in its for r in it[key]["rows"]], [])
        out.update({k: s[k] for k in ("contact_samples", "detected_fraction", "force_mag_mae_n",
                                      "force_mag_bias_n") if k in s})
        if "position_mae_mm" in s:
            out["position_mae_mm"] = s["position_mae_mm"]
        return out

    mag = np.array([np.linalg.norm(it["meas"]) for it in items])
    nc = np.array([it["n_contact"] for it in items])
    contact = nc > 0
    out = {"all": block(contact)}
    for lo, hi in zip(FORCE_BINS[:-1], FORCE_BINS[1:]):
        out[f"F {lo:g}-{hi:g} N"] = block(contact & (mag >= lo) & (mag < hi))
    for k in sorted(set(nc[contact].tolist())):
        out[f"{k} indenter(s)"] = block(nc == k)
    if items and all("at_fe_frame" in it for it in items):   # re-solved labels: at an FE frame, or interpolated
        at_fe = np.array([it["at_fe_frame"] for it in items], bool)
        out["at an FE frame"] = block(contact & at_fe)
        out["between FE frames"] = block(contact & ~at_fe)
    return out


def session_label_samples(b, spec, stride: int = 1):
    """(samples dict as the dataset builds them + 'nind', calibration) of one session: the build's own
    label path (twin solves or re-solved FE, stage-4 ratios, the unit's tables), every `stride`-th frame."""
    from . import sources
    from .build import unit_calibration
    from .dataset import DatasetConfig, session_samples

    src = sources.label_sources(b, spec)
    ratios = {int(k): v for k, v in json.loads((b.root / "simreal" / f"{spec.name}.json").read_text())["ratios"].items()}
    cal = unit_calibration(b, spec.serial)
    dcfg = DatasetConfig(size=b.cfg.size, contact_stride=stride, rest_fraction=b.cfg.rest_fraction)
    if sources.fe_mode(b) == "twin":
        d = session_samples(b.session(spec), cal, [s.poke for s in src], [s.result for s in src],
                            [s.slots for s in src], ratios, dcfg)
    else:
        from ...contracts.session import load_session
        from .labels import LabelConfig, session_samples_measured

        d = session_samples_measured(b.session(spec), cal, src, ratios, dcfg,
                                     LabelConfig(frames=b.cfg.label_frames, sigma=b.cfg.label_sigma))
        d["at_fe_frame"] = at_fe_frames(load_session(b.session(spec)).table("frames")[:, 0], d["frame"], src)
    return d, cal


def budget_items(b, spec, d: dict, cal, contacts, predict=None, bounds: dict | None = None,
                 cfg: EvalConfig = EvalConfig()) -> list[dict]:
    """Per sample of one session: measured force, label forces (after the bounds' clipping when given) and,
    with `predict` ((n, 6, S, S) uint8 → (n, 15, S, S) physical), the model's forces; clusters with the
    contact settings `contacts`."""
    from ...contracts.session import load_session
    from .fields import denormalize, normalize_global

    ses = load_session(b.session(spec))
    meas = measured_at(ses, ses.table("frames")[:, 0])
    ids = sorted(meas)
    pred = predict(d["input"]) if predict is not None else None
    items = []
    for n, i in enumerate(d["frame"]):
        tips = np.array([meas[k]["tip"][i] for k in ids])
        forces = np.array([meas[k]["force"][i] for k in ids])
        lab = d["target"][n] if bounds is None else denormalize(normalize_global(d["target"][n], bounds), bounds)
        it = {"frame": int(i), "poke": int(d["poke"][n]), "meas": forces.sum(0),
              "n_contact": int((np.linalg.norm(forces, axis=1) > cfg.contact_n).sum()),
              "label": sample_forces(lab, cal, tips, forces, contacts, cfg)}
        if "at_fe_frame" in d:
            it["at_fe_frame"] = bool(d["at_fe_frame"][n])
        if pred is not None:
            it["pred"] = sample_forces(pred[n], cal, tips, forces, contacts, cfg)
        items.append(it)
    return items


def scored_package(b, package: str | None = None):
    """The model package whose contact settings the budget scores with: `package` (name or folder), else
    the build's exported package (its export stamp), else None."""
    from ...contracts.paths import models_dir
    from ...runtime.stages.model import load_package

    if package:
        return load_package(Path(package) if "/" in package else models_dir() / package)
    folder = b.read_stamp("export").get("package")
    if folder and (Path(folder) / "manifest.json").is_file():
        return load_package(Path(folder))
    return None


def budget_contacts(package):
    """The contact stage's settings of the budget: the package's own (tools.scoring.contact_config, what
    `tensortouch run` uses with it); the runtime defaults, said so, when no package is known."""
    if package is not None:
        return contact_config(package)
    from ...runtime.stages.contacts import ContactConfig

    log.warning("budget: no exported package to take the contact settings from; clustering with the "
                "runtime defaults (ContactConfig())")
    return ContactConfig()


def run_budget(b, predict=None, stride: int = 1, with_train: bool = True, contacts=None) -> dict:
    """The error budget of a build: label ceiling on the held-out sessions, and (with `predict`) the
    network's errors on train / validation / held-out samples, clustered with `contacts` (default the
    build's exported package's settings, `budget_contacts`). Returns nested tables (JSON-able)."""
    from .dataset import split_pokes
    from .fields import read_bounds

    bounds = read_bounds(b.dataset / "bounds.json") if (b.dataset / "bounds.json").is_file() else None
    contacts = contacts if contacts is not None else budget_contacts(scored_package(b))
    out = {"label_ceiling": {}, "network": {}, "contacts": asdict(contacts)}
    groups: dict[str, list] = {"train": [], "val": [], "heldout": []}
    specs = [(s, "heldout") for s in b.cfg.heldout] + ([(s, "train") for s in b.cfg.train] if with_train else [])
    for spec, split in specs:
        t0 = time.monotonic()
        d, cal = session_label_samples(b, spec, stride if split == "heldout" else b.cfg.contact_stride)
        items = budget_items(b, spec, d, cal, contacts, predict, bounds)
        if split == "heldout":
            out["label_ceiling"][spec.name] = budget_table(items, "label")
            groups["heldout"] += items
        else:
            si = [s.name for s in b.cfg.train].index(spec.name)
            val = split_pokes(int(max(d["poke"].max() + 1, 1)) if len(d["poke"]) else 1, si)
            for it in items:
                groups["val" if it["poke"] in val else "train"].append(it)
        log.info("budget %s: %d samples in %.0f s", spec.name, len(items), time.monotonic() - t0)
    if predict is not None:
        out["network"] = {g: budget_table(its, "pred") for g, its in groups.items() if its}
    return out


def _predictor(run: str | None, package: str | None, precision: str = "int8", bounds_file: Path | None = None):
    """(n, 6, S, S) uint8 → (n, 15, S, S) physical fields of a torch fit run (denormalized with
    `bounds_file`, the build's dataset bounds) or of an ONNX package (its manifest bounds)."""
    if run:
        import torch

        from .fields import denormalize, read_bounds
        from .model.train import load_trained, predict

        model, _ = load_trained(run)
        torch.set_num_threads(1)
        bounds = read_bounds(bounds_file)
        return lambda x: np.stack([denormalize(y, bounds) for y in predict(model, x)])
    if package:
        from ...contracts.paths import models_dir
        from ...runtime.stages.model import FieldModel, load_package

        m = FieldModel(load_package(Path(package) if "/" in package else models_dir() / package), precision, 2)
        return lambda x: np.stack([m(xi.astype(np.float32) / 255.0) for xi in x])
    return None


def add_budget_arguments(ap) -> None:
    """`tensortouch train budget …`: the error budget of a build (label and network error per stage)."""
    ap.add_argument("--recipe", default="hiera-qup-128", help="recipe whose build is scored (name, .toml or manifest)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a recipe field changed as in train all")
    ap.add_argument("--root", help="build folder (default: <cache>/train/<recipe name>/)")
    ap.add_argument("--run", help="torch fit run folder (best.pt) to score")
    ap.add_argument("--package", help="model package name or folder to score (ONNX, --precision)")
    ap.add_argument("--precision", default="int8", choices=("int8", "fp32"), help="network graph to run")
    ap.add_argument("--stride", type=int, default=1, help="every n-th contact frame of the held-out sessions")
    ap.add_argument("--heldout-only", action="store_true", help="score only the held-out sessions")
    ap.add_argument("--out", help="JSON file for the tables (default <build>/eval/budget.json)")


def run_budget_command(args) -> int:
    from .build import recipe_build

    b = recipe_build(args.recipe, args.set, args.root)
    res = run_budget(b, _predictor(args.run, args.package, args.precision, b.dataset / "bounds.json"), args.stride,
                     not args.heldout_only, budget_contacts(scored_package(b, args.package)))
    atomic_write_json(Path(args.out) if args.out else b.root / "eval" / "budget.json", res)
    print(json.dumps(res, indent=1))
    return 0

