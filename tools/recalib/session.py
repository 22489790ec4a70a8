"""The guided recalibration session: frames → pokes → fit → decision (no devices, no files here).

`run_guided` consumes (t, clusters) per frame (the shell feeds them from the camera through the
runtime's SensorPipeline with the correction switched off, so the fit sees the raw model force),
tells the user where to poke next, detects each poke, pairs it with a reference force and accepts
or rejects it with a reason. `analyse` turns the accepted pokes into a correction fit (and, when
true 3D poke positions are known, a geometry refresh) plus the store/refuse decision.

References (the "gauge"): `GaugeReference` (serial gauge, background reader), `TypedReference`
(the user types the gauge's peak-hold reading), `StreamReference` (a recorded force stream on the
frames' clock: a replayed session's wrench.csv — how the twin's force gauge enters).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ...contracts.errors import CalibrationError
from ...contracts.store import Calibration
from ...runtime.stages.geometry import sample_bilinear
from .fit import CorrectionFit, Decision, FitConfig, PokeSet, decide, error_stats, fit_correction
from .gpr_geometry import GeometryFit, GeometryFitConfig, camera_to_model, model_to_camera, refresh_geometry, theta_phi_from_xyz
from .pokes import Poke, PokeDetector, PokeRules, ascii_map, check_poke, describe, reference_from_readings, suggest_next
from .store_ops import active_magnitudes

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SessionConfig:
    pokes: int = 6                 # accepted pokes to collect (seed: 5–7)
    max_attempts: int = 20         # detected pokes (accepted + rejected) before giving up
    rules: PokeRules = field(default_factory=PokeRules)
    fit: FitConfig = field(default_factory=FitConfig)
    geometry: GeometryFitConfig = field(default_factory=GeometryFitConfig)


class GaugeReference:
    """Serial force gauge (drivers.gauge.ForceGauge, started) on the frames' monotonic clock."""

    def __init__(self, gauge, rules: PokeRules = PokeRules()):
        self.gauge, self.rules = gauge, rules
        self.name = f"gauge {gauge.cfg.url} ({gauge.cfg.protocol})"

    def check(self) -> None:
        self.gauge.check()

    def for_poke(self, poke: Poke) -> float | None:
        self.gauge.check()
        t, f = self.gauge.window(poke.t0 - 1.0, poke.t1 + 1.0)
        return reference_from_readings(np.array(t), np.array(f), poke.t0, poke.t1, self.rules)


class TypedReference:
    """The user reads the gauge (peak hold) and types the value in N."""

    name = "typed in"

    def __init__(self, ask=input, say=print, tries: int = 3):
        self.ask, self.say, self.tries = ask, say, tries

    def check(self) -> None:
        pass

    def for_poke(self, poke: Poke) -> float | None:
        for _ in range(self.tries):
            text = self.ask(f"  gauge peak reading for this poke in N (sensor saw {poke.pred_mag:.2f} N), "
                            "or 's' to skip: ").strip()
            if text.lower() in ("s", "skip"):
                return None
            try:
                value = float(text.replace(",", "."))
            except ValueError:
                self.say(f"  '{text}' is not a number in N")
                continue
            if value >= 0:
                return value
            self.say("  a force magnitude is >= 0 N")
        return None


class StreamReference:
    """A recorded force stream on the frames' clock, e.g. a replayed session's wrench.csv (the twin's
    force gauge): rows (t s, indenter id, F vector N); a poke's reference is the strongest indenter's
    plateau mean |F| during the poke (|F| does not depend on the F/T frame's orientation)."""

    def __init__(self, t: np.ndarray, force: np.ndarray, indenter: np.ndarray | None = None,
                 name: str = "recorded force stream", rules: PokeRules = PokeRules()):
        self.t = np.asarray(t, float)
        self.mag = np.linalg.norm(np.asarray(force, float).reshape(len(self.t), -1), axis=1)
        self.ind = np.zeros(len(self.t)) if indenter is None else np.asarray(indenter, float)
        self.name, self.rules = name, rules

    @classmethod
    def from_session(cls, session, rules: PokeRules = PokeRules()) -> "StreamReference":
        w = session.table("wrench")
        return cls(w[:, 0], w[:, 2:5], w[:, 1], f"{session.path.name}/wrench.csv", rules)

    def check(self) -> None:
        pass

    def for_poke(self, poke: Poke) -> float | None:
        vals = [reference_from_readings(self.t[self.ind == k], self.mag[self.ind == k], poke.t0, poke.t1, self.rules)
                for k in np.unique(self.ind)]
        vals = [v for v in vals if v is not None]
        return max(vals) if vals else None


@dataclass
class SessionOutcome:
    accepted: list[Poke]
    rejected: list[Poke]
    frames: int
    complete: bool


