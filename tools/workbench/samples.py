"""Session -> sample table: measured force lined up with contact geometry and every covariate.

Reads only the measured streams of a session (wrench, poses, temperature, frames) and the
sensor's calibration (gel geometry, gel circle in the image). Never reads `truth/`, the
manifest's provenance or any effect list.

Per indenter (one F/T per indentation module, docs/session.md), measured through the tools' one
scoring path (tools.scoring.measured_at, with its explicit filters):
  force    F/T reading averaged over `average` consecutive samples (less noise), rotated into the
           sensor frame with the indenter pose and the F/T->indenter transform of the manifest.
           The table's sign is the F/T's (the load of the gel on the indenter): meas = −measured_at's
           "force" (the force the indenter applies to the gel, the sign the runtime publishes).
  pose     mocap tip position low-pass filtered (`pose_cutoff_hz`, zero-phase Butterworth) and
           interpolated to the force samples; orientation by spherical interpolation.
  geometry contact point = tip projected on the rest cap sphere; depth, normal, θ/φ (about the
           cap sphere centre, as the calibration tables), rim distance, slip since touch-down,
           depth rate, largest earlier depth; the tip's velocity and acceleration per axis
           (sensor frame, from the filtered mocap track, in and out of contact).
Brightness: mean frame intensity inside the gel circle / median of the first frames, usable
only on frames with no contact in the preceding `quiet_s` seconds.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ...contracts.errors import CalibrationError, SessionError
from ...contracts.session import Session
from ..scoring import measured_at
from .table import SampleTable, nearest_index

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SampleConfig:
    average: int = 4              # F/T samples averaged per table row (200 Hz -> 50 Hz)
    pose_cutoff_hz: float = 8.0   # low-pass of the mocap track
    baseline_frames: int = 10     # frames whose median intensity is brightness 1
    quiet_s: float = 0.3          # no contact this long before (and half as long after) a frame
    frame_stride: int = 1         # read every n-th frame


@dataclass(frozen=True)
class CapGeometry:
    """Spherical-cap gel (calibration.json "gel"): sphere radius, centre height, skirt height."""

    radius: float
    center_z: float
    skirt: float = 0.0

    @classmethod
    def from_calibration(cls, cal) -> "CapGeometry":
        gel = cal.meta.get("gel") or {}
        if "radius_mm" not in gel:
            raise CalibrationError(f"{cal.folder / 'calibration.json'}: field gel.radius_mm missing "
                                   "(the workbench needs the gel's cap sphere)")
        return cls(float(gel["radius_mm"]), float(gel.get("center_z_mm", 0.0)), float(gel.get("skirt_mm", 0.0)))

    @property
    def height(self) -> float:
        return self.center_z + self.radius

    @property
    def theta_rim(self) -> float:
        return float(np.arccos(np.clip((self.skirt - self.center_z) / self.radius, -1.0, 1.0)))

    def contact(self, tip: np.ndarray) -> dict[str, np.ndarray]:
        """Geometry of tip positions (N,3) against the rest surface."""
        c = np.array([0.0, 0.0, self.center_z])
        v = tip - c
        dist = np.linalg.norm(v, axis=1)
        n = v / np.maximum(dist, 1e-9)[:, None]
        depth = np.clip(self.radius - dist, 0.0, None)
        theta = np.arccos(np.clip(n[:, 2], -1.0, 1.0))
        phi = np.arctan2(n[:, 1], n[:, 0])
        rim = self.radius * np.clip(self.theta_rim - theta, 0.0, None) + self.skirt
        return {"depth": depth, "normal": n, "theta": theta, "phi": phi, "rim_distance": rim,
                "point": c + self.radius * n}


def _episodes_slip(t_depth: np.ndarray, tip: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Tangential travel (vector, N x 3) of the tip since the current contact began."""
    s = np.zeros_like(tip)
    touching = t_depth > 0
    start = None
    for i in range(len(tip)):
        if touching[i]:
            if start is None:
                start = i
            d = tip[i] - tip[start]
            s[i] = d - (d @ normal[i]) * normal[i]
        else:
            start = None
    return s


def indenter_series(session: Session, k: int, geom: CapGeometry, cfg: SampleConfig) -> dict:
    """Columns of one indenter's force samples."""
    wr = session.table("wrench")
    ps = session.table("poses")
    w = wr[wr[:, 1] == k]
    p = ps[ps[:, 1] == k]
    if len(w) < cfg.average * 4 or len(p) < 4:
        raise SessionError(f"{session.path}: indenter {k} has too few wrench/pose samples")
    m = measured_at(session, None, indenters=[k], average=cfg.average, pose_cutoff_hz=cfg.pose_cutoff_hz)[k]
    t, tip, R_ft = m["t"], m["tip"], m["rotation"]
    meas = -m["force"]                  # the table's sign: what the F/T reads (load on the indenter)
    g = geom.contact(tip)
    slip_vec = _episodes_slip(g["depth"], tip, g["normal"])
    return {"t": t, "meas": meas, "tip": tip, "ft_rotation": R_ft, "slip_vec": slip_vec, **g}


