"""Stage 3 — 2D–3D correspondence (seed §III.G): pokes at known 3D points → GPR θ/φ tables per unit.

Per unit a short calibration session is recorded with the twin: light single-indenter pokes
(sphere R3, 0.8–1.2 mm, < 1 N) at random places of the cap. The poke plan is the same for every unit
(so its FE solves, and the label re-solves from the measured poses, are shared through the FE cache);
each unit renders it with its own camera, as stills (`RecordConfig.camera`): only the frames around
each poke's start and deepest moment, the ones the detector reads, each equal to the video's frame at
that time (rendering all 783 frames of the 9 pokes was most of a unit's time). For each
contact found on the measured F/T (stage 1 with the calibration thresholds `contact_force_n` /
`detach_force_n`: light pokes never reach the seed's 1.5 N):
- 3D point: the mocap tip (smoothed, `resolve.fit_pose`) at the deepest moment of the poke (smallest
  clearance to the rest gel), projected radially onto the rest cap sphere (the indenter approaches
  along the surface normal) → true (θ, φ);
- FE: the poke re-solved from the measured poses (clear initial pose → that deepest pose, one FE
  frame; `resolve.period_scenario`, tools.fe batch runner and shared cache) → surface displacement;
- 2D point: `tools.train.pokes2d` — the dot motion between the rest frame before the poke and the
  camera frame nearest the deepest moment, matched with the motion predicted from the FE
  displacement and the sensor design's nominal lens → sub-pixel image of the 3D point.
`tools.recalib.gpr_geometry.refresh_geometry` fits the gel centre, φ rotation and θ = f_GPR(dist) from
the nominal design centre. The crop radius (`crop`) is the design's rim radius ("nominal") or the unit's
rim measured in the session's rest frames ("rim", `session_rim`: the circle `tensortouch calib init`
fits on a rig, so a model trained on these crops sees a new unit the way its calibration crops it);
dense tables (θ, φ, surface_xyz, normals, pixel_area, mask) on the
model grid are then stored as a new version (`provenance.method = "gpr-pokes"`) in the build's
calibration store. For twin units the result is checked against the unit's true tables (diagnostics
only: nothing downstream reads them). `image_change_centroid` is the simple detector (kept for
comparison: 1.6–9 px off).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from ...contracts.errors import TensorTouchError
from ...contracts.files import atomic_write_json

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CorrespondenceConfig:
    pokes: int = 9                   # calibration pokes per unit (GPR fit needs ≥ 6)
    seed: int = 900                  # one plan for every unit: FE solves shared via the cache
    indenter: str = "sphere3"
    depth: tuple = (0.8, 1.2)        # mm
    diff_blur_px: float = 2.0
    diff_level: float = 0.5          # weights: blurred |Δ| above this fraction of its maximum
    quality: int = 90                # MJPG quality of the calibration recordings
    contact_force_n: float = 0.3     # stage-1 thresholds for the light calibration pokes (F/T noise 0.02 N)
    detach_force_n: float = 0.2
    camera: str = "stills"           # twin camera of the calibration session: "stills" renders only the frames
                                     # the detector can read (around each poke's start and deepest moment); "video" all
    crop: str = "nominal"            # crop radius of the tables: "nominal" (the design's rim radius) or "rim" (the
                                     # unit's rim measured in the session's rest frames, `runtime.calib.rim.fit_rim`)
    rest_frames: int = 3             # frames before the first contact averaged for the rim
    rest_margin_s: float = 0.2       # ... ending this long before the first measured contact


def image_change_centroid(base: np.ndarray, cur: np.ndarray, cfg: CorrespondenceConfig = CorrespondenceConfig()
                          ) -> tuple[float, float]:
    """(x, y) camera px of the centre of the change between two (H, W, 3) uint8 frames."""
    d = np.abs(cur.astype(np.float32) - base.astype(np.float32)).sum(axis=2)
    d = ndimage.gaussian_filter(d, cfg.diff_blur_px)
    w = np.clip(d - cfg.diff_level * d.max(), 0.0, None)
    if not w.sum() > 0:
        return float("nan"), float("nan")
    yy, xx = np.mgrid[0:d.shape[0], 0:d.shape[1]]
    return float((w * xx).sum() / w.sum()), float((w * yy).sum() / w.sum())


def project_to_cap(tip_xyz: np.ndarray, sphere_z: float, sphere_radius: float) -> np.ndarray:
    """Tip positions (N, 3) → nearest points of the rest cap sphere (radial projection)."""
    c = np.array([0.0, 0.0, sphere_z])
    v = np.asarray(tip_xyz, float).reshape(-1, 3) - c
    return c + sphere_radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def tables_from_theta_phi(theta: np.ndarray, phi: np.ndarray, gel, valid: np.ndarray) -> dict:
    """θ/φ tables → the calibration store's tables on the twin gel (cap + skirt): surface points,
    outward normals, per-pixel area |∂X/∂u × ∂X/∂v| (central differences), mask."""
    th = np.where(valid, np.clip(theta, 0.0, gel.theta_max - 1e-6), 0.0)
    pts = gel.point_at(th, phi)
    dxv, dxu = np.gradient(pts, axis=(0, 1))
    area = np.linalg.norm(np.cross(dxu, dxv), axis=-1)
    mask = valid & (theta <= gel.theta_max)
    nrm = gel.normals(pts)
    z = lambda a: np.where(mask[..., None] if a.ndim == 3 else mask, a, 0.0)  # noqa: E731
    return {"theta": z(theta).astype(np.float32), "phi": z(phi).astype(np.float32),
            "surface_xyz": z(pts).astype(np.float32), "normals": z(nrm).astype(np.float32),
            "pixel_area": z(area).astype(np.float32), "mask": mask}


def calibration_spec(serial: str, cfg: CorrespondenceConfig):
    from .build import SessionSpec

    return SessionSpec(serial, cfg.seed, cfg.pokes, "mjpg", cfg.quality)


def record_calibration_session(b, serial: str, cfg: CorrespondenceConfig):
    """Record (or reuse) the unit's calibration poke session; returns its path."""
    from ..progress import stage_progress
    from ..twin.record import RecordConfig, Recorder

    path = b.root / "correspondence" / "sessions" / f"{serial}-calib"
    rcfg = RecordConfig(serial=serial, pokes=cfg.pokes, seed=cfg.seed, physics=b.cfg.physics,
                        frame_format="mjpg", mjpg_quality=cfg.quality, model_size=b.cfg.size, camera=cfg.camera)
    rcfg.trajectory = replace(rcfg.trajectory, kinds=("poke",), indenters=(cfg.indenter,), p_two=0.0,
                              depth_poke=cfg.depth)
    if not (path / "session.json").is_file():
        Recorder(rcfg, path, progress=stage_progress(path.name)).run()
    return path


