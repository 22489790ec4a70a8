"""Selective-grasp trials (seed §V-B, Table II) in simulation, closed through the sensor runtime.

One trial: build the scene for a pair of objects at the start pinch (with a random placement
jitter), open the hand, let both simulated sensors collect their startup baseline, close the
pinch, tell the controller to watch, pull one object (chosen at random) along its length, run the
controller's decision and path, hold, and judge from the simulator:

    success          the controller named the pulled object, and at the end both fingertips hold it
                     (their rigid cores touch it) and neither touches the other: no core contact and
                     no gel indentation deeper than `TrialConfig.touch_mm` (the gel is the sensor's
                     skin: an object pressed into it is touched, whether or not the core feels it);
    false detection  the controller named the other object;
    other            no decision in time, no path, or the final pinch is wrong.
"""
from __future__ import annotations

import json
import logging
import socket
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ...contracts import wire
from ...contracts.files import atomic_write
from . import graph as graph_mod
from .controller import (
    ControllerConfig,
    ControllerNode,
    SelectiveGraspController,
)
from .hand_model import HandSpec
from .scene import PAIRS, Scene, SceneConfig
from .sensor_mount import SensorMount
from .task import TaskDistribution, draw, fixed
from .touch import GelTouch

log = logging.getLogger(__name__)

PAPER = {  # seed Table II: success, false detection, other, trials
    "A+A": (21, 4, 6, 31), "A+B": (15, 2, 3, 20), "cable+rigid": (17, 1, 2, 20), "rigid+rigid": (18, 0, 2, 20)}
SENSOR_IDS = {"thumb": "hand-thumb", "index": "hand-index"}


@dataclass(frozen=True)
class TrialConfig:
    frame_dt: float = 0.04             # s of simulated time between sensor frames (25 Hz)
    open_mm: float = 8.0
    close_s: float = 0.4
    settle_s: float = 0.24
    settle_until_still: bool = False   # then keep settling (up to settle_max_s) until the measured joint angles of the
    settle_max_s: float = 1.0          # pinch move less than still_rad per frame for 2 frames (the hand's encoders:
    still_rad: float = 0.002           # the fingers have stopped where the objects block them)
    pull_n: float = 0.6
    pull_ramp_s: float = 0.2
    decide_timeout_s: float = 0.8
    hold_s: float = 0.3
    jitter_mm: float = 1.0
    startup_frames: int = 32
    sensor_unit: str = "TWIN-DEMO"     # twin unit rendered, and its calibration in the store
    # the network the fingertips run (a package name or folder): the one the controller's decision weights and
    # re-pinch were chosen with (docs/grasp.md), not the runtime's newest default; `--model` runs another
    model: str = "hiera-qup-128"
    release_after_decision: bool = False
    pull_only: bool = False            # pull for the whole decide window, no path (records the detection's inputs)
    frame_timeout_s: float = 120.0     # wall time a frame's contacts may take over Zenoh (slow machine)
    touch_mm: float = 0.1              # the verdict: a gel indented deeper than this by an object touches it
    randomize: bool = False            # draw each trial's task from `task` (tools.grasp.task) instead of the fixed scene
    task: TaskDistribution = field(default_factory=TaskDistribution)
    start_from_layout: bool = True     # randomized: each trial's start pinch from the graph where the objects lie
                                       # (`graph.start_near`), as a camera would see them: to ± layout_error_mm across
    layout_error_mm: float = 1.0
    arm: bool = False                  # the palm on an arm (SceneConfig.arm): randomized, the arm brings the hand's
                                       # own start pinch to where the objects are seen (to ± layout_error_mm across)
                                       # instead of `start_from_layout`; the controller moves it too (`arm_mm`)
    arm_mm: float = 25.0               # the arm's reach across from home, for the controller's goals
    squeeze_mm: float = 0.0            # the pinch's joint targets close this far past the graph's touching poses (each
                                       # fingertip along its node's pinch normal), at the start and along every path