def run_guided(frames, cal: Calibration, reference, cfg: SessionConfig = SessionConfig(), say=print) -> SessionOutcome:
    """Collect `cfg.pokes` accepted pokes from an iterable of (t, clusters)."""
    detector = PokeDetector(cfg.rules)
    accepted: list[Poke] = []
    rejected: list[Poke] = []
    size = cal.model_size

    def prompt():
        uv, _ = suggest_next(cal.mask, cal.theta, cal.surface_xyz, [p.xyz_mm for p in accepted], cfg.rules)
        say(f"poke {len(accepted) + 1}/{cfg.pokes}: press {describe(uv, size, cal.theta, cal.mask)}, "
            f"firmly ({cfg.rules.min_force_n:.1f}–{cfg.rules.max_force_n:.0f} N), hold ~1 s, release")
        say(ascii_map(size, cal.mask, [p.uv_px for p in accepted], uv))

    def handle(poke: Poke) -> None:
        poke.ref_force_n = reference.for_poke(poke)
        poke.verdict = check_poke(poke, accepted, cfg.rules)
        if poke.verdict:
            rejected.append(poke)
            say(f"  poke rejected: {poke.verdict}")
        else:
            accepted.append(poke)
            say(f"  poke {len(accepted)} accepted: sensor {poke.pred_mag:.2f} N, reference {poke.ref_force_n:.2f} N")

    prompt()
    n = 0
    for t, clusters in frames:
        n += 1
        reference.check()
        poke = detector.feed(t, clusters)
        if poke is None:
            continue
        handle(poke)
        if len(accepted) >= cfg.pokes:
            break
        if len(accepted) + len(rejected) >= cfg.max_attempts:
            say(f"giving up after {cfg.max_attempts} pokes")
            break
        prompt()
    else:
        poke = detector.flush()
        if poke is not None and len(accepted) < cfg.pokes:
            handle(poke)
    return SessionOutcome(accepted, rejected, n, len(accepted) >= cfg.pokes)


def poke_set(pokes: list[Poke], cal: Calibration, uv_px: np.ndarray | None = None,
             theta: np.ndarray | None = None, phi: np.ndarray | None = None) -> PokeSet:
    """Accepted pokes → fit inputs (positions normalized by the model size, θ/φ from the tables)."""
    h, w = cal.model_size
    uv_px = np.array([p.uv_px for p in pokes]) if uv_px is None else uv_px
    theta = cal.theta if theta is None else theta
    phi = cal.phi if phi is None else phi
    tp = np.array([[sample_bilinear(theta, u - 0.5, v - 0.5), sample_bilinear(phi, u - 0.5, v - 0.5)]
                   for u, v in uv_px])
    return PokeSet(np.array([p.pred_force for p in pokes]), np.array([p.ref_force_n for p in pokes]),
                   uv_px / np.array([w, h]), tp)


@dataclass
class Analysis:
    pokes: PokeSet
    fit: CorrectionFit
    decision: Decision
    active: dict                      # error of the active calibration on these pokes
    geometry: GeometryFit | None = None

    def summary(self) -> dict:
        return {"pokes": len(self.pokes), "active": self.active, "loo": self.fit.loo,
                "decision": {"store": self.decision.store, "reason": self.decision.reason},
                "geometry": None if self.geometry is None else
                {"center_px": list(self.geometry.center), "phi0_rad": self.geometry.phi0,
                 "center_shift_px": self.geometry.fit["center_shift_px"], "residual_deg": self.geometry.residual_deg}}


def analyse(pokes: list[Poke], cal: Calibration, cfg: SessionConfig = SessionConfig(), force: bool = False,
            truth_xyz: np.ndarray | None = None) -> Analysis:
    """Fit the correction (and the geometry when true 3D poke positions are given) and decide."""
    if len(pokes) < cfg.fit.min_pokes:
        raise CalibrationError(f"only {len(pokes)} pokes accepted, the fit needs {cfg.fit.min_pokes}; "
                               "nothing was stored")
    geo = None
    ps = poke_set(pokes, cal)
    active = error_stats(active_magnitudes(cal, ps.pred_force, ps.uv, ps.theta_phi), ps.ref_force)
    if truth_xyz is not None:
        xy = model_to_camera(ps.uv * np.array(cal.model_size)[::-1], cal.gel_center_px, cal.gel_radius_px,
                             cal.model_size)
        th, ph = theta_phi_from_xyz(truth_xyz, float((cal.meta.get("gel") or {}).get("center_z_mm", 0.0)))
        geo = refresh_geometry(xy, th, ph, cal.gel_center_px, cal.gel_radius_px, cal.model_size, cfg.geometry)
        uv_new = camera_to_model(xy, geo.center, cal.gel_radius_px, cal.model_size)
        ps = poke_set(pokes, cal, uv_new, geo.theta, geo.phi)
    fit = fit_correction(ps, cfg.fit)
    return Analysis(ps, fit, decide(fit.loo["after"], active, force), active, geo)


def session_truth_xyz(session, pokes: list[Poke]) -> np.ndarray:
    """True 3D contact point (sensor frame, mm) of each poke from a recording: the twin's
    truth/contact.csv, else the mocap `poses` stream (indenter pose = its tip, docs/session.md)."""
    from ...contracts.session import read_table

    contact = session.path / "truth" / "contact.csv"
    if contact.is_file():
        tab = read_table(contact, ["t", "indenter", "depth", "x", "y", "z", "area", "touching"])
        tab = tab[tab[:, 7] > 0]
        cols = slice(3, 6)
    elif session.has("poses"):
        tab = session.table("poses")
        cols = slice(2, 5)
    else:
        raise CalibrationError(f"{session.path}: --geometry needs true poke positions (truth/contact.csv or a "
                               "poses stream); this recording has neither")
    out = []
    for p in pokes:
        sel = tab[(tab[:, 0] >= p.t0) & (tab[:, 0] <= p.t1)]
        if len(sel) == 0:
            raise CalibrationError(f"{session.path}: no true position during the poke at t={p.t0:.2f}–{p.t1:.2f} s")
        ids, counts = np.unique(sel[:, 1], return_counts=True)
        out.append(sel[sel[:, 1] == ids[np.argmax(counts)], cols].mean(axis=0))
    return np.array(out)