def session_rim(session_dir, center0: tuple[float, float], radius0: float,
                 cfg: CorrespondenceConfig = CorrespondenceConfig()):
    """The gel rim (`RimFit`) in a calibration session's rest frames: the first `rest_frames` frames that end
    `rest_margin_s` before the first F/T reading above `contact_force_n`, averaged, then `fit_rim` from the
    design's circle: what `tensortouch calib init` does on a rig, from the recording alone."""
    from ...contracts.session import load_session
    from ...runtime.calib.rim import fit_rim, rest_image
    from ..sessions.writer import read_frames

    ses = load_session(session_dir)
    frames = ses.table("frames")
    w = ses.table("wrench")
    loaded = np.linalg.norm(w[:, 2:5], axis=1) > cfg.contact_force_n
    t_touch = float(w[loaded, 0].min()) if loaded.any() else float("inf")
    rest = frames[frames[:, 0] < t_touch - cfg.rest_margin_s][:cfg.rest_frames]
    if not len(rest):
        raise CorrespondenceError(f"{session_dir}: no frame before the first contact (t {t_touch:.2f} s) to find "
                                  "the gel rim in; the calibration session must start at rest")
    imgs = [img for _, img in read_frames(ses, rest[:, 1].astype(int))]
    return fit_rim(rest_image(imgs), center0, radius0, where=f"{session_dir} rest frames")


def nominal_lens():
    """The sensor design's lens (nominal fisheye of tools.twin.camera.CameraConfig: focal, centre, camera
    height) — what a real unit's datasheet gives before calibration."""
    from ..twin.camera import CameraConfig, FisheyeModel

    return FisheyeModel(CameraConfig())


