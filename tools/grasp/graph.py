"""The thumb–index contact graph (seed §V-B).

Nodes: contact configurations of the chosen hand variant, each with its joint angles (thumb then
index), the world contact point p_c, the contact direction in each fingertip frame (unit vector from
the sphere centre to coal's nearest point) and where each fingertip sensor reports that contact
(gel point in the sensor frame, mm, through the SensorMount). Only contacts on both gels are kept. Edges: the k nearest neighbours in joint space, weighted by joint-space distance
(rad). Paths: Dijkstra (scipy.sparse.csgraph). Stored as one .npz (no pickle).

Nodes are collected the way the seed describes it — exploring the joint space while keeping thumb
and index in contact: uniform samples seed the set, then random small joint steps from stored nodes
that stay in contact are added until the set has `nodes` entries. The region around the start
pinch (the node whose contacts sit nearest both gels' apexes, where a grasp begins) is then refined
the same way: smaller random joint steps from stored nodes whose pinch lies within
`refine_radius_mm` of the start's, keeping the new contacts that also lie within it.
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from ...contracts.errors import TensorTouchError
from ...contracts.files import atomic_write
from .hand_model import HandSpec, limits
from .sensor_mount import SensorMount
from .workspace import WorkspaceConfig, evaluate, sample_q

SCHEMA = "tensortouch.contact_graph/1"


class GraphError(TensorTouchError):
    """A contact graph file is not what was expected."""


@dataclass(frozen=True)
class GraphConfig:
    nodes: int = 2700            # seed §V-B: about 2,700 contact configurations
    k: int = 12                  # neighbours per node
    step_rad: float = 0.06       # joint step of the exploration
    seed_nodes: int = 100        # uniform samples until this many contacts, then exploration steps
    batch: int = 4000
    max_rounds: int = 400
    seed: int = 1
    refine_nodes: int = 1300     # extra nodes around the start pinch (0: no refinement)
    refine_radius_mm: float = 14.0
    refine_step_rad: float = 0.03


@dataclass
class ContactGraph:
    q: np.ndarray             # (N, n) joint angles, thumb joints then index joints (rad)
    point: np.ndarray         # (N, 3) world contact point p_c (m)
    normal: np.ndarray        # (N, 3) contact normal, index → thumb
    dir_thumb: np.ndarray     # (N, 3) contact direction in the thumb fingertip frame (unit)
    dir_index: np.ndarray     # (N, 3) contact direction in the index fingertip frame (unit)
    sensor_thumb_mm: np.ndarray  # (N, 3) where the thumb sensor reports the contact (sensor frame, mm)
    sensor_index_mm: np.ndarray  # (N, 3) the same for the index sensor
    tip_thumb: np.ndarray     # (N, 4, 4) fingertip poses
    tip_index: np.ndarray
    edges: np.ndarray         # (E, 2) int node pairs, i < j
    weights: np.ndarray       # (E,) joint-space distance (rad)
    variant: np.ndarray       # (2,) z_cm, pitch_deg of the hand variant

    def __len__(self) -> int:
        return len(self.q)

    def matrix(self) -> csr_matrix:
        n = len(self)
        i, j = self.edges[:, 0], self.edges[:, 1]
        return csr_matrix((np.concatenate([self.weights, self.weights]),
                           (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(n, n))

    def nearest(self, q: np.ndarray) -> int:
        """Node closest to joint configuration q."""
        return int(np.argmin(np.linalg.norm(self.q - np.asarray(q), axis=1)))

    def path(self, start: int, goal: int) -> list[int]:
        """Shortest joint-space path start → goal (node ids); [] when unreachable."""
        _, pred = dijkstra(self.matrix(), indices=start, return_predecessors=True)
        if start != goal and pred[goal] < 0:
            return []
        out = [goal]
        while out[-1] != start:
            out.append(int(pred[out[-1]]))
        return out[::-1]

    def reachable_costs(self, start: int) -> np.ndarray:
        return dijkstra(self.matrix(), indices=start)


def knn_edges(q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Undirected k-NN edges in joint space with their Euclidean lengths."""
    k = min(k, len(q) - 1)
    if k < 1:
        return np.zeros((0, 2), int), np.zeros(0)
    d, j = cKDTree(q).query(q, k=k + 1)
    i = np.repeat(np.arange(len(q)), k)
    j, d = j[:, 1:].ravel(), d[:, 1:].ravel()
    pairs = np.stack([np.minimum(i, j), np.maximum(i, j)], 1)
    pairs, first = np.unique(pairs, axis=0, return_index=True)
    return pairs, d[first]


