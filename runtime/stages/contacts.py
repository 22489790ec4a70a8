"""Contact clustering (seed §III.M): contact-force field → ranked, tracked contact clusters.

|f_n + f_s| per pixel (N, = traction × pixel area) above a threshold (seed: 0.005 N; default 0.002 N, see ContactConfig) → binary mask →
8-connected components (the cluster cores; a light touch spreads thinner than the threshold, so a
component of pixels above the weak threshold counts as a core too when its total force reaches
min_total_n) → cores bridged above merge_n joined, other cores holding several peaks with a deep enough
dip between them split (split_dip) → each core grown onto weaker pixels nearby, so its total
force includes the tails the threshold cuts off → per cluster: 2D centroid, 3D centroid (deformed surface, mm), mean normal,
area (mm²), total force vector (N), perimeter (px), circularity 4πA/P², priority from force and
stability. Ids stay stable across frames by matching 3D centroids (Hungarian assignment with a gate).
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ContactConfig:
    # per-pixel force (N) that makes a cluster core. The seed uses 0.005 N on its grid; on ours (128²,
    # pixel area 0.044–0.066 mm²) with the current FE gel a 1 N poke peaks at ~0.004 N per pixel, so
    # 0.005 N missed every contact below ~1.5 N. 0.002 N: the lowest value with no false contact on any
    # rest frame of the 6 training sessions with an earlier model (0.0015 N gave 2–16 per session). A
    # package carries its own measured value (manifest `contacts`, tools/train/threshold.py).
    threshold_n: float = 0.002
    support_floor_n: float = 0.0001  # weaker pixels near a cluster still add their force ...
    support_radius_px: float = 10.0  # ... if within this distance of the cluster's core mask (the σ = 2 px
                                     # tails of a 4 N contact: 0.0005 N / 6 px lost 2.5 % of its force)
    min_pixels: int = 3             # drop specks smaller than this (noise)
    # light touches: a component of pixels above weak_threshold_n with no pixel above threshold_n is a core
    # when |its total force| >= min_total_n (N). 0 = off; packages carry measured values
    # (manifest.runtime, tools/train/threshold.py): with the model it was measured on, 0.3-0.5 / 0.5-1 N
    # contacts went from 43 / 80 % to 81 / 97 % of held-out frames detected (docs/history/BENCHMARKS-sessions-1-16.md "Light contacts")
    weak_threshold_n: float = 0.0
    min_total_n: float = 0.0
    # cores joined by pixels above merge_n (N) are one cluster (0 = off); packages carry a measured value
    merge_n: float = 0.0
    # a core holding several peaks is split where the field between them dips: a peak is its own contact
    # when every path from it to a higher pixel falls below (1 - split_dip) x its own peak (0 = off; in
    # (0, 1): 0.5 splits two presses whose fields join at less than half the weaker peak). Two heavy
    # presses 8 mm apart join above any usable threshold; packages carry a measured value
    split_dip: float = 0.0
    match_gate_mm: float = 4.0      # max centroid jump to keep a cluster's id between frames
    stable_frames: int = 5          # frames until a cluster counts as fully stable for priority
    max_contacts: int = 16          # cap published clusters (highest priority first)


@dataclass
class Cluster:
    id: int
    uv_px: tuple[float, float]       # (u = column, v = row) on the model grid, force-weighted
    position_mm: tuple[float, float, float]
    normal: tuple[float, float, float]
    area_mm2: float
    force_n: tuple[float, float, float]
    force_mag_n: float
    pixels: int
    perimeter_px: float
    circularity: float
    priority: float = 0.0
    age_frames: int = 0                    # frames this id has been tracked
    indentation_mm: float = 0.0            # deepest inward displacement (along the rest normal) of its pixels

    def to_dict(self) -> dict:
        return asdict(self)


def pixel_forces(fields: np.ndarray, pixel_area: np.ndarray) -> np.ndarray:
    """(15, H, W) fields (tractions in MPa) → (3, H, W) contact force per pixel in N."""
    return (fields[9:12] + fields[12:15]) * pixel_area[None]


def find_clusters(force_px: np.ndarray, surface_xyz: np.ndarray, normals: np.ndarray,
                  pixel_area: np.ndarray, mask: np.ndarray, disp: np.ndarray | None = None,
                  cfg: ContactConfig = ContactConfig()) -> list[Cluster]:
    """Untracked clusters (id = -1) of one frame, in label order.

    Every per-cluster sum runs over the cluster's pixels in raster order (np.bincount), so the numbers
    do not depend on how the work is cut: a frame with no pixel above a threshold returns before any
    labelling, and the support growth runs on the cores' neighbourhood only (docs/runtime.md "Speed")."""
    fx, fy, fz = force_px[0], force_px[1], force_px[2]
    mag = np.sqrt(fx * fx + fy * fy + fz * fz)
    binary = ((mag > cfg.threshold_n) & mask).astype(np.uint8)
    light = light_cores(force_px, mag, mask, binary, cfg)
    if light is not None:
        binary = binary | light
    if not binary.any():
        return []
    n, labels = cv2.connectedComponents(binary, connectivity=8)
    joined = None
    if n > 2 and cfg.merge_n > 0:
        n0, pre = n, labels
        labels, n, _ = merge_bridged(labels, binary, mag, mask, cfg.merge_n)
        ci = np.flatnonzero(pre.ravel())
        pairs = np.unique(labels.ravel()[ci].astype(np.int64) * n0 + pre.ravel()[ci])
        joined = np.bincount(pairs // n0, minlength=n) > 1        # labels made of several cores
    split = ()
    if 0.0 < cfg.split_dip < 1.0:
        labels, n, split = split_peaks(labels, n, mag, cfg.split_dip, joined)
    k = n
    flat = labels.ravel()
    ci = np.flatnonzero(flat)                     # core pixels, raster order
    core = flat[ci]
    pixels = np.bincount(core, minlength=k)
    area = np.bincount(core, weights=pixel_area.ravel()[ci], minlength=k)
    support = _support_labels(labels, mag, cfg)
    idx = np.flatnonzero(support)                 # only pixels that belong to some cluster
    lab = support.ravel()[idx]
    w = mag.ravel()[idx]
    wsum = np.bincount(lab, weights=w, minlength=k)
    safe = np.where(wsum > 0, wsum, 1.0)
    wd = mag.shape[1]
    vv, uu = np.divmod(idx, wd)

    def per_cluster(values, weights=None):  # (len(idx), m) values -> (k, m) per-cluster sums of weights * values
        return np.stack([np.bincount(lab, weights=values[:, i] if weights is None else weights * values[:, i],
                                     minlength=k) for i in range(values.shape[1])], 1)

    uv = per_cluster(np.stack([uu + 0.5, vv + 0.5], 1), w) / safe[:, None]
    pos = surface_xyz.reshape(-1, 3)[idx]
    nrm = normals.reshape(-1, 3)[idx]
    indent = np.zeros(k)
    if disp is not None:
        d = disp.reshape(3, -1)[:, idx].T
        pos = pos + d
        # the indenter's depth: the cluster's deepest point, not its force-weighted centroid
        _max_per_label(indent, lab, -np.einsum("ij,ij->i", d, nrm))
    centroid = per_cluster(pos, w) / safe[:, None]
    nsum = per_cluster(nrm, w) / safe[:, None]
    nsum /= np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-12)
    fvec = per_cluster(force_px.reshape(3, -1)[:, idx].T)
    perim, circ = _shape_metrics(binary, labels, k, split)
    out = []
    for j in range(1, k):
        if pixels[j] < cfg.min_pixels:
            continue
        out.append(Cluster(
            id=-1, uv_px=(float(uv[j, 0]), float(uv[j, 1])), position_mm=tuple(map(float, centroid[j])),
            normal=tuple(map(float, nsum[j])), area_mm2=float(area[j]), force_n=tuple(map(float, fvec[j])),
            force_mag_n=float(np.linalg.norm(fvec[j])), pixels=int(pixels[j]),
            perimeter_px=float(perim[j]), circularity=float(circ[j]), indentation_mm=float(indent[j])))
    return out