def poke_moments(session, cfg: CorrespondenceConfig, gel_surface, catalog=None) -> list[dict]:
    """Single-indenter contacts of a calibration session → per poke: indenter id/name, the deepest
    moment t_peak (smallest clearance of the smoothed mocap pose to the rest gel), the tip there."""
    from ..fe import Indenter
    from ..fe.indenters import make_shape
    from ..twin.trajectory import INDENTER_SET
    from .keypoints import KeypointConfig, extract_keypoints
    from .resolve import PoseTrack, ResolveConfig, clearance, fit_pose, surface_samples

    catalog = catalog or INDENTER_SET
    rcfg = ResolveConfig()
    names = {int(k): v for k, v in session.streams["poses"].get("indenters", {}).items()}
    poses = session.table("poses")
    kcfg = KeypointConfig(contact_force_n=cfg.contact_force_n, detach_force_n=cfg.detach_force_n)
    kps = extract_keypoints(poses, session.table("wrench"), session.table("frames"), kcfg)
    surf = surface_samples(gel_surface, rcfg.surface_spacing_mm)
    out = []
    for k in kps:
        if len(k.period.indenters) != 1:
            continue
        ind = int(k.period.indenters[0])
        spec = catalog[names[ind]]
        shape = make_shape(Indenter(shape=spec["shape"], params=dict(spec["params"])))
        tr = PoseTrack.from_table(poses, ind)
        ts = tr.t[(tr.t >= k.period.t_start) & (tr.t <= k.period.t_end)]
        if len(ts) == 0:
            continue
        P, R = fit_pose(tr, ts, rcfg.pose_half_window_s)
        gap = np.array([clearance(shape, p, r, surf) for p, r in zip(P, R)])
        i = int(np.argmin(gap))
        out.append({"indenter": ind, "name": names[ind], "t_peak": float(ts[i]), "tip": P[i], "depth": float(-gap[i]),
                    "t_start": float(k.period.t_start), "track": tr})
    return out


def correspondences(b, session_dir, gel, cfg: CorrespondenceConfig = CorrespondenceConfig()) -> dict:
    """Poke correspondences of one calibration session: camera px (N, 2) ↔ true θ, φ (N,), with the
    FE of each poke re-solved from its measured poses (cached) and the model-based 2D detector."""
    import cv2

    from ...contracts.session import load_session
    from ..sessions.writer import read_frames
    from .pokes2d import FlowPredictor, PokeDetectConfig, fit_offset, track_dots

    ses = load_session(session_dir)
    frames = ses.table("frames")
    period = 1.0 / float(ses.streams["frames"].get("fps", 30.0))
    moments = poke_moments(ses, cfg, gel)
    sources = _calibration_fe(b, Path(session_dir).name, moments, gel)
    lens = nominal_lens()
    dcfg = PokeDetectConfig()
    pairs = []
    for m, src in zip(moments, sources):
        if src is None:
            continue
        peak = int(np.argmin(np.abs(frames[:, 0] - m["t_peak"])))
        base = int(np.searchsorted(frames[:, 0], src["t_init"])) - 1
        if base < 0:
            continue
        if abs(frames[peak, 0] - m["t_peak"]) > period:   # stills that miss the measured deepest moment
            log.warning("%s: no frame within %.3f s of the poke's deepest moment t %.2f s; poke left out",
                        session_dir, period, m["t_peak"])
            continue
        pairs.append((int(frames[base, 1]), int(frames[peak, 1]), m, src))
    imgs = dict(read_frames(ses, sorted({i for a, c, _, _ in pairs for i in (a, c)})))
    xy, pts, diag = [], [], []
    for base, peak, m, src in pairs:
        p3 = project_to_cap(m["tip"][None], gel.profile.center_z_mm, gel.profile.radius_mm)[0]
        q0 = lens.project(p3)
        x, v = track_dots(cv2.cvtColor(imgs[base], cv2.COLOR_BGR2GRAY), cv2.cvtColor(imgs[peak], cv2.COLOR_BGR2GRAY), dcfg)
        res = src["result"]
        sn = np.asarray(res.surface_nodes)
        U = np.asarray(res.U)[0][sn]
        fit = fit_offset(x, v, FlowPredictor(lens, gel, np.asarray(res.nodes)[sn], U, q0, dcfg), dcfg)
        diag.append({"t_peak": m["t_peak"], "depth_mm": m["depth"], "dots": fit["dots"], "rms_px": fit["rms_px"],
                     "offset_px": fit["offset"], "scale": fit["scale"], "ok": fit["ok"]})
        if fit["ok"]:
            xy.append(fit["xy"])
            pts.append(p3)
        else:
            log.warning("%s: poke at t %.2f s not located (%d dots, rms %.2f px)", session_dir, m["t_peak"],
                        fit["dots"], fit["rms_px"])
    pts = np.array(pts).reshape(-1, 3)
    theta, phi = gel.theta_phi(pts) if len(pts) else (np.zeros(0), np.zeros(0))
    return {"xy": np.array(xy).reshape(-1, 2), "theta": theta, "phi": phi, "points": pts, "pokes": diag}


