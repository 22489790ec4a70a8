"""Stage 5 (shell) — twin sessions + FE results → the training dataset (docs/train.md "Dataset").

For each session frame chosen as a sample:
- input  = the runtime's own view: `runtime.stages.preprocess.Preprocessor(cx, cy, R, S).crop` of a baseline
           rest frame and of the current frame, with the unit's calibration centre/radius → uint8 (6, S, S);
- target = `tools.train.fields.fe_to_fields` of the FE solution at that frame (surface U, S, contact
           normal/shear forces), interpolated between the poke's keypoints with the twin's own PCHIP in the
           keypoint parameter σ (`tools.twin.physics.interpolate`), on the unit's θ/φ tables; contact
           forces scaled by the sim-to-real ratios of the indenter that owns each node (stage 4; nodes of
           two-indenter frames attributed by k-means, `attribute_contacts`); stresses scaled by the
           session's mean magnitude ratio (a displacement-controlled gel with all constants scaled);
- rest frames (no indenter in the poke window) get all-zero fields, so no contact predicts zero force.

Pure cores: `select_frames`, `surface_view`, `frame_fields`. Shell: `session_samples`, `write_dataset`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ...contracts.fields import N_CHANNELS
from ...contracts.files import atomic_write

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DatasetConfig:
    size: int = 128
    contact_stride: int = 2          # every n-th frame inside a poke's keypoint span
    rest_fraction: float = 0.15      # rest samples per contact sample
    master_baseline_share: float = 0.5   # share of samples whose baseline is the session's first frames
    master_frame: int = 2            # (the runtime's STARTUP picks its master among the first frames)
    seed: int = 0


def select_frames(frame_poke: np.ndarray, cfg: DatasetConfig = DatasetConfig()) -> list[tuple[int, int, int]]:
    """Samples of one session as (frame, baseline frame, poke or −1) from the per-frame poke labels
    (truth/frames.csv: −1 = no poke window). Contact frames: every `contact_stride`-th of each poke
    window (its first and last kept); baseline = the last rest frame before that poke, or — for a
    share `master_baseline_share`, seeded — the session's master frame. Rest frames: evenly spaced,
    `rest_fraction` × the contact samples, baseline = the rest frame before the latest poke (what the
    runtime holds while the gel recovers) or the master frame."""
    fp = np.asarray(frame_poke, int)
    rng = np.random.default_rng(cfg.seed)
    out: list[tuple[int, int, int]] = []
    starts: dict[int, int] = {}
    for p in sorted(set(fp[fp >= 0].tolist())):
        idx = np.flatnonzero(fp == p)
        starts[p] = int(idx[0])
        pre = np.flatnonzero(fp[:idx[0]] < 0)
        base = int(pre[-1]) if len(pre) else cfg.master_frame
        pick = sorted(set(idx[::max(1, cfg.contact_stride)].tolist()) | {int(idx[0]), int(idx[-1])})
        for i in pick:
            b = cfg.master_frame if rng.random() < cfg.master_baseline_share else base
            out.append((int(i), b, int(p)))
    rest = np.flatnonzero((fp < 0) & (np.arange(len(fp)) > cfg.master_frame + 2))
    n_rest = min(len(rest), int(round(cfg.rest_fraction * len(out))) if out else len(rest))
    for i in rest[np.linspace(0, len(rest) - 1, n_rest).round().astype(int)] if n_rest else []:
        before = [s for s in starts.values() if s < i]
        pre = np.flatnonzero(fp[:max(before)] < 0) if before else np.array([], int)
        base = int(pre[-1]) if len(pre) and rng.random() >= cfg.master_baseline_share else cfg.master_frame
        out.append((int(i), base, -1))
    return sorted(set(out))


def surface_view(res) -> SimpleNamespace:
    """FE result → its free-surface nodes: rest xyz, per-keypoint U/S/contact forces, triangles, areas."""
    from .fields import tributary_area

    sn = np.asarray(res.surface_nodes)
    remap = np.full(res.nodes.shape[0], -1)
    remap[sn] = np.arange(len(sn))
    tris = remap[np.asarray(res.surface_tris)]
    tris = tris[(tris >= 0).all(1)]
    xyz = np.asarray(res.nodes)[sn]
    return SimpleNamespace(xyz=xyz, tris=tris, area=tributary_area(xyz, tris),
                           U=np.asarray(res.U)[:, sn], S=np.asarray(res.S)[:, sn],
                           CNORMF=np.asarray(res.CNORMF)[:, sn], CSHEAR=np.asarray(res.CSHEAR)[:, sn],
                           pose_position=np.asarray(res.pose_position), RF=np.asarray(res.RF))


class FieldProjector:
    """`fe_to_fields` with the interpolation weights computed once per (surface nodes, θ/φ tables).

    The (θ, φ) linear interpolation (with φ padding and the nearest-value fill) is linear in the node
    values, so interpolating the identity gives a sparse pixel × node matrix W; each frame then costs
    one sparse product plus the Gaussian smoothing (the same `interpolate_to_grid` / `smooth_fields`).
    Contact forces are divided by `fields.contact_area` (force-conserving with `conserve_force`)."""

    def __init__(self, xyz: np.ndarray, area: np.ndarray, tables: dict, field_cfg):
        from scipy import sparse

        from .fields import contact_area, interpolate_to_grid, surface_angles

        self.xyz, self.cfg = np.asarray(xyz, float), field_cfg
        self.mask = np.asarray(tables["pixel_area"]) > 0
        th, ph = surface_angles(self.xyz, field_cfg)
        eye = np.eye(len(self.xyz), dtype=np.float32)
        w = interpolate_to_grid(th, ph, eye, tables["theta"], tables["phi"], self.mask, field_cfg)
        self.W = sparse.csr_matrix(w[:, self.mask].T.astype(np.float64))
        seen = self.W.T @ np.asarray(tables["pixel_area"], float)[self.mask]   # node kernel area on the grid
        self.contact_area = contact_area(np.asarray(area, float), seen, field_cfg)
        self.inv_area = 1.0 / np.where(self.contact_area > 0, self.contact_area, np.inf)
        self.key = (len(self.xyz), float(np.round(self.xyz.sum(), 6)))

    def project(self, u, s, cn, cs) -> np.ndarray:
        from .fields import smooth_fields

        values = np.concatenate([u, s, cn * self.inv_area[:, None], cs * self.inv_area[:, None]], axis=1)
        img = np.zeros((values.shape[1],) + self.mask.shape)
        img[:, self.mask] = (self.W @ values).T
        return smooth_fields(img, self.mask, self.cfg).astype(np.float32)


def frame_fields(view, poke, t: float, ratios: np.ndarray, stress_scale: float, tables: dict,
                 field_cfg, projector: FieldProjector | None = None) -> np.ndarray:
    """(15, S, S) physical fields of one frame at session time t inside the poke's keypoint span.

    ratios (K, 3): sim-to-real ratios of the poke's indenters (k-th indenter of the poke)."""
    from ..twin.physics import interpolate
    from .fields import attribute_contacts, fe_to_fields

    tt = np.array([float(t)])
    u, s = interpolate(view, poke, tt, "U")[0], interpolate(view, poke, tt, "S")[0] * stress_scale
    cn, cs = interpolate(view, poke, tt, "CNORMF")[0], interpolate(view, poke, tt, "CSHEAR")[0]
    K = ratios.shape[0]
    owner = np.full(len(u), -1)
    touch = np.flatnonzero(np.linalg.norm(cn, axis=1) + np.linalg.norm(cs, axis=1) > 1e-9)
    if len(touch):
        if K == 1:
            owner[touch] = 0
        else:
            pos = interpolate(view, poke, tt, "pose_position")[0]
            owner[touch] = attribute_contacts(view.xyz[touch], pos)
    from .simreal import apply_ratios

    cn, cs = apply_ratios(cn, owner, ratios), apply_ratios(cs, owner, ratios)
    if projector is not None:
        return projector.project(u, s, cn, cs)
    return fe_to_fields(view.xyz, u, s, cn, cs, tables["theta"], tables["phi"], tables["pixel_area"],
                        node_area=view.area, cfg=field_cfg)