def _max_per_label(out: np.ndarray, lab: np.ndarray, values: np.ndarray) -> None:
    """out[j] = max(out[j], values where lab == j) for every label (np.maximum.at, without its slow path):
    one masked pass per label when there are few, else one sort."""
    if not len(lab):
        return
    if len(out) <= 8:
        for j in range(1, len(out)):
            sel = values[lab == j]
            if len(sel):
                out[j] = np.maximum(out[j], sel.max())
        return
    order = np.argsort(lab, kind="stable")
    sl = lab[order]
    starts = np.flatnonzero(np.concatenate([[True], sl[1:] != sl[:-1]]))
    j = sl[starts]
    out[j] = np.maximum(out[j], np.maximum.reduceat(values[order], starts))


def merge_bridged(labels: np.ndarray, binary: np.ndarray, mag: np.ndarray, mask: np.ndarray,
                  merge_n: float) -> tuple[np.ndarray, int, np.ndarray]:
    """Cores joined by a path of pixels above merge_n (8-connected) become one cluster: one contact
    whose field dips between two peaks (a sliding contact's split shear) is not published twice.
    Returns (labels, n incl. background, stats with CC_STAT_AREA filled)."""
    _, wl = cv2.connectedComponents((((mag > merge_n) & mask) | (binary > 0)).astype(np.uint8), connectivity=8)
    core = np.where(labels > 0, wl, 0)
    present = np.zeros(int(wl.max()) + 1, bool)
    present[core[labels > 0]] = True
    present[0] = False
    remap = np.cumsum(present) * present
    new = remap[core].astype(np.int32)
    n = int(remap.max()) + 1
    stats = np.zeros((n, 5), np.int64)
    stats[:, cv2.CC_STAT_AREA] = np.bincount(new.ravel(), minlength=n)
    return new, n, stats


