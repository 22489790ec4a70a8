"""`twin record`: simulate a session of one twin unit -- deterministic for a seed, resumable.

Stages: plan (trajectory.py) -> physics per poke (FE by default, cached) -> signals at the rig's
rates (signals.py) with the truth effects (effects.py) -> frames rendered at camera rate (or, camera
"stills", only those around each poke's start and deepest moment) (camera.py) into numbered staged frames (resume skips the ones already on disk) -> streams, truth/ and the
manifest last (tools.sessions.writer). Everything random comes from generators seeded by
(seed, stream), so a resumed recording equals an uninterrupted one.
"""
from __future__ import annotations

import hashlib
import json
import logging
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ...contracts.errors import SessionError
from ...contracts.files import atomic_write_json
from ...contracts.session import write_table
from ..sessions.writer import SessionWriter
from .camera import NoiseConfig
from .effects import FrictionMismatch, apply_stage, build_effects
from .fe_physics import PokeSolveFailed
from .physics import HertzFallbackPhysics, interpolate
from .signals import Hysteresis, RigConfig, ft_reading, mocap_noise, quat_wxyz, slot_track, temperature
from .trajectory import (
    GuidedConfig,
    TrajectoryConfig,
    apply_replans,
    module_indenters,
    plan_guided,
    plan_session,
    segment_phase,
    session_duration,
    shorten,
)
from .unit import TwinUnit
from .world import WORLDS, WorldConfig, ar1_filter, distort_ft, draw_world, quat_wxyz_of, sensor_to_mocap, stamp

log = logging.getLogger(__name__)
PHYSICS = ("fe", "hertz-fallback")
CAMERAS = ("video", "stills")
# camera "stills": the camera-clock frames rendered per poke (s): STILL_BEFORE_S before to STILL_AFTER_S after
# the poke's start (the rest frame before contact), and those where its planned depth is within
# STILL_DEPTH_MM of the deepest, widened by STILL_MARGIN_S (the moment the mocap finds deepest)
STILL_BEFORE_S, STILL_AFTER_S = 0.12, 0.08
STILL_DEPTH_MM, STILL_MARGIN_S = 0.05, 0.07


@dataclass
class RecordConfig:
    serial: str = "TWIN-0001"
    pokes: int = 5
    seed: int = 0
    effects: list = field(default_factory=list)      # [(name, {param: value})]
    physics: str = "fe"
    frame_format: str = "ffv1"
    mjpg_quality: int = 90                             # only for frame_format "mjpg"
    model_size: int = 128
    fe_mesh_top: float = 1.0                           # mm; twin default coarser than the FE's 0.7
    fe_mesh_inside: float = 2.5
    rig: RigConfig = field(default_factory=RigConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    unit: dict | None = None         # explicit unit variation (unit.py UNIT_OVERRIDES keys), else from the serial
    guided: GuidedConfig | None = None  # guided presses at given points instead of a random plan (pokes ignored)
    world: str = "label"             # "label": the labels' own physics and an ideal rig; "rig": tools.twin.world
    world_params: dict | None = None  # WorldConfig fields that differ from its defaults (world "rig")
    camera: str = "video"            # "video": every frame at camera_fps; "stills": only the frames around each
                                     # poke's start and deepest moment (a calibration jig's triggered stills)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["effects"] = [[n, dict(p)] for n, p in self.effects]
        for k in ("unit", "guided", "world_params"):     # absent when unset: keys of earlier recordings stay valid
            if d[k] is None:
                d.pop(k)
        if d["world"] == "label":
            d.pop("world")
        if d["camera"] == "video":
            d.pop("camera")
        return json.loads(json.dumps(d))

    def key(self) -> str:
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:16]