@dataclass
class TrialResult:
    pair: str
    seed: int
    pulled: int
    judged: int | None
    outcome: str
    touching: list                        # final (2 fingertips × 2 objects): the rigid cores touch
    path_len: int
    seconds: float
    scores: list = field(default_factory=list)
    cause: str = ""                       # sub-cause of a failure (see `verdict`)
    decide_frames: int = 0                # frames scored before the decision (or the timeout)
    score_log: list = field(default_factory=list)   # every scored frame's object scores
    gel_mm: list = field(default_factory=list)      # final (2 fingertips × 2 objects): gel indentation, mm
    task: dict = field(default_factory=dict)        # the trial's draw (tools.grasp.task.TaskDraw), or {} before it
    randomized: bool = False
    diag: dict = field(default_factory=dict)        # diagnosis only (simulator truth, never the controller's input):
                                                    # final gel clearance of each tip from each object (mm), goal terms


def wait_matched(session, key: str, timeout_s: float) -> None:
    """Block until `session` sees a subscriber matching `key` (Zenoh's matching status)."""
    pub = session.declare_publisher(key)
    try:
        deadline = time.monotonic() + timeout_s
        while not pub.matching_status.matching:
            if time.monotonic() > deadline:
                raise RuntimeError(f"zenoh: no subscriber for {key} within {timeout_s:g} s")
            time.sleep(0.005)
    finally:
        pub.undeclare()


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