def _calibration_fe(b, name: str, moments: list[dict], gel) -> list:
    """FE displacement of each calibration poke at its deepest moment: scenario from the measured
    poses (clear initial pose → one FE frame at t_peak), solved through the tools.fe batch runner
    (shared cache); hertz-fallback builds use the analytic stand-in. None where it failed."""
    from ..fe import GelGeometry, load_result, save_scenario
    from ..fe.batch import run_batch
    from ..twin.trajectory import INDENTER_SET
    from .resolve import ResolveError, period_scenario
    from .sources import fallback_solve, fe_cache_dir, label_solver

    fe_gel = GelGeometry(kind="flattened_dome", radius=gel.radius, cap_height=gel.cap_height, skirt=gel.skirt)
    items = []
    for i, m in enumerate(moments):
        try:
            ps = period_scenario([m["track"]], [m["indenter"]], [m["name"]], np.array([m["t_peak"]]), INDENTER_SET,
                                 fe_gel, gel, solver=label_solver(b))
        except ResolveError as exc:
            log.warning("%s poke %d: no FE scenario (%s)", name, i, exc)
            items.append(None)
            continue
        f = b.root / "correspondence" / "scenarios" / name / f"p{i:02d}.json"
        save_scenario(ps.scenario, f)
        items.append((f, ps))
    todo = [it for it in items if it is not None]
    if b.cfg.physics == "fe" and todo:
        run_batch([str(f) for f, _ in todo], fe_cache_dir(), workers=1)
    out = []
    for it in items:
        if it is None:
            out.append(None)
            continue
        f, ps = it
        if b.cfg.physics == "fe":
            path = fe_cache_dir() / f"{ps.scenario.hash()}.npz"
            out.append({"result": load_result(path), "t_init": ps.t_init} if path.is_file() else None)
        else:
            out.append({"result": fallback_solve(ps, gel), "t_init": ps.t_init})
    return out


def gpr_tables(xy, theta, phi, gel, center0: tuple[float, float], radius: float, size: tuple[int, int]):
    """Poke correspondences → (GeometryFit, store tables, valid-pixel camera coordinates x, y):
    GPR θ(dist) + φ from `refresh_geometry`, completed on the gel by `tables_from_theta_phi`."""
    from ...runtime.stages.preprocess import Preprocessor
    from ..recalib.gpr_geometry import refresh_geometry

    fit = refresh_geometry(xy, theta, phi, center0, radius, size)
    vv, uu = np.mgrid[0:size[0], 0:size[1]].astype(float)
    x, y = Preprocessor(fit.center[0], fit.center[1], radius, size).to_raw(uu, vv)
    valid = np.hypot(x - fit.center[0], y - fit.center[1]) <= radius
    tables = tables_from_theta_phi(fit.theta.astype(float), fit.phi.astype(float), gel, valid)
    return fit, tables, x, y


def truth_errors(unit, tables: dict, x: np.ndarray, y: np.ndarray, theta_max: float = 0.6) -> dict:
    """θ/φ errors (deg) of recovered tables against a twin unit's true lens at the same camera px
    (pixels on the gel with θ ≤ theta_max, where the pokes are)."""
    dirs, fov = unit.model.rays(np.stack([x, y], -1))
    tp, ok = unit.gel.intersect(unit.model.center, dirs)
    th_true, ph_true = unit.gel.theta_phi(tp)
    cmp = ok & fov & tables["mask"] & (th_true <= theta_max)
    err_t = np.degrees(np.abs(tables["theta"] - th_true))[cmp]
    err_p = np.degrees(np.abs((tables["phi"] - ph_true + np.pi) % (2 * np.pi) - np.pi))[cmp & (th_true > 0.1)]
    return {"theta_err_deg": {"mean": float(err_t.mean()), "p95": float(np.percentile(err_t, 95)),
                              "max": float(err_t.max())},
            "phi_err_deg": {"mean": float(err_p.mean()), "p95": float(np.percentile(err_p, 95))}}