def make_physics(cfg: RecordConfig, unit: TwinUnit, progress=None):
    """The recording's physics: in world "label" the labels' FE (nominal Yeoh; the unit's force factor is
    applied by the recorder); in world "rig" the unit's own gel and Yeoh constants on the world's mesh."""
    w = unit.world
    if cfg.physics == "hertz-fallback":
        if w is not None:
            return HertzFallbackPhysics(unit.gel, shear_modulus=2.0 * w.yeoh[0])
        return HertzFallbackPhysics(unit.gel)
    if cfg.physics == "fe":
        from ..fe import GelGeometry, MeshSettings, SolverSettings
        from .fe_physics import FEPhysics

        g = unit.gel
        gel = GelGeometry(kind="flattened_dome", radius=g.radius, cap_height=g.cap_height, skirt=g.skirt)
        if w is not None:
            c = w.config
            return FEPhysics(gel=gel, material=w.material(), progress=progress,
                             mesh=MeshSettings(size_top=c.fe_mesh_top, size_inside=c.fe_mesh_inside, order=c.fe_order),
                             solver=SolverSettings(max_bulk_ratio=c.fe_max_bulk_ratio))
        return FEPhysics(gel=gel, mesh=MeshSettings(size_top=cfg.fe_mesh_top, size_inside=cfg.fe_mesh_inside),
                         progress=progress)
    raise SessionError(f"physics {cfg.physics!r}: expected one of {PHYSICS}")


def _rng(cfg: RecordConfig, stream: int, *more: int) -> np.random.Generator:
    return np.random.default_rng([cfg.seed, stream, *more])


def _interleave(t: np.ndarray, per_slot: list[np.ndarray]) -> np.ndarray:
    """Rows (t, indenter, values...) sorted by time then indenter."""
    rows = [np.column_stack([t, np.full(len(t), k), v]) for k, v in enumerate(per_slot)]
    return np.concatenate(rows)[np.lexsort((np.concatenate([np.full(len(t), k) for k in range(len(per_slot))]),
                                            np.concatenate([t] * len(per_slot))))]


def _restamp(rows: np.ndarray, offset_s: float) -> np.ndarray:
    """Rows (t, ...) stamped by a clock `offset_s` ahead of the camera's (world.stamp); rows stamped
    before 0 are dropped."""
    rows = rows.copy()
    rows[:, 0] = stamp(rows[:, 0], offset_s)
    return rows[rows[:, 0] >= 0.0]


