"""The selective-grasp controller (seed §V-B): which of two pinched objects is being pulled, and
the contact-graph path to a pinch on that object alone.

Inputs, and the only ones: the contact messages the two fingertip sensors publish (decoded
`contracts.wire.ContactsFrame`s, delivered by a `runtime.apps.subscriber.Subscriber`) and the contact
graph (joint angles, fingertip poses and contact points of known pinches). It never sees the
simulator; `ControllerNode` wires it to Zenoh like any other subscriber.

1. Reference: when told to watch, the mean force of each contact cluster over a few frames.
2. Detection (`attribute="lever"`, the default): from the reference, the two objects (clusters
   placed on the hand through the current graph node's fingertip poses and the sensor mount,
   grouped ≤ `group_mm`; the two most loaded) and where each lies on each gel. Each frame every
   cluster of a gel is split between the two objects by where its centroid lies on the line
   joining them (`split_forces`: the force-weighted centroid of two loads lies between them in
   proportion to the loads, so one cluster covering both objects is shared as they load it, and a
   cluster that splits apart later is shared the same way). Per object and gel: the change of its
   share along the objects' length per load^`load_power` of its reference share, plus
   `lever_drift_weight` per mm its share's force centroid slid along them; the object's score is
   the geometric mean over both gels. `attribute="cluster"` is the rule by reference cluster
   identity (each reference cluster matched to the nearest current one ≤ `match_mm`). The object
   whose score exceeds `min_change` and leads the other by `lead_ratio` for `confirm_frames`
   frames moved.
3. Plan (`goal_scores`): for every reachable graph node with a pinch normal within
   `max_normal_deg` of the current one: where its line of fingertip centres crosses the objects'
   plane relative to the moving object (e), how far its fingertips lean off that line across the
   objects, its pinch point's distance from the plane (h), and the other object's distance across
   from the nearer fingertip. The graph's fingertip poses are those of touching fingertips; a pinch
   closing on an object of any thickness closes along the same line, so e = 0 keeps the object
   centred between the fingertips whatever its diameter. The goal keeps e within `keep_mm`, the
   lean within `lean_mm`, h within `depth_mm` and the other object `clear_mm` from both
   fingertips where the graph allows, as near as it can otherwise, then prefers a short joint
   path. An object held firmly on both gels (≥ `aim_min_load_n`: a thick, stiff one) is aimed
   `aim_mm` beyond, away from the other. Dijkstra gives the path.
   With an arm (`arm_mm` > 0) each node's goal also carries the arm's translation of the palm
   across the objects that puts its line of fingertip centres at the aimed place (the moving
   object, or `aim_mm` beyond it) or up to `arm_beyond_mm` farther from the other object,
   whichever scores best (more room from the other object against an off-centre pinch), within
   ±`arm_mm` of the arm's home; the arm's travel costs `arm_weight` per mm.
   Where the arm is comes from its own commands (`arm`), never from the simulator.
4. Re-pinch (`repinch`): after the hold, while a gel still reports at least `touch_n` on the other
   object's side (`other_felt`, seen from the goal's fingertip poses), a new goal from there with
   `repinch_clear_mm` more clearance, at most `repinches` times.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field, replace

import numpy as np

from .graph import ContactGraph, centre_line
from .sensor_mount import SensorMount

# an object's change from its per-gel changes
WITNESS = {"both": lambda v: float(np.prod(v)) ** (1.0 / len(v)), "max": max, "min": min, "sum": sum}


@dataclass(frozen=True)
class ControllerConfig:
    reference_frames: int = 4
    shear_only: bool = True                 # score the change of the force along the gel surface
    per_load: bool = True                   # an object's change per newton of its reference |F|
    min_ref_n: float = 0.3                  # clusters weaker than this in the reference are ignored
    load_floor_n: float = 0.0               # added to an object's load before dividing (per_load)
    load_power: float = 0.75                # per_load divides by (load + floor) to this power
    lost_is_change: bool = True             # a reference cluster with no match counts as released
    both_sensors: bool = True               # only objects felt by both fingertips compete (if ≥ 2)
    along_only: bool = True                 # score only the change along the objects' length
    witness: str = "both"                   # an object's change over the sensors: "both" (geometric mean), "max", "min", "sum"
    drift_weight: float = 0.15              # added per mm its cluster's centroid moved along the object (per gel)
    most_loaded: int = 2                    # > 0: only this many objects felt by both gels compete, the most loaded
    drop_between: bool = True               # without two objects felt by both: one between two others is their merged contact
    attribute: str = "lever"                # "lever": each gel's clusters' force split between the two reference objects by
                                            # where each cluster lies between them (`split_forces`); "cluster": per reference
                                            # cluster identity (the rule before, with drift_weight)
    lever_drift_weight: float = 0.1         # lever: added per mm an object's force centroid moved along it (per gel)
    match_mm: float = 3.0
    group_mm: float = 4.0
    min_change: float = 0.05                # N per N^load_power of load (per_load), else N
    lead_ratio: float = 1.1
    confirm_frames: int = 2
    keep_mm: float = 2.5                    # the goal's line of fingertip centres this near the moving object
    aim_mm: float = 1.5                     # a thick object's goal line crosses this far beyond it, away from the other
    aim_min_load_n: float = 2.5             # thick: held with at least this on both gels in the reference
    aim_beside_load_n: float = 3.6          # a thinner moving object is aimed too when the other is held with at least
                                            # this on both gels (a pen beside a cable); inf: off
    lean_mm: float = 1.5                    # its fingertip centres this near where that line crosses, across
    depth_mm: float = 1.5                   # the goal's pinch point this near it along the normal
    clear_mm: float = 17.0                  # wanted distance of the other object's axis from both fingertip centres
                                            # (gel radius 12 mm + a pen's 4 mm, + 1 mm: the fingertips end up to
                                            # 0.6 mm nearer than the graph's poses; its gel does not touch the other)
    repinches: int = 2                      # after the hold: while a gel still feels the other object, plan again with
    repinch_clear_mm: float = 1.5           # this much more clearance, from where the hand is, at most this many times
    touch_n: float = 0.15                   # the other object is felt: a cluster nearer its place on the gel than the
                                            # held object's, at least this strong
    keep_weight: float = 30.0               # score per mm beyond keep_mm or depth_mm
    clear_weight: float = 30.0              # score per mm short of clear_mm
    max_normal_deg: float = 15.0
    cost_weight_mm_per_rad: float = 2.0     # path length penalty when choosing the goal
    step_s: float = 0.04                    # time per path node when executing
    arm_mm: float = 0.0                     # > 0: the palm rides an arm that can move it this far across from home (m·1e-3)
    arm_weight: float = 0.5                 # goal score per mm the arm travels
    arm_step_mm: float = 1.0                # the arm moves at most this far per step_s
    arm_grid_mm: float = 0.25               # the arm's places tried per node: the aim, and beyond it (away from the
    arm_beyond_mm: float = 1.5              # other object) up to this far, on this grid

    def __post_init__(self):
        for name, allowed in (("attribute", ("lever", "cluster")), ("witness", tuple(WITNESS))):
            if getattr(self, name) not in allowed:
                raise ValueError(f"ControllerConfig.{name} = {getattr(self, name)!r}; expected one of {', '.join(allowed)}")


@dataclass
class Decision:
    moving_point: np.ndarray                # world (m): where the moving object is pinched
    other_point: np.ndarray | None
    goal: int
    path: list[int]
    scores: list[float] = field(default_factory=list)
    terms: dict = field(default_factory=dict)   # the goal's e, lean, h, rho_other (mm), clearance wanted, aim
    arm: np.ndarray | None = None           # the arm's translation at the goal (m), None without an arm
    arm_from: np.ndarray | None = None      # and where it starts the path from


class SelectiveGraspController:
    SENSORS = ("thumb", "index")

    def __init__(self, graph: ContactGraph, start: int, mount: SensorMount | None = None,
                 cfg: ControllerConfig | None = None, arm: np.ndarray | None = None):
        """`arm`: the arm's translation of the palm from its home (world, m) at the start; the graph's
        poses are the hand's with the arm at home."""
        self.graph, self.node, self.start = graph, int(start), int(start)
        self.arm = np.zeros(3) if arm is None else np.asarray(arm, float).copy()
        self.mount = mount or SensorMount()
        self.cfg = cfg or ControllerConfig()
        self._lock = threading.Condition()
        self.latest: dict[str, list] = {s: [] for s in self.SENSORS}
        self.received = {s: 0 for s in self.SENSORS}    # newest frame seq per sensor
        self._ref: dict[str, list] | None = None
        self._ref_acc: dict[str, list] = {s: [] for s in self.SENSORS}
        self._watching = False
        self._streak = (None, 0)
        self._pair: dict | None = None
        self.decision: Decision | None = None
        self.log: list[dict] = []

    # ------------------------------------------------------------------ inputs
    def on_contacts(self, sensor: str, frame) -> None:
        """A decoded ContactsFrame from `sensor` ("thumb" or "index")."""
        with self._lock:
            self.latest[sensor] = [(np.array(c.position_mm), np.array(c.force_n), np.array(c.normal),
                                    float(c.area_mm2)) for c in frame.contacts]
            self.received[sensor] = max(self.received[sensor], int(frame.seq))
            self._lock.notify_all()

    def wait_frames(self, counts: dict[str, int], timeout: float = 10.0) -> bool:
        """Block until each sensor's contacts of frame `counts[s]` (its seq) arrived (lock-step
        simulation; a message lost on the way is superseded by a newer one)."""
        with self._lock:
            return self._lock.wait_for(lambda: all(self.received[s] >= n for s, n in counts.items()), timeout)

    def watch(self) -> None:
        with self._lock:
            self._watching = True
            self._ref, self._ref_acc = None, {s: [] for s in self.SENSORS}

    # ------------------------------------------------------------------ per frame
    def update(self) -> Decision | None:
        """Call once per frame pair; returns the decision (the pulled object, goal and path) once made."""
        if self.decision is not None or not self._watching:
            return self.decision
        named = self.detect()
        if named is not None:
            self.decision = self._plan(*named)
        return self.decision

    def detect(self) -> tuple | None:
        """One frame of the decision rule, without planning: (moving point, other point or None,
        scores, the moving object's weaker gel's reference force N, the other object's N (0 without
        one)) once an object is confirmed as pulled, else None. Call once per frame pair after `watch`."""
        with self._lock:
            latest = {s: list(v) for s, v in self.latest.items()}
        if self._ref is None:
            for s in self.SENSORS:
                self._ref_acc[s].append(latest[s])
            if len(self._ref_acc["thumb"]) >= self.cfg.reference_frames:
                self._ref = {s: self._reference(self._ref_acc[s]) for s in self.SENSORS}
                self._pair = self._reference_pair() if self.cfg.attribute == "lever" else None
            return None
        objects = self._lever(latest) if self.cfg.attribute == "lever" else None
        if objects is None:
            objects = self._objects(latest)
        if len(objects) == 0:
            return None
        scores = [o["change"] for o in objects]
        order = np.argsort(scores)[::-1]
        best = int(order[0])
        second = scores[order[1]] if len(order) > 1 else 0.0
        ok = scores[best] >= self.cfg.min_change and scores[best] >= self.cfg.lead_ratio * second
        key = tuple(np.round(objects[best]["point"] * 1000 / self.cfg.group_mm).astype(int)) if ok else None
        streak = self._streak[1] + 1 if ok and key == self._streak[0] else (1 if ok else 0)
        self._streak = (key, streak)
        self.log.append({"scores": [float(x) for x in scores], "n_objects": len(objects)})
        if streak < self.cfg.confirm_frames:
            return None
        other = objects[int(order[1])]["point"] if len(order) > 1 else None
        held = min(objects[best]["load_by"].get(s, 0.0) for s in self.SENSORS)
        held_other = min(objects[int(order[1])]["load_by"].get(s, 0.0) for s in self.SENSORS) if len(order) > 1 else 0.0
        return objects[best]["point"], other, [float(x) for x in scores], held, held_other

    def _reference(self, frames: list[list]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Clusters of the last reference frame with their force averaged over the frames."""
        last = frames[-1]
        out = []
        for p, _, nrm, area in last:
            fs = []
            for fr in frames:
                if fr:
                    d = [np.linalg.norm(q - p) for q, *_ in fr]
                    k = int(np.argmin(d))
                    if d[k] <= self.cfg.match_mm:
                        fs.append(fr[k][1])
            out.append((p, np.mean(fs, axis=0), nrm, area))
        return out

    def _world(self, sensor: str, p_mm: np.ndarray) -> np.ndarray:
        T = self.graph.tip_thumb[self.node] if sensor == "thumb" else self.graph.tip_index[self.node]
        u = self.mount.gel_to_direction(p_mm)
        return T[:3, 3] + self.arm + T[:3, :3] @ u * (self.mount.tip_radius_mm / 1000.0)

    def _along(self, s: str, p_ref: np.ndarray, nrm: np.ndarray) -> np.ndarray | None:
        """Unit direction along the object pinched at reference cluster p_ref on sensor s: the
        gel normal × the direction to the nearest reference cluster of another object on the same
        gel (the objects lie side by side). None with no other object on that gel."""
        others = [q for q, f, *_ in self._ref[s] if np.linalg.norm(f) >= self.cfg.min_ref_n
                  and np.linalg.norm(q - p_ref) > self.cfg.group_mm]
        if not others:
            return None
        q = min(others, key=lambda x: np.linalg.norm(x - p_ref))
        e = np.cross(nrm, q - p_ref)
        n = np.linalg.norm(e)
        return e / n if n > 1e-9 else None

    def _objects(self, latest: dict[str, list]) -> list[dict]:
        pts, changes, loads, who, drifts = [], [], [], [], []
        for s in self.SENSORS:
            for p_ref, f_ref, nrm, _ in self._ref[s]:
                if np.linalg.norm(f_ref) < self.cfg.min_ref_n:
                    continue
                cur = latest[s]
                d = [np.linalg.norm(q - p_ref) for q, *_ in cur]
                if d and min(d) <= self.cfg.match_mm:
                    p_now, f = cur[int(np.argmin(d))][:2]
                elif self.cfg.lost_is_change:
                    p_now, f = p_ref, np.zeros(3)      # the cluster vanished: its force changed fully
                else:
                    continue                           # the cluster moved or split: no reading this frame
                pts.append(self._world(s, p_ref))
                df = f - f_ref
                if self.cfg.shear_only:                # a pull drags the gel along its surface
                    df = df - (df @ nrm) * nrm
                e = self._along(s, p_ref, nrm) if self.cfg.along_only else None
                changes.append(float(abs(df @ e)) if e is not None else float(np.linalg.norm(df)))
                dp = p_now - p_ref
                drifts.append(float(abs(dp @ e)) if e is not None else float(np.linalg.norm(dp - (dp @ nrm) * nrm)))
                loads.append(float(np.linalg.norm(f_ref)))
                who.append(s)
        objects: list[dict] = []
        for p, ch, load, s, dr in zip(pts, changes, loads, who, drifts):
            for o in objects:
                if np.linalg.norm(o["point"] - p) * 1000 <= self.cfg.group_mm:
                    o["members"].append(p)
                    o["point"] = np.mean(o["members"], axis=0)
                    o["by_sensor"][s] = o["by_sensor"].get(s, 0.0) + ch
                    o["drift_by"][s] = max(o["drift_by"].get(s, 0.0), dr)
                    o["load_by"][s] = o["load_by"].get(s, 0.0) + load
                    o["load"] += load
                    o["sensors"].add(s)
                    break
            else:
                objects.append({"point": p, "members": [p], "by_sensor": {s: ch}, "load_by": {s: load}, "load": load,
                                "sensors": {s}, "drift_by": {s: dr}})
        c = self.cfg
        for o in objects:                              # both gels' witness, the stronger or weaker one, or the sum
            if c.witness in ("both", "max", "min"):
                per = [ch / (max(o["load_by"][k] + c.load_floor_n, 1e-6) ** c.load_power if c.per_load else 1.0)
                       + c.drift_weight * o["drift_by"][k] for k, ch in o["by_sensor"].items()]
                o["change"] = WITNESS[c.witness](per)
            else:
                o["change"] = sum(o["by_sensor"].values())
        both = [o for o in objects if len(o["sensors"]) == len(self.SENSORS)]
        if self.cfg.both_sensors and len(both) >= 2:   # a cluster only one fingertip feels is not a pinched object
            objects = both
            if self.cfg.most_loaded > 0:               # a pinch holds two objects: the most loaded ones
                objects = sorted(objects, key=lambda o: -o["load"])[:self.cfg.most_loaded]
        elif self.cfg.drop_between:                    # a contact spanning two objects is not a third one
            objects = [o for o in objects if not between(o["point"], [x["point"] for x in objects if x is not o],
                                                         self.cfg.group_mm)]
        if self.cfg.per_load and self.cfg.witness == "sum":   # change per newton the object was held with
            for o in objects:
                o["change"] /= max(o["load"] + self.cfg.load_floor_n, 1e-6) ** self.cfg.load_power
        return objects

    def _gel(self, sensor: str, x: np.ndarray) -> np.ndarray:
        """World point x (m) → the gel point (mm, sensor frame) in its direction from the fingertip
        centre (the inverse of `_world`)."""
        T = self.graph.tip_thumb[self.node] if sensor == "thumb" else self.graph.tip_index[self.node]
        u = T[:3, :3].T @ (np.asarray(x, float) - self.arm - T[:3, 3])
        return self.mount.direction_to_gel(u / np.linalg.norm(u))

    def _reference_pair(self) -> dict | None:
        """The two objects of the reference (those the cluster rule would let compete, the two most
        loaded) and, per gel, where each lies on it (its world point seen from that fingertip), the
        direction along them there and the reference clusters split between them."""
        objs = self._objects({s: list(self._ref[s]) for s in self.SENSORS})
        if len(objs) < 2:
            return None
        objs = sorted(objs, key=lambda o: -o["load"])[:2]
        gels = {}
        for s in self.SENSORS:
            g = [self._gel(s, o["point"]) for o in objs]
            nrm = np.mean([n for _, _, n, _ in self._ref[s]], axis=0) if self._ref[s] else g[0] / np.linalg.norm(g[0])
            nrm = nrm / np.linalg.norm(nrm)
            gels[s] = {"at": g, "normal": nrm, "along": along_direction(g[0], g[1], nrm)}
        pair = {"objects": objs, "gels": gels}
        pair["ref"] = {s: split_forces(self._ref[s], gels[s]["at"]) for s in self.SENSORS}
        return pair

    def _lever(self, latest: dict[str, list]) -> list[dict] | None:
        """Per object of the reference pair: on each gel the force of all clusters split between
        the two objects by lever (`split_forces`), its change along the objects since the reference
        per load^`load_power`, plus `lever_drift_weight` per mm its force centroid slid along them; the
        geometric mean (`witness`) over the gels. None without a reference pair."""
        if self._pair is None:
            return None
        c = self.cfg
        out = []
        per: dict[int, list] = {0: [], 1: []}
        for s in self.SENSORS:
            gel = self._pair["gels"][s]
            now = split_forces(latest[s], gel["at"])
            ref = self._pair["ref"][s]
            e = gel["along"]
            for k in range(2):
                df = now["force"][k] - ref["force"][k]
                load = float(np.linalg.norm(ref["force"][k]))
                slide = float(abs((now["centroid"][k] - ref["centroid"][k]) @ e)) if now["weight"][k] > 0 and ref["weight"][k] > 0 else 0.0
                per[k].append(abs(float(df @ e)) / max(load + c.load_floor_n, 1e-6) ** c.load_power
                              + c.lever_drift_weight * slide)
        for k, o in enumerate(self._pair["objects"]):
            v = per[k]
            change = WITNESS[c.witness](v)
            out.append({"point": o["point"], "change": float(change), "load_by": o["load_by"], "load": o["load"],
                        "sensors": o["sensors"]})
        return out

    def _plan(self, moving: np.ndarray, other: np.ndarray | None, scores: list[float],
              held_n: float = 0.0, other_held_n: float = 0.0) -> Decision:
        """The goal and path for the moving object; `held_n`: its weaker gel's reference force (N).
        A thick, stiff object (held with ≥ `aim_min_load_n` on both gels) is aimed `aim_mm` beyond:
        a round pen centred between the fingertips lets one of them slide off it onto the other
        object; a thin string (held with less) would slip out of an off-centre pinch. Beside an
        object held with ≥ `aim_beside_load_n` on both gels (`other_held_n`) it is aimed as well: the
        fingertip centred on a cable rests on the pen beside it."""
        g = self.graph
        tips = np.stack([g.tip_thumb[:, :3, 3], g.tip_index[:, :3, 3]], axis=1)
        aimed = held_n >= self.cfg.aim_min_load_n or other_held_n >= self.cfg.aim_beside_load_n
        aim = self.cfg.aim_mm if aimed else 0.0
        cfg = self.cfg
        terms = goal_terms(g.point, g.normal, tips, g.normal[self.node], moving, other, cfg, aim, self.arm)
        score = goal_scores(g.point, g.normal, tips, g.reachable_costs(self.node), g.normal[self.node], moving,
                            other, cfg, aim, terms)
        goal = int(np.argmin(score)) if np.isfinite(score).any() else self.node
        return self._decision(moving, other, goal, g.path(self.node, goal), scores, terms, cfg, aim, self.arm)

    def _decision(self, moving, other, goal, path, scores, terms, cfg, aim, arm_from, **extra) -> Decision:
        arm = terms.pop("arm", None)
        chosen = {k: round(float(v[goal]), 3) for k, v in terms.items()}
        chosen.update(clear_mm=round(cfg.clear_mm, 3), aim_mm=aim, **extra)
        if arm is not None:
            chosen["arm_mm"] = [round(float(x) * 1000.0, 3) for x in arm[goal]]
        return Decision(moving, other, goal, path, scores, chosen, None if arm is None else arm[goal].copy(),
                        None if arm is None else np.asarray(arm_from, float).copy())

    def other_felt(self) -> dict[str, float]:
        """After a path: per gel the force (N) of the clusters lying nearer the other object's place
        on that gel than the held object's (both seen from the node the hand was sent to)."""
        d = self.decision
        out = {s: 0.0 for s in self.SENSORS}
        if d is None or d.other_point is None:
            return out
        with self._lock:
            latest = {s: list(v) for s, v in self.latest.items()}
        node, self.node = self.node, d.goal
        arm = self.arm
        if d.arm is not None:
            self.arm = d.arm
        try:
            for s in self.SENSORS:
                a, b = self._gel(s, d.moving_point), self._gel(s, d.other_point)
                for p, f, *_ in latest[s]:
                    if np.linalg.norm(p - b) < np.linalg.norm(p - a):
                        out[s] += float(np.linalg.norm(f))
        finally:
            self.node, self.arm = node, arm
        return out

    def repinch(self) -> Decision | None:
        """Call after the hold: when a gel still feels the other object (`other_felt` ≥ `touch_n`) and
        fewer than `repinches` were made, a new goal from the current one with `repinch_clear_mm`
        more clearance (and the same aim); its path is the new `trajectory`. None otherwise (also
        when the graph holds no better pinch)."""
        d = self.decision
        if d is None or d.other_point is None or d.terms.get("repinch", 0) >= self.cfg.repinches:
            return None
        felt = self.other_felt()
        if max(felt.values()) < self.cfg.touch_n:
            return None
        k = d.terms.get("repinch", 0) + 1
        g = self.graph
        tips = np.stack([g.tip_thumb[:, :3, 3], g.tip_index[:, :3, 3]], axis=1)
        cfg = replace(self.cfg, clear_mm=d.terms["clear_mm"] + self.cfg.repinch_clear_mm)
        aim = d.terms.get("aim_mm", 0.0)
        arm_now = self.arm if d.arm is None else d.arm
        terms = goal_terms(g.point, g.normal, tips, g.normal[self.start], d.moving_point, d.other_point, cfg, aim, arm_now)
        score = goal_scores(g.point, g.normal, tips, g.reachable_costs(d.goal), g.normal[self.start], d.moving_point,
                            d.other_point, cfg, aim, terms)
        goal = int(np.argmin(score)) if np.isfinite(score).any() else d.goal
        moved = "arm" in terms and np.linalg.norm(terms["arm"][goal] - arm_now) > 1e-4
        if goal == d.goal and not moved:
            return None
        before = {k2: d.terms[k2] for k2 in ("e", "lean", "h", "rho_other", "clear_mm") if k2 in d.terms}
        self.decision = self._decision(d.moving_point, d.other_point, goal, g.path(d.goal, goal), d.scores, terms, cfg,
                                       aim, arm_now, repinch=k, felt_n=[round(felt[s], 3) for s in self.SENSORS],
                                       before=before)
        return self.decision

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(times from now, joint targets) along the decided path; with an arm, the path is held at
        its goal for as many more steps as the arm needs (`arm_trajectory`)."""
        d = self.decision
        if d is None or not d.path:
            return np.zeros(0), np.zeros((0, self.graph.q.shape[1]))
        qs = self.graph.q[d.path]
        n = len(self.arm_trajectory())
        if n > len(qs):
            qs = np.concatenate([qs, np.repeat(qs[-1:], n - len(qs), axis=0)])
        return np.arange(1, len(qs) + 1) * self.cfg.step_s, qs

    def arm_trajectory(self) -> np.ndarray:
        """(steps, 3) the arm's translation at each step of `trajectory` (m): from where it was to the
        goal's, evenly over the path's steps or over enough steps to stay within `arm_step_mm` per
        step. Empty without an arm."""
        d = self.decision
        if d is None or d.arm is None or not d.path:
            return np.zeros((0, 3))
        move = d.arm - d.arm_from
        n = max(len(d.path), int(np.ceil(np.linalg.norm(move) * 1000.0 / self.cfg.arm_step_mm - 1e-9)))
        return d.arm_from + np.arange(1, n + 1)[:, None] / n * move

    def moved_to_goal(self) -> None:
        """The hand has executed the decision's trajectory: the arm is at its goal."""
        if self.decision is not None and self.decision.arm is not None:
            self.arm = self.decision.arm.copy()


def along_direction(a: np.ndarray, b: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Unit direction along two side-by-side objects lying at gel points a and b (mm) on a gel
    with surface normal `normal`: normal × (b − a), normalised."""
    e = np.cross(np.asarray(normal, float), np.asarray(b, float) - np.asarray(a, float))
    n = float(np.linalg.norm(e))
    return e / n if n > 1e-9 else np.zeros(3)


def split_forces(clusters: list, at: list[np.ndarray]) -> dict[str, list]:
    """Split a gel's clusters (position mm, force N, …) between two objects lying at gel points
    at[0] and at[1] (mm). A cluster whose centroid lies a fraction t of the way from at[0] to at[1]
    (projected on the line joining them, clipped to [0, 1]) gives (1 − t) of its force to object 0
    and t to object 1: the force-weighted centroid of two loads F0 at a and F1 at b lies at
    a + F1/(F0 + F1)·(b − a), so one cluster covering both objects is split as they load it, and a
    cluster on one object goes to it whole. Returns per object the summed force (3,), the
    force-weighted centroid of its shares (mm; `at[k]` when it has none) and the summed weight
    (|F| · share)."""
    a, b = np.asarray(at[0], float), np.asarray(at[1], float)
    ab = b - a
    L2 = max(float(ab @ ab), 1e-12)
    force = [np.zeros(3), np.zeros(3)]
    wsum, wpos = [0.0, 0.0], [np.zeros(3), np.zeros(3)]
    for p, f, *_ in clusters:
        p, f = np.asarray(p, float), np.asarray(f, float)
        t = min(1.0, max(0.0, float((p - a) @ ab) / L2))
        m = float(np.linalg.norm(f))
        for k, share in ((0, 1.0 - t), (1, t)):
            force[k] = force[k] + share * f
            wsum[k] += share * m
            wpos[k] = wpos[k] + share * m * p
    centroid = [wpos[k] / wsum[k] if wsum[k] > 1e-9 else (a, b)[k].copy() for k in range(2)]
    return {"force": force, "centroid": centroid, "weight": wsum}


def lateral_mm(points: np.ndarray, normals: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Distance (mm) of world point x (m) from each line through points[i] (m) along normals[i]
    (unit; one normal for all lines when given as (3,))."""
    d = np.asarray(x, float)[None, :] - points
    normals = np.broadcast_to(normals, d.shape)
    along = np.einsum("ij,ij->i", d, normals)
    return np.linalg.norm(d - along[:, None] * normals, axis=1) * 1000.0


def between(p: np.ndarray, others: list[np.ndarray], gap_mm: float) -> bool:
    """True when point p (m) lies between two of `others`: within `gap_mm` of the segment joining
    them and at least `gap_mm` from both ends. Two objects pressed on one gel close together can
    give one cluster whose force-weighted centroid lies between them, and a weak cluster can show
    up between two strong ones; neither is an object of its own."""
    g = gap_mm / 1000.0
    for i in range(len(others)):
        for j in range(i + 1, len(others)):
            a, b = others[i], others[j]
            ab = b - a
            L = float(np.linalg.norm(ab))
            if L < 2 * g:
                continue
            t = float((p - a) @ ab) / (L * L)
            off = np.linalg.norm(p - (a + t * ab))
            if off <= g and t * L >= g and (1 - t) * L >= g:
                return True
    return False


def goal_terms(points: np.ndarray, normals: np.ndarray, tips: np.ndarray, normal_now: np.ndarray,
               moving: np.ndarray, other: np.ndarray | None, cfg: ControllerConfig,
               aim_mm: float = 0.0, arm: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per graph node e, lean, h and rho_other (mm), as `goal_scores` describes them. `points` and
    `tips` are the graph's (the arm at home); `arm` is the arm's translation now (m). With
    `cfg.arm_mm` > 0 and another object, each node also gets the arm's translation across (within
    ±`arm_mm` of home: "arm", (N, 3) m) that puts its line of fingertip centres at the aimed place
    or up to `arm_beyond_mm` beyond it, away from the other object (on a grid of `arm_grid_mm`), where its
    clearance, centring and travel terms of `goal_scores` are least, and that travel ("arm_travel",
    mm); the terms are those of the node so carried."""
    n0 = np.asarray(normal_now, float) / np.linalg.norm(normal_now)
    moving = np.asarray(moving, float)
    arm = np.zeros(3) if arm is None else np.asarray(arm, float)
    points, tips = points + arm, tips + arm
    cross = centre_line(points, normals, moving, n0)
    across = None if other is None else (moving - other) - ((moving - other) @ n0) * n0
    out = {}
    if across is not None and np.linalg.norm(across) > 1e-6:
        u = across / np.linalg.norm(across)
        along = np.cross(n0, u)
        if cfg.arm_mm > 0:   # slide each node across, along u, to the best place up to arm_beyond_mm beyond the aim
            a_now = float(arm @ u)
            c = (cross - moving) @ u
            best, best_a = np.full(len(points), np.inf), np.full(len(points), a_now)
            for beyond in np.arange(0.0, cfg.arm_beyond_mm + 1e-9, cfg.arm_grid_mm):
                a = np.clip(a_now + (aim_mm + beyond) / 1000.0 - c, -cfg.arm_mm / 1000.0, cfg.arm_mm / 1000.0)
                e_k = np.abs((c + a - a_now) * 1000.0 - aim_mm)
                t_k = tips + ((a - a_now)[:, None] * u)[:, None, :]
                rho_k = lateral_mm(t_k.reshape(-1, 3), along, np.asarray(other, float)).reshape(-1, 2).min(axis=1)
                local = (cfg.clear_weight * np.clip(cfg.clear_mm - rho_k, 0.0, None) + e_k
                         + cfg.keep_weight * np.clip(e_k - cfg.keep_mm, 0.0, None)
                         + cfg.arm_weight * np.abs(a - a_now) * 1000.0)
                better = local < best - 1e-12
                best, best_a = np.where(better, local, best), np.where(better, a, best_a)
            shift = (best_a - a_now)[:, None] * u
            points, tips, cross = points + shift, tips + shift[:, None, :], cross + shift
            out = {"arm": arm + shift, "arm_travel": np.abs(best_a - a_now) * 1000.0}
        e = np.abs((cross - moving) @ u * 1000.0 - aim_mm)
        lean = np.max(np.abs((tips - cross[:, None, :]) @ u), axis=1) * 1000.0
        rho_o = lateral_mm(tips.reshape(-1, 3), along, np.asarray(other, float)).reshape(-1, 2).min(axis=1)
    else:
        e = lateral_mm(cross, n0, moving)
        d = tips - cross[:, None, :]
        lean = np.max(np.linalg.norm(d - (d @ n0)[..., None] * n0, axis=2), axis=1) * 1000.0
        rho_o = np.full(len(points), cfg.clear_mm)
    h = np.abs((moving[None, :] - points) @ n0) * 1000.0
    return {"e": e, "lean": lean, "h": h, "rho_other": rho_o, **out}


def goal_scores(points: np.ndarray, normals: np.ndarray, tips: np.ndarray, costs: np.ndarray,
                normal_now: np.ndarray, moving: np.ndarray, other: np.ndarray | None,
                cfg: ControllerConfig, aim_mm: float = 0.0, terms: dict | None = None) -> np.ndarray:
    """Score of each graph node as the goal (lower is better, inf = not allowed). `tips` (N, 2, 3):
    both fingertip centres of each node (m). The objects lie in the plane through `moving` normal
    to the current pinch normal `normal_now`, side by side (distances along them do not count: a
    pinch's place along the objects does not matter). Per node:
      e      how far its line of fingertip centres crosses that plane from the moving object: the
             object is centred between the fingertips when e = 0, whatever its thickness;
      lean   the larger across offset of its two fingertip centres from that crossing (a tilted
             line leans one fingertip towards the other object and lets it slide off a thick one);
      h      its pinch point's distance from the plane along `normal_now` (a pinch closing off the
             plane pushes the object into one fingertip first);
      ρ_other the nearer fingertip centre's distance from the other object's axis (the line through
             it along the objects): the gel, a sphere about that centre, touches the other object
             when ρ_other < gel radius + the object's radius.
    With `aim_mm` e is measured from the point that far beyond the moving object, away from the
    other (the pinch then squeezes the object away from the other, not towards it). Without another
    object e and lean are distances in the plane. Allowed: reachable (finite path
    cost, rad) with a pinch normal within `max_normal_deg` of `normal_now`. Score =
    clear_weight · (shortfall of ρ_other below `clear_mm`) + keep_weight · (excess of e over
    `keep_mm`, of lean over `lean_mm`, of h over `depth_mm`) + e + lean + h + cost_weight · path
    cost, so the limits are met where the graph allows and approached as near as it can otherwise."""
    n0 = np.asarray(normal_now, float) / np.linalg.norm(normal_now)
    t = terms if terms is not None else goal_terms(points, normals, tips, n0, moving, other, cfg, aim_mm)
    e, lean, h, rho_o = t["e"], t["lean"], t["h"], t["rho_other"]
    miss = (cfg.clear_weight * np.clip(cfg.clear_mm - rho_o, 0.0, None)
            + cfg.keep_weight * (np.clip(e - cfg.keep_mm, 0.0, None) + np.clip(lean - cfg.lean_mm, 0.0, None)
                                 + np.clip(h - cfg.depth_mm, 0.0, None)))
    score = miss + e + lean + h + cfg.cost_weight_mm_per_rad * np.nan_to_num(costs, posinf=0.0)
    if "arm_travel" in t:
        score = score + cfg.arm_weight * t["arm_travel"]
    ok = np.isfinite(costs) & (normals @ n0 >= np.cos(np.radians(cfg.max_normal_deg)))
    return np.where(ok, score, np.inf)


class ControllerNode:
    """Wires a controller to Zenoh: one Subscriber per fingertip sensor id. `controller` may be
    replaced between trials; the subscriptions stay."""

    def __init__(self, controller: SelectiveGraspController, session, sensor_ids: dict[str, str]):
        from ...runtime.apps.subscriber import Subscriber

        self.controller = controller
        self.subs = [Subscriber(sid, session=session, on_contacts=lambda fr, s=name: self.controller.on_contacts(s, fr))
                     for name, sid in sensor_ids.items()]

    def close(self) -> None:
        for s in self.subs:
            s.close()