def frame_brightness(session: Session, cal, cfg: SampleConfig) -> tuple[np.ndarray, np.ndarray]:
    """(t, relative mean intensity inside the gel circle) per frame read."""
    import cv2

    frames = session.table("frames")
    kind, src = session.image_source()
    cx, cy = cal.gel_center_px
    r = cal.gel_radius_px
    values = []
    mask = None

    def add(img):
        nonlocal mask
        gray = img.mean(axis=2) if img.ndim == 3 else img
        if mask is None:
            yy, xx = np.mgrid[0:gray.shape[0], 0:gray.shape[1]]
            mask = (xx - cx) ** 2 + (yy - cy) ** 2 <= (0.9 * r) ** 2
        values.append(float(gray[mask].mean()))

    if kind == "video":
        cap = cv2.VideoCapture(str(src))
        i = 0
        while True:
            ok = cap.grab()
            if not ok:
                break
            if i % cfg.frame_stride == 0:
                ok, img = cap.retrieve()
                if ok:
                    add(img)
            i += 1
        cap.release()
    else:
        for idx in frames[::cfg.frame_stride, 1].astype(int):
            img = cv2.imread(str(src / f"{idx:06d}.png"), cv2.IMREAD_COLOR)
            if img is not None:
                add(img)
    v = np.asarray(values)
    t = frames[::cfg.frame_stride, 0][:len(v)]
    if len(v) == 0:
        return t, v
    base = float(np.median(v[:cfg.baseline_frames]))
    return t, v / max(base, 1e-9)


def build_table(session: Session, cal, cfg: SampleConfig | None = None, brightness: bool = True) -> SampleTable:
    """The sample table of a session (model column zero until a model predicts it)."""
    cfg = cfg or SampleConfig()
    for s in ("wrench", "poses"):
        if not session.has(s):
            raise SessionError(f"{session.path / 'session.json'}: stream '{s}' needed to compare forces")
    geom = CapGeometry.from_calibration(cal)
    ids = np.unique(session.table("wrench")[:, 1]).astype(int)
    parts = [indenter_series(session, int(k), geom, cfg) for k in ids]
    cat = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    series = np.concatenate([np.full(len(p["t"]), k, float) for k, p in zip(ids, parts)])
    depth = cat["depth"]
    max_depth = np.concatenate([np.maximum.accumulate(p["depth"]) for p in parts])
    rate = np.concatenate([np.gradient(p["depth"], p["t"]) for p in parts])
    cols = {"t": cat["t"], "series": series, "time": cat["t"] - float(session.manifest["clock"].get("t0", 0.0)),
            "depth": depth, "max_depth": max_depth, "rate": rate,
            "slip": np.linalg.norm(cat["slip_vec"], axis=1), "rim_distance": cat["rim_distance"],
            "theta": cat["theta"], "phi": cat["phi"], "gel_height": np.full(len(depth), geom.height)}
    vel = np.concatenate([np.gradient(p["tip"], p["t"], axis=0) for p in parts])   # mocap, in and out of contact
    acc = np.concatenate([np.gradient(np.gradient(p["tip"], p["t"], axis=0), p["t"], axis=0) for p in parts])
    for j, a in enumerate("xyz"):
        cols[f"vel_{a}"], cols[f"acc_{a}"] = vel[:, j], acc[:, j]
    if session.has("temperature"):
        tt = session.table("temperature")
        cols["temperature"] = np.interp(cat["t"], tt[:, 0], tt[:, 1])
    if brightness:
        tf, bv = frame_brightness(session, cal, cfg)
        if len(bv):
            contact_t = cat["t"][depth > 0]
            last = np.searchsorted(contact_t, tf, side="right") - 1
            since = np.where(last >= 0, tf - contact_t[np.clip(last, 0, None)], np.inf)
            nxt = np.clip(last + 1, 0, max(len(contact_t) - 1, 0))
            until = np.where(last + 1 < len(contact_t), contact_t[nxt] - tf, np.inf) if len(contact_t) else np.inf
            quiet = (since > cfg.quiet_s) & (until > 0.5 * cfg.quiet_s)
            j = nearest_index(tf, cat["t"])   # nearest frame
            first = series == ids[0]
            near = np.abs(tf[j] - cat["t"]) <= 0.5 * np.median(np.diff(tf)) if len(tf) > 1 else first
            ok = first & quiet[j] & near
            cols["brightness"] = np.where(ok, bv[j], np.nan)
            cols["bright_ok"] = ok.astype(float)
    names = session.streams["poses"].get("indenters", {})
    meta = {"session": str(session.path), "sensor_id": session.sensor_id, "config": cfg.__dict__,
            "indenters": {str(int(k)): names.get(str(int(k)), f"indenter{int(k)}") for k in ids},
            "gel": geom.__dict__}
    vec = {"normal": cat["normal"], "ft_rotation": cat["ft_rotation"], "slip_vec": cat["slip_vec"]}
    return SampleTable(cols, cat["meas"], np.zeros_like(cat["meas"]), vec, meta)