def split_peaks(labels: np.ndarray, n: int, mag: np.ndarray, dip: float,
                keep: np.ndarray | None = None) -> tuple[np.ndarray, int, tuple[int, ...]]:
    """Cores (labels 1..n-1) holding several significant peaks become one cluster per peak.

    A peak (a local maximum of |f| on a core, 8-neighbourhood) is significant when, at the level
    (1 - dip) x its value, the part of its core above that level that holds it has no higher pixel: the
    field dips by at least `dip` of the peak on every path within the core to a higher one. The highest
    peak of a core always is. Each significant peak's part at its level seeds a cluster, and the rest of
    the core goes to the nearest seed pixel. Labels where `keep` (bool per label) is set stay whole: cores
    merging joined on purpose (merge_bridged). Returns (labels, n incl. background, labels whose pixels
    were split)."""
    dil = cv2.dilate(mag, np.ones((3, 3), np.uint8))
    peak = (mag >= dil) & (labels > 0)
    per = np.bincount(labels[peak], minlength=n)
    if keep is not None:
        per[np.flatnonzero(keep)] = 0
    multi = np.flatnonzero(per[1:] > 1) + 1
    if not len(multi):
        return labels, n, ()
    out = labels.copy()
    touched = []
    for j in multi:
        rows, cols = np.nonzero(labels == j)
        r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
        m, core = mag[r0:r1, c0:c1], labels[r0:r1, c0:c1] == j
        pv, pu = np.nonzero(peak[r0:r1, c0:c1] & core)
        seeds = []
        for i in np.argsort(-m[pv, pu], kind="stable"):
            v, u = pv[i], pu[i]
            p = float(m[v, u])
            if any(sd[v, u] for sd in seeds):             # a plateau's twin, or inside a seed already
                continue
            _, cl = cv2.connectedComponents(((m > (1.0 - dip) * p) & core).astype(np.uint8), connectivity=8)
            comp = cl == cl[v, u]
            if seeds and float(m[comp].max()) > p:          # a path to a higher pixel stays above the level
                continue
            seeds.append(comp)
        if len(seeds) < 2:
            continue
        marker = np.zeros(m.shape, np.int32)
        for s_i, sd in enumerate(seeds):
            marker[sd] = s_i + 1
        _, nearest = cv2.distanceTransformWithLabels((marker == 0).astype(np.uint8), cv2.DIST_L2, 5,
                                                     labelType=cv2.DIST_LABEL_PIXEL)
        flat = marker.ravel()
        grown = np.concatenate([[0], flat[flat > 0]])[nearest]       # seed pixels numbered in raster order
        new_ids = np.array([0, j] + list(range(n, n + len(seeds) - 1)), np.int32)
        sub = out[r0:r1, c0:c1]
        sub[core] = new_ids[grown[core]]
        touched += [int(j)] + list(range(n, n + len(seeds) - 1))
        n += len(seeds) - 1
    return out, n, tuple(touched)


def weak_components(force_px: np.ndarray, mag: np.ndarray, mask: np.ndarray, strong: np.ndarray,
                    weak_n: float) -> tuple[np.ndarray, np.ndarray]:
    """Components of pixels above weak_n that hold no strong pixel: (labels (H, W), |total force| per
    label (N), 0 for label 0 and for labels holding a strong pixel)."""
    n, labels = cv2.connectedComponents(((mag > weak_n) & mask).astype(np.uint8), connectivity=8)
    idx = np.flatnonzero(labels)                 # only the (few) pixels above weak_n
    lab = labels.ravel()[idx]
    tot = np.linalg.norm(np.stack([np.bincount(lab, weights=force_px[i].ravel()[idx], minlength=n)
                                   for i in range(3)], 1), axis=1)
    tot[np.bincount(lab, weights=strong.ravel()[idx].astype(np.float64), minlength=n) > 0] = 0.0
    tot[0] = 0.0
    return labels, tot