class Recorder:
    """One recording job. `run()` returns the session path."""

    def __init__(self, cfg: RecordConfig, out, physics=None, progress=None):
        self.cfg, self.out = cfg, Path(out)
        self.progress = progress or (lambda stage, i, n: None)
        if cfg.world not in WORLDS:
            raise SessionError(f"world {cfg.world!r}: expected one of {WORLDS}")
        if cfg.camera not in CAMERAS:
            raise SessionError(f"camera {cfg.camera!r}: expected one of {CAMERAS}")
        if cfg.world_params and cfg.world == "label":
            raise SessionError("world_params: only world 'rig' takes world parameters")
        self.world = (draw_world(cfg.serial, WorldConfig.with_overrides(cfg.world_params, "world_params"))
                      if cfg.world == "rig" else None)
        self.unit = TwinUnit(cfg.serial, noise=cfg.noise, override=cfg.unit, world=self.world)
        self.gel = self.unit.gel
        if cfg.guided is not None:
            g = cfg.guided if isinstance(cfg.guided, GuidedConfig) else GuidedConfig(**cfg.guided)
            self.plan = plan_guided(g, self.gel, cfg.trajectory)
            self.modules = [g.indenter]
        else:
            self.plan = plan_session(cfg.pokes, cfg.seed, self.gel, cfg.trajectory)
            self.modules = module_indenters(cfg.seed, cfg.trajectory)
        self.planned = list(self.plan)
        self.events: list[dict] = []     # physics replans (shortened / skipped pokes)
        truth = self.out / "truth" / "truth.json"
        if (self.out / "session.json").is_file() and truth.is_file():   # a finished recording: its final plan
            self.events = json.loads(truth.read_text()).get("physics_events", [])
            self.plan = apply_replans(self.planned, self.events, cfg.trajectory)
        self.physics = physics
        self.effects = build_effects(cfg.effects)
        self.timing: dict = {}

    # -- resume bookkeeping -----------------------------------------------------------------
    def _claim(self) -> bool:
        """Check/create .partial/record.json; True when resuming an earlier run."""
        state = self.out / ".partial" / "record.json"
        if (self.out / "session.json").is_file():
            raise SessionError(f"{self.out}: already holds a finished session; choose another --out")
        if state.is_file():
            old = json.loads(state.read_text())
            if old.get("key") != self.cfg.key():
                raise SessionError(f"{self.out}: holds a partial recording with other settings "
                                   f"(key {old.get('key')} != {self.cfg.key()}); use another --out or delete it")
            return True
        state.parent.mkdir(parents=True, exist_ok=True)
        state.write_text(json.dumps({"key": self.cfg.key(), "config": self.cfg.to_dict()}, indent=2))
        return False

    def run(self) -> Path:
        cfg, rig = self.cfg, self.cfg.rig
        resumed = self._claim()
        t_start = time.perf_counter()
        physics = self.physics or make_physics(cfg, self.unit)
        solves = self._solve_all(physics)
        self.timing["physics_s"] = time.perf_counter() - t_start
        writer = SessionWriter(self.out, cfg.serial, cfg.frame_format)
        dur = session_duration(self.plan, cfg.trajectory)
        K = len(self.modules)
        t_pose = np.arange(0.0, dur, 1.0 / rig.pose_rate)
        t_wr = np.arange(0.0, dur, 1.0 / rig.wrench_rate)
        t_cam = np.arange(0.0, dur, 1.0 / rig.camera_fps)
        t_tmp = np.arange(0.0, dur, 1.0 / rig.temperature_rate)
        temp = temperature(t_tmp, rig, _rng(cfg, 1))
        # poses -------------------------------------------------------------------------------
        w = self.world
        phi = w.noise_ar1 if w is not None else 0.0
        true_pose, meas_pose = [], []
        for k in range(K):
            pos, rv = slot_track(self.plan, k, t_pose, rig)
            npos, nrv = mocap_noise(pos, rv, rig, _rng(cfg, 2, k), phi)
            if w is not None:                 # the rig's mocap reports its own frame
                npos, nrv = sensor_to_mocap(npos, nrv, *w.extrinsic_true())
            true_pose.append(np.column_stack([pos, quat_wxyz(rv)]))
            meas_pose.append(np.column_stack([npos, quat_wxyz(nrv)]))
        # wrench ------------------------------------------------------------------------------
        truth_rows, fe_rows, contact_rows, ft_rows, shear = [], [], [], [], []
        scale = self.unit.params.stiffness_scale if w is None else 1.0   # rig: the unit's Yeoh is in the physics
        for k in range(K):
            rf, rm = np.zeros((len(t_wr), 3)), np.zeros((len(t_wr), 3))
            depth, area = np.zeros(len(t_wr)), np.zeros(len(t_wr))
            cpt = np.full((len(t_wr), 3), np.nan)
            for poke, sol in zip(self.plan, solves):
                if k not in poke.slots:
                    continue
                j = poke.slots.index(k)
                sel = (t_wr >= poke.times[0]) & (t_wr <= poke.times[-1])
                if not sel.any():
                    continue
                rf[sel] = interpolate(sol, poke, t_wr[sel], "RF")[:, j]
                rm[sel] = interpolate(sol, poke, t_wr[sel], "RM")[:, j]
                depth[sel] = interpolate(sol, poke, t_wr[sel], "depth")[:, j]
                area[sel] = interpolate(sol, poke, t_wr[sel], "CAREA")[:, j]
                c = sol.contact[:, j]
                if np.isfinite(c).any():
                    c = np.where(np.isnan(c), np.nanmean(c, axis=0), c)
                idx = np.rint(np.interp(t_wr[sel], poke.times, np.arange(len(c)))).astype(int)
                cpt[sel] = c[idx]
            touching = depth > 0
            cpt[~touching] = np.nan
            fe_rows.append(np.column_stack([rf, rm]))
            x = scale * np.column_stack([rf, rm])
            safe = np.where(np.isnan(cpt), [0.0, 0.0, self.gel.top_z], cpt)
            normal = self.gel.normals(safe)
            fvec = -x[:, :3]
            fn = np.abs(np.sum(fvec * normal, 1))
            cov = {"time": t_wr, "temperature": np.interp(t_wr, t_tmp, temp), "depth": depth,
                   "max_depth": np.maximum.accumulate(depth), "normal": normal, "force_n": fn,
                   "force_t": np.linalg.norm(fvec - (np.sum(fvec * normal, 1))[:, None] * normal, axis=1),
                   "rim_distance": np.where(touching, self.gel.rim_distance(safe), 1e3),
                   "gel_height": np.full(len(t_wr), self.gel.top_z)}
            ratio = np.ones(len(t_wr))
            for e in self.effects:
                if isinstance(e, FrictionMismatch):
                    ratio = e.shear_ratio(x, cov)
            shear.append(ratio)
            x = apply_stage(self.effects, "force", x, cov)
            truth_rows.append(x)
            contact_rows.append(np.column_stack([depth, np.nan_to_num(cpt, nan=0.0), area, touching]))
            pos, rv = slot_track(self.plan, k, t_wr, rig)
            ft = ft_reading(x[:, :3], x[:, 3:], pos, rv, rig)
            ft = apply_stage(self.effects, "measurement", ft, {"time": t_wr})
            if w is not None:
                ft = distort_ft(ft, w.ft_crosstalk[k], w.ft_bias[k])
            white = _rng(cfg, 3, k).normal(0.0, 1.0, ft.shape)
            noise = (ar1_filter(white, phi) if phi else white) * np.array([rig.ft_noise_n] * 3 + [rig.ft_noise_nmm] * 3)
            ft_rows.append(ft + noise)
        pose_info = {"frame": "sensor"}
        pose_rows, wrench_rows = _interleave(t_pose, meas_pose), _interleave(t_wr, ft_rows)
        if w is not None:                     # mocap frame + its calibrated extrinsic; each stream on its own clock
            R, t = w.extrinsic_calibrated()
            pose_info = {"frame": "mocap", "mocap_to_sensor": {
                "rotation_wxyz": quat_wxyz_of(R), "translation_mm": [float(v) for v in t],
                "meaning": "p_sensor = R p_mocap + t, as calibrated (tools.twin.world: with an error)"}}
            pose_rows, wrench_rows = (_restamp(r, w.clock_offset_s[n]) for r, n in
                                      ((pose_rows, "poses"), (wrench_rows, "wrench")))
        writer.table("poses", pose_rows, rate_hz=rig.pose_rate, **pose_info,
                     indenters={str(k): n for k, n in enumerate(self.modules)},
                     pose="indenter tip position (mm) and orientation (local -> sensor), docs/fe.md frame",
                     noise={"position_mm": rig.pose_noise_mm, "rotation_rad": rig.pose_noise_rad})
        writer.table("wrench", wrench_rows, rate_hz=rig.wrench_rate, frame="ft",
                     ft_to_indenter=rig.ft_to_indenter_dict(),
                     sign="load of the gel on the indenter (= -RF of docs/fe.md), moment about the F/T origin",
                     noise={"force_n": rig.ft_noise_n, "torque_nmm": rig.ft_noise_nmm})
        writer.table("temperature", np.column_stack([t_tmp, temp]), rate_hz=rig.temperature_rate)
        self._truth(t_pose, true_pose, t_wr, truth_rows, fe_rows, contact_rows, solves)
        # frames ------------------------------------------------------------------------------
        t0 = time.perf_counter()
        keep = self._still_frames(t_cam, solves) if cfg.camera == "stills" else np.ones(len(t_cam), bool)
        rendered = self._frames(writer, t_cam, t_wr, shear, t_tmp, temp, solves, keep)
        self.timing["render_s"] = time.perf_counter() - t0
        self.timing["frames_rendered"] = rendered
        extra = {} if cfg.camera == "video" else {
            "camera": "stills: frames around each poke's start and deepest moment only (t in frames.csv)"}
        writer.finish_frames(t_cam[keep], rig.camera_fps, quality=cfg.mjpg_quality, **extra)
        self.timing["total_s"] = time.perf_counter() - t_start
        prov = {"source": "twin", "unit": cfg.serial, "seed": cfg.seed, "pokes": len(self.plan),
                "planned_pokes": len(self.planned),
                "replanned": [{k: e[k] for k in ("poke", "action")} for e in self.events],
                "generator": "tensortouch twin record", "resumed": resumed, **({"world": cfg.world} if w else {}),
                "command": " ".join(sys.argv) if sys.argv and "tensortouch" in sys.argv[0] else ""}
        writer.finish(prov, {"source": "simulated", "t0": 0.0, "unit": "s"},
                      truth={"dir": "truth", "note": "twin ground truth: no deploy or workbench stage reads it"})
        (self.out / ".partial" / "record.json").unlink(missing_ok=True)
        try:
            (self.out / ".partial").rmdir()
        except OSError:
            pass
        log.info("session %s: %.1f s recorded, %s", self.out, dur, self.timing)
        return self.out

    def _solve_all(self, physics) -> list:
        """Solve every planned poke; a poke the physics cannot solve is shortened to the last keypoint
        reached (then released), else skipped — recorded in self.events, never fatal."""
        plan, solves, self.events = [], [], []
        n = len(self.planned)
        for i, poke in enumerate(self.planned):
            self.progress("physics", i, n)
            try:
                solves.append(physics.solve(poke))
                plan.append(poke)
                continue
            except PokeSolveFailed as exc:
                first, last = str(exc), exc.last_keypoint
            short = shorten(poke, last, self.cfg.trajectory)
            if short is not None:
                try:
                    solves.append(physics.solve(short))
                    plan.append(short)
                    self.events.append({"poke": i, "action": "shortened", "last_keypoint": last,
                                        "planned_keypoints": int(poke.translation.shape[1]), "reason": first})
                    log.warning("%s: poke %d (%s) shortened to keypoint %d of %d: %s", self.out, i, poke.kind,
                                last, poke.translation.shape[1] - 1, first)
                    continue
                except PokeSolveFailed as exc2:
                    first = f"{first}; shortened to keypoint {last}: {exc2}"
            self.events.append({"poke": i, "action": "skipped", "reason": first})
            log.warning("%s: poke %d (%s with %s) skipped, the physics could not solve it: %s", self.out, i,
                        poke.kind, poke.indenters, first)
        self.progress("physics", n, n)
        self.plan = plan
        return solves

    def _truth(self, t_pose, true_pose, t_wr, truth_rows, fe_rows, contact_rows, solves) -> None:
        d = self.out / "truth"
        d.mkdir(exist_ok=True)
        write_table(d / "poses.csv", ["t", "indenter", "x", "y", "z", "qw", "qx", "qy", "qz"], _interleave(t_pose, true_pose))
        cols = ["t", "indenter", "fx", "fy", "fz", "mx", "my", "mz"]
        write_table(d / "reaction.csv", cols, _interleave(t_wr, truth_rows))
        write_table(d / "reaction_fe.csv", cols, _interleave(t_wr, fe_rows))
        write_table(d / "contact.csv", ["t", "indenter", "depth", "x", "y", "z", "area", "touching"],
                    _interleave(t_wr, contact_rows))
        info = {"schema": "tensortouch.twin_truth", "schema_version": 1, "config": self.cfg.to_dict(),
                "unit": self.unit.describe(), "effects": [e.to_dict() for e in self.effects],
                "modules": self.modules, "physics": solves[0].backend if solves else "",
                "fe_scenarios": [s.key for s in solves], "plan": [p.to_dict() for p in self.plan],
                "physics_events": self.events,
                "reaction": "true force the indenter applies to the gel (FE RF convention), sensor frame, "
                            "moment about the tip; reaction_fe.csv = nominal material, no effects",
                "hysteresis": {"fraction": self.cfg.rig.hysteresis_fraction, "tau_s": self.cfg.rig.hysteresis_tau_s},
                "calibration": {"store_sensor_id": self.cfg.serial, "method": "twin-truth"}}
        if self.world is not None:
            info["world"] = {"name": self.cfg.world, **self.world.to_dict(),
                             "note": "truth/ is on the camera clock, in the sensor frame, without F/T bias or noise"}
        atomic_write_json(d / "truth.json", info, indent=2)

    def _still_frames(self, t_cam: np.ndarray, solves) -> np.ndarray:
        """Camera-clock frames a "stills" recording keeps (bool per frame of t_cam): per poke, the rest
        frames just before its start and the frames around its deepest planned moment."""
        keep = np.zeros(len(t_cam), bool)
        for poke, sol in zip(self.plan, solves):
            keep |= (t_cam >= poke.t_start - STILL_BEFORE_S) & (t_cam <= poke.t_start + STILL_AFTER_S)
            t = t_cam[(t_cam >= poke.t_start) & (t_cam <= poke.t_end)]
            if not len(t):
                continue
            depth = interpolate(sol, poke, t, "depth").max(axis=1)
            deep = t[depth >= depth.max() - STILL_DEPTH_MM]
            keep |= (t_cam >= deep.min() - STILL_MARGIN_S) & (t_cam <= deep.max() + STILL_MARGIN_S)
        if len(keep) and not keep.any():   # no poke left: one rest still, so the session has an image stream
            keep[0] = True
        return keep

    def _frames(self, writer, t_cam, t_wr, shear, t_tmp, temp, solves, keep) -> int:
        """Render the frames of t_cam where `keep` (the camera state, hysteresis, runs through all of
        them; frame i's noise is seeded by i, so a still equals the video's frame at that time); kept
        frames are numbered 0, 1, ... in the image stream."""
        cfg, rig = self.cfg, self.cfg.rig
        r = self.unit.renderer
        mask = r.view.mask
        targets = r.view.points[mask]
        W_cache: dict = {}
        hyst = None
        gains = apply_stage(self.effects, "image", np.ones(len(t_cam)),
                            {"time": t_cam, "temperature": np.interp(t_cam, t_tmp, temp)})
        n_nodes = solves[0].nodes.shape[0] if solves else 0
        rendered = 0
        keys = np.full((len(t_cam), 4), -1.0)  # t, index, poke, keypoint parameter sigma = j + s
        index = np.cumsum(keep) - 1
        for i, t in enumerate(t_cam):
            keys[i, :2] = t, index[i]
            u = np.zeros((n_nodes, 3))
            nodes = solves[0].nodes if solves else np.zeros((0, 3))
            for pi, (poke, sol) in enumerate(zip(self.plan, solves)):
                if poke.times[0] <= t <= poke.times[-1]:
                    if keys[i, 2] < 0:
                        j, ph = segment_phase(poke.times, np.array([t]))
                        keys[i, 2:] = pi, float(j[0] + ph[0])
                    du = interpolate(sol, poke, np.array([t]), "U")[0]
                    ratio = min(float(np.interp(t, t_wr, shear[s])) for s in poke.slots)
                    if ratio < 1.0:
                        n0 = self.gel.normals(sol.nodes)
                        un = np.sum(du * n0, 1, keepdims=True) * n0
                        du = un + ratio * (du - un)
                    u, nodes = u + du, sol.nodes
            if hyst is None:
                hyst = Hysteresis(rig.hysteresis_fraction, rig.hysteresis_tau_s, u.shape)
            u_vis = hyst.step(float(t), u)
            if not keep[i] or writer.has_frame(int(index[i])):
                continue
            if n_nodes and np.any(u_vis):
                key = nodes.shape[0], float(nodes[:7].sum())
                if key not in W_cache:
                    W_cache[key] = self.gel.interpolator(nodes, targets)
                u_pix = np.zeros(r.view.points.shape)
                u_pix[mask] = W_cache[key] @ u_vis
            else:
                u_pix = None
            img = r.render(u_pix, float(gains[i]), _rng(cfg, 4, i))
            writer.frame(int(index[i]), img)
            rendered += 1
            self.progress("frames", i + 1, len(t_cam))
        write_table(self.out / "truth" / "frames.csv", ["t", "index", "poke", "sigma"], keys[keep])
        return rendered


def record(cfg: RecordConfig, out, physics=None, progress=None) -> Path:
    return Recorder(cfg, out, physics, progress).run()