def crops(session, pre, indices) -> dict[int, np.ndarray]:
    """{frame index: (S, S, 3) uint8 RGB crop} through the runtime's Preprocessor."""
    import cv2

    from ..sessions.writer import read_frames

    return {i: pre.crop(cv2.cvtColor(img, cv2.COLOR_BGR2RGB)) for i, img in read_frames(session, indices)}


def session_samples(session_dir: Path, calibration, plan, fe_results, slot_of_poke, ratios: dict,
                    cfg: DatasetConfig = DatasetConfig(), progress=None) -> dict:
    """All samples of one session: {'input' (n,6,S,S) u8, 'target' (n,15,S,S) f32 physical,
    'frame', 'baseline', 'poke' (n,)}.

    calibration: contracts.store.Calibration of the unit (tables + crop); fe_results[p]: the FEResult
    of poke p; slot_of_poke[p]: session indenter id per poke indenter; ratios: {slot: {'ratio': [3], ...}}."""
    from ...contracts.session import load_session, read_table
    from ...runtime.stages.preprocess import Preprocessor
    from .fields import FieldConfig
    from .simreal import slot_ratios

    ses = load_session(session_dir)
    fr = read_table(Path(session_dir) / "truth" / "frames.csv", ["t", "index", "poke", "sigma"])
    picks = select_frames(fr[:, 2], cfg)
    cx, cy = calibration.gel_center_px
    pre = Preprocessor(cx, cy, calibration.gel_radius_px, calibration.model_size)
    need = sorted({i for i, _, _ in picks} | {b for _, b, _ in picks})
    images = crops(ses, pre, need)
    gel = calibration.meta.get("gel", {})
    fcfg = FieldConfig(center_mm=(0.0, 0.0, float(gel.get("center_z_mm", 0.0))))
    tables = {"theta": calibration.theta, "phi": calibration.phi, "pixel_area": calibration.pixel_area}
    mags = [v["magnitude"] for v in ratios.values()] or [1.0]
    stress_scale = float(np.mean(mags))
    views, projectors = {}, {}
    S = calibration.model_size
    inp = np.zeros((len(picks), 6) + tuple(S), np.uint8)
    tgt = np.zeros((len(picks), N_CHANNELS) + tuple(S), np.float32)
    for n, (i, b, p) in enumerate(picks):
        inp[n, :3] = images[b].transpose(2, 0, 1)
        inp[n, 3:] = images[i].transpose(2, 0, 1)
        if p >= 0:
            if p not in views:
                views[p] = v = surface_view(fe_results[p])
                key = (len(v.xyz), float(np.round(v.xyz.sum(), 6)))
                if key not in projectors:
                    projectors[key] = FieldProjector(v.xyz, v.area, tables, fcfg)
                v.projector = projectors[key]
            tgt[n] = frame_fields(views[p], plan[p], float(fr[i, 0]), slot_ratios(ratios, slot_of_poke[p]),
                                  stress_scale, tables, fcfg, views[p].projector)
        if progress:
            progress(n + 1, len(picks))
    arr = np.array(picks, int).reshape(-1, 3)
    return {"input": inp, "target": tgt, "frame": arr[:, 0], "baseline": arr[:, 1], "poke": arr[:, 2]}