def light_cores(force_px, mag, mask, strong, cfg: ContactConfig) -> np.ndarray | None:
    """Mask (uint8) of the weak components whose total force reaches cfg.min_total_n, or None (rule off)."""
    if cfg.weak_threshold_n <= 0 or cfg.min_total_n <= 0 or cfg.weak_threshold_n >= cfg.threshold_n:
        return None
    # |a component's total force| <= the sum of its pixels' |force| <= that sum over all weak pixels: when
    # even that is short of min_total_n (a rest frame), no component can qualify (margin for rounding)
    if float(mag.sum(where=(mag > cfg.weak_threshold_n) & mask, dtype=np.float64)) < cfg.min_total_n * (1 - 1e-6):
        return None
    labels, tot = weak_components(force_px, mag, mask, strong, cfg.weak_threshold_n)
    keep = tot >= cfg.min_total_n
    return keep[labels].astype(np.uint8) if keep.any() else None


def _support_labels(labels: np.ndarray, mag: np.ndarray, cfg: ContactConfig) -> np.ndarray:
    """Core labels grown onto weaker nearby pixels (nearest core pixel within the support radius),
    so a cluster's force includes the tails the detection threshold cuts off.

    The distance transform runs on the cores' bounding box grown by more than the radius: OpenCV's 5×5
    chamfer distance is within 2 % of the Euclidean one and its shortest paths stay inside the box
    spanned by a pixel and its core pixel, so every pixel it can keep gets the same distance and label
    as on the whole image, and every pixel outside is farther than the radius."""
    if cfg.support_radius_px <= 0:
        return labels
    h, w = labels.shape
    rows = np.flatnonzero(labels.any(axis=1))
    cols = np.flatnonzero(labels.any(axis=0))
    m = int(np.ceil(cfg.support_radius_px * 1.05)) + 3
    r0, r1 = max(rows[0] - m, 0), min(rows[-1] + m + 1, h)
    c0, c1 = max(cols[0] - m, 0), min(cols[-1] + m + 1, w)
    sub = labels[r0:r1, c0:c1]
    dist, nearest = cv2.distanceTransformWithLabels((sub == 0).astype(np.uint8), cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
    flat = sub.ravel()
    by_seed = np.concatenate([[0], flat[flat > 0]])  # DIST_LABEL_PIXEL numbers core pixels in raster order
    grown = by_seed[nearest]
    keep = (sub > 0) | ((mag[r0:r1, c0:c1] > cfg.support_floor_n) & (dist <= cfg.support_radius_px))
    out = np.zeros(labels.shape, np.int32)
    out[r0:r1, c0:c1] = np.where(keep, grown, 0)
    return out


def _shape_metrics(binary: np.ndarray, labels: np.ndarray, k: int, split: tuple = ()) -> tuple[np.ndarray, np.ndarray]:
    """Perimeter (contour length, px) and circularity 4πA/P² per label (1 for a disc); the labels in
    `split` (parts of one core, split_peaks) from their own pixels."""
    perim = np.zeros(k)
    circ = np.zeros(k)

    def take(contours, j_of):
        for c in contours:
            j = j_of(c)
            p = cv2.arcLength(c, True)
            a = cv2.contourArea(c)
            if p > perim[j]:  # one external contour per 8-connected component; keep the longest
                perim[j] = p
                circ[j] = min(1.0, 4 * np.pi * a / (p * p)) if p > 0 else 0.0

    split_set = set(split)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    take([c for c in contours if labels[c[0, 0, 1], c[0, 0, 0]] not in split_set],
         lambda c: labels[c[0, 0, 1], c[0, 0, 0]])
    for j in split:
        contours, _ = cv2.findContours((labels == j).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        take(contours, lambda c, j=j: j)
    return perim, circ


@dataclass
class ContactTracker:
    """Assigns stable ids across frames and ranks clusters by force and stability."""

    cfg: ContactConfig = field(default_factory=ContactConfig)
    _prev: list[Cluster] = field(default_factory=list)
    _next_id: int = 0

    def update(self, clusters: list[Cluster]) -> list[Cluster]:
        prev = self._prev
        if prev and clusters:
            a = np.array([c.position_mm for c in prev])
            b = np.array([c.position_mm for c in clusters])
            cost = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
            rows, cols = linear_sum_assignment(cost)
            for r, c in zip(rows, cols):
                if cost[r, c] <= self.cfg.match_gate_mm:
                    clusters[c].id = prev[r].id
                    clusters[c].age_frames = prev[r].age_frames + 1
        for c in clusters:
            if c.id < 0:
                c.id = self._next_id
                self._next_id += 1
        for c in clusters:
            stability = min(1.0, (c.age_frames + 1) / self.cfg.stable_frames)
            c.priority = float(c.force_mag_n * stability)
        clusters.sort(key=lambda c: c.priority, reverse=True)
        clusters = clusters[: self.cfg.max_contacts]
        self._prev = clusters
        return clusters

    def reset(self) -> None:
        self._prev = []