class Bench:
    """Everything shared by a series of trials: graph, model, calibration, a Zenoh session."""

    def __init__(self, graph_path, urdf, cfg: TrialConfig | None = None, model=None, store=None,
                 ctrl_cfg: ControllerConfig | None = None, scene_cfg: SceneConfig | None = None):
        from ...contracts.store import CalibrationStore
        from ...runtime.apps.publisher import open_session
        from ...runtime.stages.model import find_package
        from ..twin.unit import TwinUnit

        self.cfg = cfg or TrialConfig()
        self.graph = graph_mod.load(graph_path)
        self.urdf = str(urdf)
        self.mount = SensorMount()
        self.start = graph_mod.start_node(self.graph, self.mount)
        self.package = find_package(model or self.cfg.model)
        self.cal = (store or CalibrationStore()).load(self.cfg.sensor_unit)
        self.unit = TwinUnit(self.cfg.sensor_unit)
        self.unit.renderer  # noqa: B018 - build the rest view once
        ep = free_endpoint()
        self.pub_session = open_session(listen=[ep])
        self.sub_session = open_session(connect=[ep])
        self.ctrl_cfg = ctrl_cfg or ControllerConfig()
        self.scene_cfg = scene_cfg or SceneConfig()
        self.joints = list(HandSpec().thumb.joints + HandSpec().index.joints)
        deadline = time.monotonic() + 10.0   # the controller's session must reach the sensors' one
        while not list(self.sub_session.info.peers_zid()) and time.monotonic() < deadline:
            time.sleep(0.05)
        if not list(self.sub_session.info.peers_zid()):
            raise RuntimeError(f"zenoh: the controller session did not connect to {ep} within 10 s")
        # one subscription for all trials (each trial hands it its own controller); no frame is
        # rendered before the sensors' session knows it: every frame then reaches the controller,
        # and a trial does not depend on how fast a declaration travels
        self.node = ControllerNode(SelectiveGraspController(self.graph, self.start, self.mount, self.ctrl_cfg),
                                   self.sub_session, SENSOR_IDS)
        for sid in SENSOR_IDS.values():
            wait_matched(self.pub_session, wire.key(sid, "contacts"), self.cfg.frame_timeout_s)

    def close(self) -> None:
        self.node.close()
        self.sub_session.close()
        self.pub_session.close()

    def trial(self, pair: str, seed: int, frames_out: list | None = None, log_out: list | None = None,
              pulled: int | None = None) -> TrialResult:
        """One trial; `frames_out` collects picture frames, `log_out` every frame's simulated time,
        phase, joint angles and the contacts (position, force, normal) the controller received.
        `pulled` overrides the seed's choice of the pulled object (0 or 1)."""
        from ...runtime.pipeline import open_pipeline
        from .sim_sensor import SimFingertip

        t0 = time.perf_counter()
        cfg, g, s = self.cfg, self.graph, self.start
        n0 = g.normal[s] / np.linalg.norm(g.normal[s])
        across0 = g.tip_index[s][:3, 2] - (g.tip_index[s][:3, 2] @ n0) * n0
        across0 /= np.linalg.norm(across0)
        if cfg.randomize:
            task = draw(cfg.task, PAIRS[pair], seed)
            # the layout's shift: across the pinch and along the objects (before the yaw)
            jitter = (task.shift_mm[0] * across0 + task.shift_mm[1] * np.cross(n0, across0)) / 1000.0
        else:
            task, jitter = fixed(PAIRS[pair], seed, cfg.jitter_mm, cfg.pull_n)
            jitter = jitter / 1000.0
            jitter -= (jitter @ g.normal[s]) * g.normal[s]
        pulled = task.pulled if pulled is None else int(pulled)
        s0 = s
        arm0 = np.zeros(3)
        if cfg.randomize and (cfg.start_from_layout or cfg.arm):
            seen = task.shift_mm[0] + np.random.default_rng((seed, 1)).uniform(-1, 1) * cfg.layout_error_mm
            if cfg.arm:
                arm0 = seen / 1000.0 * across0
            else:
                s = graph_mod.start_near(g, self.mount, s0, seen)
        scene_cfg = replace(self.scene_cfg, friction=task.friction, contact=task.contact) if cfg.randomize else self.scene_cfg
        scene = Scene(self.urdf, self.joints, PAIRS[pair], g.point[s0], g.normal[s0], g.tip_index[s0][:3, 2],
                      replace(scene_cfg, arm=cfg.arm), jitter, diameters_mm=task.diameters_mm, yaw_deg=task.yaw_deg)
        pull_dir = (task.pull_direction(scene.objects[pulled].axis, scene.across, scene.normal)
                    if task.pull_tilt_deg else None)
        if cfg.arm:
            scene.set_arm(arm0)
        q_open = scene.opened(g.q[s], g.normal[s], cfg.open_mm)
        scene.set_hand(q_open)
        ctrl_cfg = replace(self.ctrl_cfg, arm_mm=cfg.arm_mm) if cfg.arm else self.ctrl_cfg
        ctrl = SelectiveGraspController(g, s, self.mount, ctrl_cfg, arm=arm0 if cfg.arm else None)
        self.node.controller = ctrl
        sensors = {name: SimFingertip(sid, self.unit, open_pipeline(self.package, self.cal, sensor_id=self.cfg.sensor_unit),
                                      self.pub_session, seed=seed * 2 + i)
                   for i, (name, sid) in enumerate(SENSOR_IDS.items())}
        gel_touch = GelTouch(scene, self.mount)
        sim_t = 0.0
        judged, outcome, path_len = None, "other", 0
        diag: dict = {}
        phase = "rest"

        def frame(record: str = ""):
            nonlocal sim_t
            felt = {name: gel_touch.contacts(i) for i, name in enumerate(sensors)}
            for name, sen in sensors.items():
                sen.show(felt[name], sim_t)
            # step-locked: exactly this frame's contacts, however long the machine takes; a lost
            # message ends the trial rather than showing the state again (that would change the
            # runtime's frame count and the render noise, so the result would depend on timing)
            if not ctrl.wait_frames({n: sen.pushed for n, sen in sensors.items()}, timeout=cfg.frame_timeout_s):
                why = "; ".join(f"{n}: received {ctrl.received[n]}, sent {sen.publisher.stats.as_dict()}"
                                for n, sen in sensors.items())
                why += "; subscriber errors " + ", ".join(f"{sub.errors} ({sub.last_error})" for sub in self.node.subs)
                raise RuntimeError(f"the sensors' contacts of frame {sensors['thumb'].pushed} did not arrive "
                                   f"over Zenoh within {cfg.frame_timeout_s:g} s ({why})")
            if log_out is not None:
                log_out.append({"t": round(sim_t, 6), "phase": phase, "q": scene.data.qpos[scene.qadr].tolist(),
                                "contacts": {n: [(p.tolist(), f.tolist(), nr.tolist(), a) for p, f, nr, a in ctrl.latest[n]]
                                             for n in sensors},
                                "felt": {n: [(o.index, o.point.tolist(), o.depth, o.shear.tolist()) for o in felt[n]]
                                         for n in sensors}})
            if frames_out is not None and record:
                frames_out.append({"label": record, "t": sim_t, "scene": scene, "felt": felt,
                                   "touching": scene.touching(), "model": scene.snapshot(),
                                   "frames": {n: sen.last_frame for n, sen in sensors.items()},
                                   "contacts": {n: list(ctrl.latest[n]) for n in sensors}})

        def advance(seconds: float, q_from=None, q_to=None, label: str = "", arm_from=None, arm_to=None):
            nonlocal sim_t
            n = max(1, round(seconds / cfg.frame_dt))
            for k in range(n):
                a = (k + 1) / n
                if q_from is not None:
                    scene.command((1 - a) * q_from + a * q_to)
                if arm_from is not None:
                    scene.command_arm((1 - a) * arm_from + a * arm_to)
                scene.step(cfg.frame_dt)
                sim_t += cfg.frame_dt
                frame(label if k == n - 1 else "")

        try:
            # rest frames (the runtime's startup baseline); the controller already hears both sensors
            for _ in range(cfg.startup_frames):
                frame()
            phase = "close"
            q_close = scene.opened(g.q[s], g.normal[s], -cfg.squeeze_mm) if cfg.squeeze_mm else g.q[s]
            advance(cfg.close_s, q_open, q_close, label="pinch")
            gel_touch.relax()
            phase = "settle"
            advance(cfg.settle_s)
            if cfg.settle_until_still:
                q_last, still = scene.data.qpos[scene.qadr].copy(), 0
                for _ in range(max(0, round((cfg.settle_max_s - cfg.settle_s) / cfg.frame_dt))):
                    advance(cfg.frame_dt)
                    q_now = scene.data.qpos[scene.qadr].copy()
                    still = still + 1 if np.abs(q_now - q_last).max() < cfg.still_rad else 0
                    q_last = q_now
                    if still >= 2:
                        break
            ctrl.watch()
            phase = "reference"
            for _ in range(ctrl.cfg.reference_frames):   # the reference, before anything is pulled
                advance(cfg.frame_dt)
                ctrl.update()
            n_pull = max(1, round(cfg.pull_ramp_s / cfg.frame_dt))
            decision = None
            steps = round(cfg.decide_timeout_s / cfg.frame_dt)
            phase = "pull"
            for k in range(steps):
                scene.pull(pulled, task.pull_n * min(1.0, (k + 1) / n_pull), pull_dir)
                scene.step(cfg.frame_dt)
                sim_t += cfg.frame_dt
                frame()
                decision = ctrl.update()
                if cfg.pull_only:
                    decision = None if k < steps - 1 else decision
                    continue
                if decision is not None or k == steps - 1:
                    if frames_out is not None:   # the frame the decision was made on (or the last)
                        frames_out.append({"label": "pull", "t": sim_t, "scene": scene, "touching": scene.touching(),
                                           "model": scene.snapshot(),
                                           "frames": {n: sen.last_frame for n, sen in sensors.items()},
                                           "contacts": {n: list(ctrl.latest[n]) for n in sensors}})
                    break
            if decision is not None:
                own, oth = (_off_axis(decision.moving_point, *scene.object_axis(k)) for k in (pulled, 1 - pulled))
                judged = pulled if own <= oth else 1 - pulled
            if decision is not None and not cfg.pull_only:
                if cfg.release_after_decision:
                    scene.release()
                def follow(q_prev):
                    _, qs = ctrl.trajectory()
                    arms = ctrl.arm_trajectory()
                    if cfg.squeeze_mm and len(qs):
                        path = ctrl.decision.path
                        ids = path + [path[-1]] * (len(qs) - len(path))
                        qs = [scene.opened(g.q[i], g.normal[i], -cfg.squeeze_mm) for i in ids]
                    a_prev = ctrl.arm
                    for k, q in enumerate(qs):
                        if len(arms):
                            advance(ctrl.cfg.step_s, q_prev, q, arm_from=a_prev, arm_to=arms[k])
                            a_prev = arms[k]
                        else:
                            advance(ctrl.cfg.step_s, q_prev, q)
                        q_prev = q
                    ctrl.moved_to_goal()
                    return q_prev, len(qs)

                phase = "path"
                q_prev, path_len = follow(q_close)
                phase = "hold"
                advance(cfg.hold_s, label="" if ctrl.cfg.repinches else "final")
                while ctrl.repinch() is not None:   # a gel still feels the other object: move on from it
                    phase = "path"
                    q_prev, n_path = follow(q_prev)
                    path_len += n_path
                    phase = "hold"
                    advance(cfg.hold_s)
                if frames_out is not None:
                    frame("final")
            touching = scene.touching()
            gel_mm = np.zeros((2, 2))
            for i in range(2):
                for c in gel_touch.contacts(i):
                    gel_mm[i, c.index] = max(gel_mm[i, c.index], c.depth)
            outcome, cause = verdict(judged, pulled, touching, gel_mm, cfg.touch_mm)
            diag = _diagnosis(scene, ctrl, gel_touch, pulled)
        finally:
            for sen in sensors.values():
                sen.close()
        return TrialResult(pair, seed, pulled, judged, outcome, touching.astype(int).tolist(), path_len,
                           round(time.perf_counter() - t0, 2), decision.scores if decision else [], cause,
                           len(ctrl.log), [e["scores"] for e in ctrl.log], np.round(gel_mm, 3).tolist(),
                           {**task.as_dict(), "pulled": pulled, "start": int(s),
                            **({"arm_start_mm": np.round(arm0 * 1000.0, 3).tolist()} if cfg.arm else {})},
                           cfg.randomize, diag)