def split_pokes(n_pokes: int, session_index: int, every: int = 2) -> set[int]:
    """Validation pokes of a session: one poke of every `every`-th session (≈ 10 % of the samples)."""
    return {session_index % max(1, n_pokes)} if session_index % every == 0 else set()


def write_dataset(root: Path, parts: list[dict], size: int, source: str, pixel_area: np.ndarray | None = None,
                  bounds: dict | None = None, compress: bool = True) -> str:
    """parts: per session {'input', 'target' (physical), 'val' (bool per sample)[, 'force_n' (n, 3): the
    rig's measured total force per sample, kept in the index][, 'contacts_n' (n, 2, 5): two indenters'
    measured forces and pixels (distill.contact_pixels), kept where finite]} → dataset directory
    (index.json, bounds.json, samples/, and pixel_area.npy = the units' mean pixel area in mm² when
    given, for the fit's total-force term); returns the data hash (SHA-256 of index.json). With `bounds`
    the targets are already normalized by them (a distilled set) and are written as they are."""
    from .fields import compute_bounds, normalize_global, write_bounds
    from .model.data import write_index, write_sample

    root = Path(root)
    given = bounds is not None
    if not given:
        bounds = compute_bounds(t for p in parts for t in p["target"])
    write_bounds(root / "bounds.json", bounds)
    if pixel_area is not None:
        atomic_write(root / "pixel_area.npy", lambda fh: np.save(fh, np.asarray(pixel_area, np.float32)))
    entries, i = [], 0
    for p in parts:
        force, two = p.get("force_n"), p.get("contacts_n")
        for j, (inp, tgt, val) in enumerate(zip(p["input"], p["target"], p["val"])):
            e = write_sample(root, i, inp, tgt if given else normalize_global(tgt, bounds), compress=compress)
            e["split"] = "val" if val else "train"
            if force is not None:
                e["force_n"] = [float(v) for v in force[j]]
            if two is not None and np.isfinite(two[j]).all():
                e["contacts_n"] = [[float(v) for v in c] for c in two[j]]
            entries.append(e)
            i += 1
    h = write_index(root, entries, (size, size), source)
    log.info("dataset %s: %d samples (%d val), hash %s", root, len(entries),
             sum(e["split"] == "val" for e in entries), h[:12])
    return h
