"""Stage 3 — 2D–3D correspondence (seed §III.G): pokes at known 3D points → GPR θ/φ tables per unit.

Per unit a short calibration session is recorded with the twin: single-indenter pokes (sphere R3) at
random places of the cap. The poke plan is the same for every unit (so its FE solves are shared
through the FE cache); each unit renders it with its own camera. For each contact period found by
stage 1 on the measured F/T:
- 3D point: the mocap tip position at the force peak, projected radially onto the rest cap sphere
  (the indenter approaches along the surface normal) → true (θ, φ);
- 2D point: centroid of the image change between the rest frame before the period and the peak frame
  (|Δ| summed over RGB, Gaussian-blurred, weights above `diff_level` of its maximum), camera px.
`tools.recalib.gpr_geometry.refresh_geometry` fits the gel centre, φ rotation and θ = f_GPR(dist) from
the nominal design centre/radius; dense tables (θ, φ, surface_xyz, normals, pixel_area, mask) on the
model grid are then stored as a new version (`provenance.method = "gpr-pokes"`) in the build's
calibration store. For twin units the result is checked against the unit's true tables.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

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
    from tools.train.build import SessionSpec

    return SessionSpec(serial, cfg.seed, cfg.pokes, "mjpg", cfg.quality)


def record_calibration_session(b, serial: str, cfg: CorrespondenceConfig):
    """Record (or reuse) the unit's calibration poke session; returns its path."""
    from tools.twin.cli import _Bar
    from tools.twin.record import RecordConfig, Recorder

    path = b.root / "correspondence" / "sessions" / f"{serial}-calib"
    rcfg = RecordConfig(serial=serial, pokes=cfg.pokes, seed=cfg.seed, physics=b.cfg.physics,
                        frame_format="mjpg", mjpg_quality=cfg.quality, model_size=b.cfg.size)
    rcfg.trajectory = replace(rcfg.trajectory, kinds=("poke",), indenters=(cfg.indenter,), p_two=0.0,
                              depth_poke=cfg.depth)
    if not (path / "session.json").is_file():
        Recorder(rcfg, path, progress=_Bar()).run()
    return path


def correspondences(session_dir, gel, cfg: CorrespondenceConfig = CorrespondenceConfig()) -> dict:
    """Poke correspondences of one calibration session: camera px (N, 2) ↔ true θ, φ (N,)."""
    import cv2

    from runtime.session import load_session
    from tools.sessions.writer import read_frames
    from tools.train.keypoints import KeypointConfig, extract_keypoints

    ses = load_session(session_dir)
    frames = ses.table("frames")
    kps = extract_keypoints(ses.table("poses"), ses.table("wrench"), frames, KeypointConfig())
    poses = ses.table("poses")
    pairs = []
    for k in kps:
        if len(k.period.indenters) != 1:
            continue
        ind = int(k.period.indenters[0])
        col = list(k.indenter_ids).index(ind)
        j = int(np.argmax(np.linalg.norm(k.force[:, col], axis=1)))
        peak = int(k.frame_index[j])
        base = int(np.clip(np.searchsorted(frames[:, 0], k.period.t_start) - 1, 0, len(frames) - 1))
        p = poses[poses[:, 1] == ind]
        tip = p[int(np.argmin(np.abs(p[:, 0] - frames[peak, 0]))), 2:5]
        pairs.append((base, peak, tip))
    imgs = dict(read_frames(ses, sorted({i for a, c, _ in pairs for i in (a, c)})))
    xy, tips = [], []
    for base, peak, tip in pairs:
        c = image_change_centroid(cv2.cvtColor(imgs[base], cv2.COLOR_BGR2RGB),
                                  cv2.cvtColor(imgs[peak], cv2.COLOR_BGR2RGB), cfg)
        if np.all(np.isfinite(c)):
            xy.append(c)
            tips.append(tip)
    pts = project_to_cap(np.array(tips).reshape(-1, 3), gel.sphere_z, gel.sphere_radius)
    theta, phi = gel.theta_phi(pts)
    return {"xy": np.array(xy).reshape(-1, 2), "theta": theta, "phi": phi, "points": pts}


def gpr_tables(xy, theta, phi, gel, center0: tuple[float, float], radius: float, size: tuple[int, int]):
    """Poke correspondences → (GeometryFit, store tables, valid-pixel camera coordinates x, y):
    GPR θ(dist) + φ from `refresh_geometry`, completed on the gel by `tables_from_theta_phi`."""
    from runtime.preprocess import Preprocessor
    from tools.recalib.gpr_geometry import refresh_geometry

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
    from runtime.calibration import CalibrationStore
    from tools.twin.unit import TwinUnit, VariationConfig, calibration_meta

    unit = TwinUnit(spec_serial)
    nominal = TwinUnit(spec_serial, variation=VariationConfig(0.0, 0.0, 0.0, 0.0))
    path = record_calibration_session(b, spec_serial, cfg)
    c = correspondences(path, unit.gel, cfg)
    S = (b.cfg.size, b.cfg.size)
    radius = nominal.gel_radius_px
    fit, tables, x, y = gpr_tables(c["xy"], c["theta"], c["phi"], unit.gel, nominal.gel_center_px, radius, S)
    meta = calibration_meta(unit, b.cfg.size)
    meta["gel_center_px"] = [float(fit.center[0]), float(fit.center[1])]
    meta["gel_radius_px"] = float(radius)
    meta["provenance"] = {"method": "gpr-pokes", "pokes": int(len(c["xy"])),
                          "notes": f"tools.train.correspondence: {len(c['xy'])} twin calibration pokes, GPR θ(dist)",
                          "fit": {k: v for k, v in fit.fit.items() if k != "trend"}}
    version = CalibrationStore(b.store_root).write(spec_serial, tables, meta)
    return {"version": version, "pokes": int(len(c["xy"])), "center_px": list(fit.center),
            "true_center_px": list(unit.gel_center_px), **truth_errors(unit, tables, x, y),
            "poke_residual_theta_deg_rms": float(np.sqrt(np.mean(np.square(fit.residual_deg["theta"]))))}


def build_unit_calibrations(b, cfg: CorrespondenceConfig = CorrespondenceConfig()) -> dict:
    """Stage 3 for every unit of the build: GPR tables (tables = "gpr"), falling back to the unit's
    true tables when the fit fails; writes correspondence/<serial>.json naming the version to use."""
    from runtime.calibration import CalibrationStore
    from runtime.errors import TensorTouchError

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
                doc.update(method="gpr-pokes", version=g["version"], gpr=g)
                log.info("correspondence %s: %d pokes, θ error mean %.2f° p95 %.2f°", spec.serial, g["pokes"],
                         g["theta_err_deg"]["mean"], g["theta_err_deg"]["p95"])
            except TensorTouchError as exc:
                log.warning("correspondence %s: GPR fit failed (%s); using the unit's true tables", spec.serial, exc)
                doc["gpr_error"] = str(exc)
        (b.root / "correspondence" / f"{spec.serial}.json").write_text(json.dumps(doc, indent=1))
        out[spec.serial] = {"method": doc["method"], "version": doc["version"],
                            **({"theta_err_deg": doc["gpr"]["theta_err_deg"]} if "gpr" in doc else {})}
    return {"units": out}