def _diagnosis(scene: Scene, ctrl: SelectiveGraspController, gel_touch: GelTouch, pulled: int) -> dict:
    """The final state seen from the simulator, for diagnosis on tuning seeds: each fingertip
    centre's distance from each object's axis minus gel radius and object radius (mm; below 0 the
    gel is pressed in), and the controller's own view of its goal (`Decision.terms`)."""
    gap = np.zeros((2, 2))
    for i in range(2):
        tip = scene.tip_pose(i)[:3, 3]
        for k, o in enumerate(scene.objects):
            c, ax = scene.object_axis(k)
            gap[i, k] = _off_axis(tip, c, ax) * 1000.0 - gel_touch.mount.tip_radius_mm - o.radius_m * 1000.0
    d = ctrl.decision
    felt = ctrl.other_felt()
    return {"gel_gap_mm": np.round(gap, 2).tolist(), "terms": d.terms if d is not None else {},
            "other_felt_n": [round(felt[s], 3) for s in ctrl.SENSORS]}


def _off_axis(x: np.ndarray, centre: np.ndarray, axis: np.ndarray) -> float:
    """Distance of point x from the line through centre along the unit axis."""
    d = np.asarray(x, float) - centre
    return float(np.linalg.norm(d - (d @ axis) * axis))