def _tip_directions(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Unit direction from each fingertip frame's origin to point p, in that frame."""
    rel = p - T[:, :3, 3]
    local = np.einsum("sji,sj->si", T[:, :3, :3], rel)
    return local / np.maximum(np.linalg.norm(local, axis=1, keepdims=True), 1e-12)


def across(g: ContactGraph, node: int) -> np.ndarray:
    """Rows: the pinch frame of `node` in world — across the pinch (the index finger's long axis,
    tip z, made normal to the pinch normal), along the objects, and the pinch normal."""
    n = g.normal[node] / np.linalg.norm(g.normal[node])
    v = g.tip_index[node][:3, 2] - (g.tip_index[node][:3, 2] @ n) * n
    v = v / np.linalg.norm(v)
    return np.stack([v, np.cross(n, v), n])


def centre_line(points: np.ndarray, normals: np.ndarray, plane_point: np.ndarray,
                plane_normal: np.ndarray) -> np.ndarray:
    """Where each pinch's line of fingertip centres (through points[i] along normals[i]: for two
    spheres the nearest points, their midpoint and both centres lie on one line) crosses the plane
    through `plane_point` normal to `plane_normal` (m). A pinch closing on an object of any
    thickness closes along this line, so an object there sits centred between the fingertips; the
    touching fingertips' own positions move apart along it by the object's thickness."""
    n0 = np.asarray(plane_normal, float) / np.linalg.norm(plane_normal)
    cos = normals @ n0
    t = ((np.asarray(plane_point, float)[None, :] - points) @ n0) / np.where(np.abs(cos) > 1e-6, cos, 1e-6)
    return points + t[:, None] * normals


def room(g: ContactGraph, node: int, band_mm=(6.5, 10.5), lane_mm: float = 10.0, depth_mm: float = 2.0,
         normal_deg: float = 10.0) -> tuple[int, int]:
    """How many pinches could close centred on an object lying `band_mm` away from `node`'s pinch,
    on either side across it (−, +): nodes whose line of fingertip centres (`centre_line`) crosses
    `node`'s objects' plane (through its pinch point, normal to its pinch normal) that far away
    along the across axis and within `lane_mm` along the objects, with a pinch point within
    `depth_mm` of the plane and a pinch normal within `normal_deg` (a pinch leaning less)."""
    n = g.normal[node] / np.linalg.norm(g.normal[node])
    rel = (centre_line(g.point, g.normal, g.point[node], n) - g.point[node]) @ across(g, node).T * 1000.0
    h = (g.point - g.point[node]) @ n * 1000.0
    ok = (g.normal @ n >= np.cos(np.radians(normal_deg))) & (np.abs(rel[:, 1]) <= lane_mm) & (np.abs(h) <= depth_mm)
    a = np.abs(rel[:, 0])
    band = ok & (a >= band_mm[0]) & (a <= band_mm[1])
    return int((band & (rel[:, 0] < 0)).sum()), int((band & (rel[:, 0] > 0)).sum())


def start_node(g: ContactGraph, mount: SensorMount, min_room: int = 5, candidates: int = 1000) -> int:
    """Where a grasp begins: in the largest connected part of the graph, the pinch whose contacts
    sit nearest both gels' apexes (the larger of the two angles is smallest) among those with at
    least `min_room` pinches on either side across it (`room`), so that the hand can move the
    pinch off either of two objects held side by side. Without such a node: nearest the apexes."""
    from scipy.sparse.csgraph import connected_components

    _, lab = connected_components(g.matrix())
    big = lab == np.bincount(lab).argmax()
    ax = np.asarray(mount.axis_tip, float)
    ang = np.maximum(np.arccos(np.clip(g.dir_thumb @ ax, -1, 1)), np.arccos(np.clip(g.dir_index @ ax, -1, 1)))
    order = np.argsort(np.where(big, ang, np.inf))[:min(candidates, int(big.sum()))]
    for node in order:
        if min(room(g, int(node))) >= min_room:
            return int(node)
    return int(order[0])


def start_near(g: ContactGraph, mount: SensorMount, start: int, across_mm: float, tol_mm: float = 1.0,
               depth_mm: float = 2.0, normal_deg: float = 10.0, min_room: int = 5) -> int:
    """A trial's start pinch for objects laid out `across_mm` across the pinch from where `start`
    would hold them (the objects' plane through `start`'s pinch point, normal to its pinch normal):
    among the nodes connected to `start` whose line of fingertip centres crosses that plane within
    `tol_mm` of that place across the pinch (any place along the objects), with a pinch point within
    `depth_mm` of the plane and a normal within `normal_deg` of `start`'s, the one whose contacts
    sit nearest both gels' apexes with at least `min_room` pinches either side (`room`); without
    one with room, the nearest the apexes; without any, `start`."""
    from scipy.sparse.csgraph import connected_components

    _, lab = connected_components(g.matrix())
    fr = across(g, start)
    n = fr[2]
    rel = (centre_line(g.point, g.normal, g.point[start], n) - g.point[start]) @ fr[0] * 1000.0
    h = (g.point - g.point[start]) @ n * 1000.0
    ok = ((lab == lab[start]) & (np.abs(rel - across_mm) <= tol_mm) & (np.abs(h) <= depth_mm)
          & (g.normal @ n >= np.cos(np.radians(normal_deg))))
    if not ok.any():
        return int(start)
    ax = np.asarray(mount.axis_tip, float)
    ang = np.maximum(np.arccos(np.clip(g.dir_thumb @ ax, -1, 1)), np.arccos(np.clip(g.dir_index @ ax, -1, 1)))
    order = np.flatnonzero(ok)[np.argsort(ang[ok], kind="stable")]
    for node in order:
        if min(room(g, int(node))) >= min_room:
            return int(node)
    return int(order[0])


_KEYS = ("q", "point", "normal", "p_thumb", "p_index", "Tt", "Ti")


def _explore(model, spec: HandSpec, cfg: GraphConfig, ws_cfg: WorkspaceConfig, mount: SensorMount,
             rng: np.random.Generator, keep: dict[str, list], target: int, step: float, seed_nodes: int,
             region=None, progress=None) -> int:
    """Add contact configurations to `keep` until it holds `target`: uniform samples while it has
    fewer than `seed_nodes`, then random joint steps of `step` rad from stored nodes (only those
    whose pinch point passes `region`, when given). New contacts must land on both gels (and pass
    `region`). Returns the count."""
    cone = mount.cone_cos()
    axis = np.asarray(mount.axis_tip, float) / np.linalg.norm(mount.axis_tip)
    lo = np.concatenate(limits(model, spec.thumb)[:1] + limits(model, spec.index)[:1])
    hi = np.concatenate(limits(model, spec.thumb)[1:] + limits(model, spec.index)[1:])
    count = sum(len(a) for a in keep["q"])
    for _ in range(cfg.max_rounds):
        if count >= target:
            break
        if count < seed_nodes:
            q = sample_q(model, spec, cfg.batch, rng)
        else:
            stored_q = np.concatenate(keep["q"])
            pool = np.arange(count) if region is None else np.flatnonzero(region(np.concatenate(keep["point"])))
            if len(pool) == 0:
                break
            base = stored_q[pool[rng.integers(0, len(pool), cfg.batch)]]
            q = np.clip(base + rng.normal(0, step, base.shape), lo, hi)
        ws = evaluate(model, spec, q, ws_cfg)
        c = ws.contact.copy()
        if c.any():
            on_t = _tip_directions(ws.tip_thumb[c], ws.p_thumb[c]) @ axis >= cone
            on_i = _tip_directions(ws.tip_index[c], ws.p_index[c]) @ axis >= cone
            ok = on_t & on_i
            if region is not None:
                ok &= region(ws.point[c])
            c[np.flatnonzero(c)[~ok]] = False
        for key, arr in zip(_KEYS, (ws.q, ws.point, ws.normal, ws.p_thumb, ws.p_index, ws.tip_thumb, ws.tip_index)):
            keep[key].append(arr[c][:max(0, target - count)])
        count = min(target, count + int(c.sum()))
        if progress:
            progress(count, target)
    return count


def _assemble(a: dict, cfg: GraphConfig, mount: SensorMount, variant) -> ContactGraph:
    edges, weights = knn_edges(a["q"], cfg.k)
    dt, di = _tip_directions(a["Tt"], a["p_thumb"]), _tip_directions(a["Ti"], a["p_index"])
    return ContactGraph(a["q"], a["point"], a["normal"], dt, di, mount.direction_to_gel(dt),
                        mount.direction_to_gel(di), a["Tt"], a["Ti"], edges, weights, np.asarray(variant, float))


def build(model, spec: HandSpec, variant=(np.nan, np.nan), cfg: GraphConfig | None = None,
          ws_cfg: WorkspaceConfig | None = None, progress=None, mount: SensorMount | None = None) -> ContactGraph:
    """Explore contacts on `model` (already set to the chosen variant) and connect them. Only
    contacts that land on both sensors' gels (within `mount`'s cone) are kept; then the region
    around the start pinch is refined (`GraphConfig.refine_nodes`)."""
    cfg = cfg or GraphConfig()
    mount = mount or SensorMount()
    ws_cfg = ws_cfg or WorkspaceConfig()
    rng = np.random.default_rng(cfg.seed)
    keep: dict[str, list] = {k: [] for k in _KEYS}
    total = cfg.nodes + max(0, cfg.refine_nodes)
    report = (lambda i, n: progress(i, total)) if progress else None
    count = _explore(model, spec, cfg, ws_cfg, mount, rng, keep, cfg.nodes, cfg.step_rad, cfg.seed_nodes,
                     progress=report)
    if count < 2:
        raise GraphError(f"only {count} contact configurations found; is the hand able to pinch?")
    a = {k: np.concatenate(v) for k, v in keep.items()}
    if cfg.refine_nodes > 0:
        centre = a["point"][start_node(_assemble(a, cfg, mount, variant), mount, min_room=0)]
        keep = {k: [v] for k, v in a.items()}

        def region(p):
            return np.linalg.norm(p - centre, axis=1) <= cfg.refine_radius_mm / 1000.0

        _explore(model, spec, cfg, ws_cfg, mount, rng, keep, count + cfg.refine_nodes, cfg.refine_step_rad, 0,
                 region=region, progress=report)
        a = {k: np.concatenate(v) for k, v in keep.items()}
    return _assemble(a, cfg, mount, variant)


_FIELDS = ("q", "point", "normal", "dir_thumb", "dir_index", "sensor_thumb_mm", "sensor_index_mm", "tip_thumb", "tip_index", "edges", "weights",
           "variant")


def save(graph: ContactGraph, path: str | Path) -> Path:
    buf = io.BytesIO()
    np.savez_compressed(buf, schema=np.array(SCHEMA), **{f: getattr(graph, f) for f in _FIELDS})
    return atomic_write(path, buf.getvalue())


def load(path: str | Path) -> ContactGraph:
    path = Path(path)
    if not path.is_file():
        raise GraphError(f"{path}: no such contact graph file")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "schema" not in z or str(z["schema"]) != SCHEMA:
                raise GraphError(f"{path}: field 'schema' should be {SCHEMA!r}")
            missing = [f for f in _FIELDS if f not in z]
            if missing:
                raise GraphError(f"{path}: missing arrays {missing}")
            g = ContactGraph(**{f: np.asarray(z[f]) for f in _FIELDS})
    except (OSError, ValueError) as exc:
        raise GraphError(f"{path}: not a contact graph .npz ({exc})") from exc
    n = len(g.q)
    if g.edges.ndim != 2 or g.edges.shape[1:] != (2,) or (len(g.edges) and (g.edges.min() < 0 or g.edges.max() >= n)):
        raise GraphError(f"{path}: field 'edges' should be (E,2) node ids in [0, {n})")
    if len(g.weights) != len(g.edges) or not np.all(np.isfinite(g.weights)) or np.any(g.weights < 0):
        raise GraphError(f"{path}: field 'weights' should be {len(g.edges)} finite non-negative lengths")
    return g