def fit_unit(b, spec_serial: str, cfg: CorrespondenceConfig = CorrespondenceConfig()) -> dict:
    """GPR calibration of one unit → new store version; returns diagnostics (vs the twin truth)."""
    from ...contracts.store import CalibrationStore
    from ..twin.unit import TwinUnit, VariationConfig, calibration_meta

    unit = TwinUnit(spec_serial)
    nominal = TwinUnit(spec_serial, variation=VariationConfig(0.0, 0.0, 0.0, 0.0))
    path = record_calibration_session(b, spec_serial, cfg)
    c = correspondences(b, path, unit.gel, cfg)
    S = (b.cfg.size, b.cfg.size)
    rim = None
    if cfg.crop == "rim":
        rim = session_rim(path, nominal.gel_center_px, nominal.gel_radius_px, cfg)
        radius = rim.radius
    elif cfg.crop == "nominal":
        radius = nominal.gel_radius_px
    else:
        raise CorrespondenceError(f"correspondence crop = {cfg.crop!r}: expected 'nominal' or 'rim'")
    fit, tables, x, y = gpr_tables(c["xy"], c["theta"], c["phi"], unit.gel, nominal.gel_center_px, radius, S)
    meta = calibration_meta(unit, b.cfg.size)
    meta["gel_center_px"] = [float(fit.center[0]), float(fit.center[1])]
    meta["gel_radius_px"] = float(radius)
    meta["provenance"] = {"method": "gpr-pokes", "pokes": int(len(c["xy"])), "crop": cfg.crop,
                          "notes": f"tools.train.correspondence: {len(c['xy'])} twin calibration pokes, GPR θ(dist)",
                          "fit": {k: v for k, v in fit.fit.items() if k != "trend"}}
    if rim is not None:
        meta["provenance"]["rim"] = rim.to_dict()
    version = CalibrationStore(b.store_root).write(spec_serial, tables, meta)
    return {"version": version, "pokes": int(len(c["xy"])), "center_px": list(fit.center),
            "true_center_px": list(unit.gel_center_px), "crop": cfg.crop, "radius_px": float(radius),
            "true_radius_px": float(unit.gel_radius_px), **truth_errors(unit, tables, x, y),
            "poke_residual_theta_deg_rms": float(np.sqrt(np.mean(np.square(fit.residual_deg["theta"])))),
            "pokes_2d": c["pokes"], "poke_px_err_vs_truth": _px_truth_errors(unit, c)}


def _px_truth_errors(unit, c: dict) -> list:
    """Detected 2D poke points minus the twin lens's exact projection of the 3D points (px; diagnostics)."""
    if not len(c["points"]):
        return []
    return np.round(np.asarray(c["xy"]) - unit.model.project(c["points"]), 3).tolist()


class CorrespondenceError(TensorTouchError):
    """A unit's GPR calibration failed: the build stops (it never falls back to the twin's truth)."""


def build_unit_calibrations(b, cfg: CorrespondenceConfig | None = None) -> dict:
    """Stage 3 for every unit of the build: GPR tables (tables = "gpr") or the twin's true tables
    (tables = "truth"); writes correspondence/<serial>.json naming the version to use. A GPR fit that
    fails raises CorrespondenceError naming the unit: a build never swaps in the true tables behind
    the recipe's back."""
    from ...contracts.store import CalibrationStore

    cfg = cfg or CorrespondenceConfig(crop=getattr(b.cfg, "crop", "nominal"))
    store = CalibrationStore(b.store_root)
    out = {}
    for spec in b.all_sessions():
        truth_version = next(h["version"] for h in reversed(store.history(spec.serial))
                             if h["provenance"].get("method") == "twin-truth")
        doc = {"serial": spec.serial, "truth_version": truth_version, "method": "twin-truth",
               "version": truth_version}
        if b.cfg.tables == "gpr":
            try:
                g = fit_unit(b, spec.serial, cfg)
            except TensorTouchError as exc:
                raise CorrespondenceError(f"correspondence {spec.serial} (session {spec.name}): the GPR fit failed "
                                          f"({exc}); the build stops (tables = \"gpr\" never falls back to the "
                                          f"unit's true tables)") from exc
            doc.update(method="gpr-pokes", version=g["version"], gpr=g)
            log.info("correspondence %s: %d pokes, θ error mean %.2f° p95 %.2f°, crop %s %.2f px (true rim %.2f px)",
                     spec.serial, g["pokes"], g["theta_err_deg"]["mean"], g["theta_err_deg"]["p95"], g["crop"],
                     g["radius_px"], g["true_radius_px"])
        atomic_write_json(b.root / "correspondence" / f"{spec.serial}.json", doc)
        out[spec.serial] = {"method": doc["method"], "version": doc["version"],
                            **({"theta_err_deg": doc["gpr"]["theta_err_deg"]} if "gpr" in doc else {})}
    return {"units": out}