def verdict(judged: int | None, pulled: int, touching: np.ndarray, gel_mm: np.ndarray | None = None,
            touch_mm: float = TrialConfig.touch_mm) -> tuple[str, str]:
    """(outcome, cause) of a trial from the simulator's final state: `touching` (2 tips × 2 objects,
    the rigid cores touch) and `gel_mm` (the same, each object's gel indentation in mm; an
    indentation deeper than `touch_mm` touches too)."""
    if judged is None:
        return "other", "no decision"
    if judged != pulled:
        return "false detection", "other object named"
    touching = np.asarray(touching, bool)
    keeps, other = touching[:, pulled], touching[:, 1 - pulled]
    gel_other = np.zeros(2) if gel_mm is None else np.asarray(gel_mm, float)[:, 1 - pulled]
    if keeps.all() and not other.any() and not (gel_other > touch_mm).any():
        return "success", ""
    if keeps.all() and not other.any():
        return "other", "final pinch's gel touches the other object"
    if keeps.all():
        return "other", "final pinch also touches the other object"
    if other.any():
        return "other", "final pinch lost the pulled object, touches the other"
    return "other", "final pinch lost the pulled object"


FAILURES = ("false detection", "lost object", "touches both", "no decision")
_CLASS = {"other object named": "false detection", "no decision": "no decision",
          "final pinch's gel touches the other object": "touches both",
          "final pinch also touches the other object": "touches both",
          "final pinch lost the pulled object, touches the other": "lost object",
          "final pinch lost the pulled object": "lost object"}
NAMES = {"A+A": "two identical cables (A+A)", "A+B": "different cables (A+B)",
         "cable+rigid": "cable + rigid (A+pen)", "rigid+rigid": "two rigid (pen+pen)"}


def failure_class(r: TrialResult) -> str:
    """One of `FAILURES` for a failed trial (its `cause`), "" for a success."""
    return "" if r.outcome == "success" else _CLASS.get(r.cause, "no decision")


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a rate k/n (95 % at z = 1.96)."""
    if n <= 0:
        return 0.0, 1.0
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return float(max(0.0, mid - half)), float(min(1.0, mid + half))


def _rate(k: int, n: int) -> str:
    lo, hi = wilson(k, n)
    return f"{k}/{n} ({100 * k / max(n, 1):.0f} %, {100 * lo:.0f}–{100 * hi:.0f})"


def table(results: dict[str, list[TrialResult]]) -> str:
    """Markdown table: ours (success with its 95 % Wilson interval, failures by class) beside the
    seed's, per pair."""
    rows = [("| objects | task | success (95 % CI) | false detection | lost object | touches both | no decision | "
            "seed: success (95 % CI) | seed: false det. | seed: other |"),
            "|---|---|---|---|---|---|---|---|---|---|"]
    for pair, res in results.items():
        n = len(res)
        ok = sum(r.outcome == "success" for r in res)
        fails = [sum(failure_class(r) == c for r in res) for c in FAILURES]
        ps, pf, po, pn = PAPER[pair]
        task = "randomized" if res and res[0].randomized else "fixed scene (`--randomize` off)"
        rows.append(f"| {NAMES[pair]} | {task} | {_rate(ok, n)} | " + " | ".join(str(f) for f in fails)
                    + f" | {_rate(ps, pn)} | {pf}/{pn} | {po}/{pn} |")
    return "\n".join(rows) + "\n"


def factor_table(results: dict[str, list[TrialResult]], bins: int = 5) -> str:
    """Markdown table of each drawn factor's extreme bins (its lowest and highest `bins`-quantile
    over all randomized trials of all pairs): the success rate with its 95 % Wilson interval."""
    from .task import factors

    res = [r for rs in results.values() for r in rs if r.randomized and r.task]
    if not res:
        return ""
    vals = [factors(r.task, PAIRS[r.pair]) for r in res]
    ok = np.array([r.outcome == "success" for r in res])
    rows = ["| factor (trials) | lowest bin: range | success (95 % CI) | highest bin: range | success (95 % CI) |",
            "|---|---|---|---|---|"]
    for name in vals[0]:
        have = np.array([i for i, v in enumerate(vals) if v[name] is not None], int)
        if not len(have):
            continue
        x = np.array([vals[i][name] for i in have])
        order = have[np.argsort(x, kind="stable")]
        m = max(1, len(have) // bins)
        cells = []
        for idx in (order[:m], order[-m:]):
            xs = [vals[i][name] for i in idx]
            cells.append(f"{min(xs):.2f}–{max(xs):.2f} | {_rate(int(ok[idx].sum()), len(idx))}")
        rows.append(f"| {name} ({len(have)}) | " + " | ".join(cells) + " |")
    for contact in ("soft", "stiff"):
        idx = [i for i, r in enumerate(res) if r.task.get("contact") == contact]
        if idx:
            rows.append(f"| contact {contact} | all | {_rate(int(ok[idx].sum()), len(idx))} | | |")
    return "\n".join(rows) + "\n"


def save_results(results: dict[str, list[TrialResult]], out: Path) -> None:
    body = {pair: [asdict(r) for r in res] for pair, res in results.items()}
    atomic_write(out / "grasp_trials.json", (json.dumps(body, indent=1) + "\n").encode())
    atomic_write(out / "grasp_table.md", (table(results) + "\n" + factor_table(results)).encode())
