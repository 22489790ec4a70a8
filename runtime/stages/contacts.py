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
import threading
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
    f = fields[9:12] + fields[12:15]
    if f.dtype == np.result_type(f, pixel_area):
        return np.multiply(f, pixel_area[None], out=f)          # in place: one (3, H, W) temporary fewer
    return f * pixel_area[None]


def force_magnitude(force_px: np.ndarray) -> np.ndarray:
    """|f| per pixel, (H, W): sqrt(fx² + fy² + fz²) in the forces' own precision, added in that order."""
    fx, fy, fz = force_px[0], force_px[1], force_px[2]
    mag = fx * fx
    sq = fy * fy
    mag += sq
    np.multiply(fz, fz, out=sq)
    mag += sq
    return np.sqrt(mag, out=mag)


def find_clusters(force_px: np.ndarray, surface_xyz: np.ndarray, normals: np.ndarray,
                  pixel_area: np.ndarray, mask: np.ndarray, disp: np.ndarray | None = None,
                  cfg: ContactConfig = ContactConfig()) -> list[Cluster]:
    """Untracked clusters (id = -1) of one frame, in label order.

    Labelling runs on the work box: the bounding box of the pixels above the lowest threshold any rule
    looks at, grown by one pixel, its corner on even coordinates (`_work_box`); the support growth on
    the cores' neighbourhood only; per-cluster sums over the cluster's pixels in raster order
    (np.bincount). So the numbers do not depend on how the work is cut (docs/runtime.md "Speed")."""
    mag = force_magnitude(force_px)
    box = _work_box(mag, mask, cfg)
    if box is None:
        return []
    r0, r1, c0, c1 = box
    m = np.ascontiguousarray(mag[r0:r1, c0:c1])
    msk = mask[r0:r1, c0:c1]
    binary = ((m > cfg.threshold_n) & msk).astype(np.uint8)
    light = light_cores(force_px[:, r0:r1, c0:c1], m, msk, binary, cfg)
    if light is not None:
        binary = binary | light
    if not binary.any():
        return []
    n, labels = cv2.connectedComponents(binary, connectivity=8)
    cr, cc = np.nonzero(labels)                   # core pixels, raster order
    joined = None
    if n > 2 and cfg.merge_n > 0:
        labels, n, joined = merge_bridged(labels, n, binary, m, msk, cfg.merge_n, (cr, cc))
    split = ()
    if 0.0 < cfg.split_dip < 1.0:
        labels, n, split = split_peaks(labels, n, m, cfg.split_dip, joined, (cr, cc))
    k = n
    core = labels[cr, cc]
    pixels = np.bincount(core, minlength=k)
    wanted = pixels >= cfg.min_pixels             # the clusters published; specks still compete for support
    wanted[0] = False
    if not wanted.any():
        return []
    area = np.bincount(core, weights=pixel_area[cr + r0, cc + c0], minlength=k)
    idx, rows, cols, lab = _support_pixels(_without_far_specks(labels, cr, cc, core, wanted, cfg), r0, c0, mag, cfg)
    if k > 2:                                     # grouped by label, each label's pixels in raster order
        order = np.argsort(lab.astype(np.uint16) if k <= 65536 else lab, kind="stable")
        idx, rows, cols, lab = idx[order], rows[order], cols[order], lab[order]
    w = np.take(mag.ravel(), idx)
    pos = np.take(surface_xyz.reshape(-1, 3), idx, axis=0).T      # (3, N) views of (N, 3) gathers
    nrm = np.take(normals.reshape(-1, 3), idx, axis=0).T
    indent = np.zeros(k)
    if disp is not None:
        d = np.take(disp.reshape(3, -1), idx, axis=1)
        pos = pos + d
        # the indenter's depth: the cluster's deepest point, not its force-weighted centroid; d · n
        # added in component order in the inputs' precision
        dn = d[0] * nrm[0]
        dn += d[1] * nrm[1]
        dn += d[2] * nrm[2]
        _max_per_label(indent, lab, -dn)
    # per pixel: weight, weighted (u, v), weighted position and normal (products in the inputs' own
    # precision), force; summed per cluster in float64
    p = _workspace(len(idx))[0]
    p[0] = w
    np.multiply(w, cols + 0.5, out=p[1])
    np.multiply(w, rows + 0.5, out=p[2])
    p[3:6] = pos * w
    p[6:9] = nrm * w
    p[9:12] = np.take(force_px.reshape(3, -1), idx, axis=1)
    sums = _label_sums(p, lab, k)
    wsum = sums[:, 0]
    safe = np.where(wsum > 0, wsum, 1.0)
    uv = sums[:, 1:3] / safe[:, None]
    centroid = sums[:, 3:6] / safe[:, None]
    nsum = sums[:, 6:9] / safe[:, None]
    nsum /= np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-12)
    fvec = sums[:, 9:12]
    perim, circ = _shape_metrics(binary, labels, k, split, wanted)
    out = []
    for j in np.flatnonzero(wanted):
        out.append(Cluster(
            id=-1, uv_px=(float(uv[j, 0]), float(uv[j, 1])), position_mm=tuple(map(float, centroid[j])),
            normal=tuple(map(float, nsum[j])), area_mm2=float(area[j]), force_n=tuple(map(float, fvec[j])),
            force_mag_n=float(np.linalg.norm(fvec[j])), pixels=int(pixels[j]),
            perimeter_px=float(perim[j]), circularity=float(circ[j]), indentation_mm=float(indent[j])))
    return out


def _light_rule_on(cfg: ContactConfig) -> bool:
    return not (cfg.weak_threshold_n <= 0 or cfg.min_total_n <= 0 or cfg.weak_threshold_n >= cfg.threshold_n)


def _work_box(mag: np.ndarray, mask: np.ndarray, cfg: ContactConfig) -> tuple[int, int, int, int] | None:
    """(r0, r1, c0, c1) holding every pixel above the lowest threshold a rule of `cfg` labels (core, light
    touch, merging) with one pixel to spare (3×3 peaks and contours see the same neighbourhood as on the
    whole image), or None when there is none. r0 and c0 are even: OpenCV labels 8-connected components
    in 2×2 blocks and numbers them in block order, so a box on the image's block grid numbers them as
    the whole image does."""
    low = cfg.threshold_n
    if _light_rule_on(cfg):
        low = min(low, cfg.weak_threshold_n)
    if cfg.merge_n > 0:
        low = min(low, cfg.merge_n)
    above = ((mag > low) & mask).view(np.uint8)
    c0, r0, bw, bh = cv2.boundingRect(above)
    if bw == 0:
        return None
    h, w = mag.shape
    return max(r0 - 1, 0) & ~1, min(r0 + bh + 1, h), max(c0 - 1, 0) & ~1, min(c0 + bw + 1, w)


_local = threading.local()


def _workspace(n: int) -> tuple[np.ndarray, np.ndarray]:
    """This thread's (12, n) and (n, 12) float64 scratch arrays for the per-pixel terms of the cluster
    sums (kept between frames: a fresh array of this size is fresh memory to fault in, every frame)."""
    buf = getattr(_local, "sums", None)
    if buf is None or buf[1].shape[0] < n:
        size = max(n, 4096)
        buf = _local.sums = (np.empty((12, size)), np.empty((size, 12)))
    return buf[0][:, :n], buf[1][:n]


def _grouped(lab: np.ndarray) -> np.ndarray | None:
    """None when `lab` is grouped by label (non-decreasing), else the stable order that groups it."""
    return None if len(lab) < 2 or bool((lab[1:] >= lab[:-1]).all()) else np.argsort(lab, kind="stable")


def _label_sums(values: np.ndarray, lab: np.ndarray, k: int) -> np.ndarray:
    """(m, N) float64 values of N pixels → (k, m) sums per label (lab: label 1..k-1 per pixel), each
    added pixel after pixel, in the pixels' order, from 0.0: np.bincount(lab, weights=row, minlength=k)
    row by row, bit for bit. einsum "ij->j" on a C-ordered (N, m) array with m ≥ 2 adds its rows one
    after another, all m columns at once (a bincount per row waits on every addition in turn); with one
    column it would reduce in blocks, so that case stays a bincount."""
    m, n = values.shape
    if m < 2 or m > 12:
        return np.stack([np.bincount(lab, weights=v, minlength=k) for v in values], 1)
    order = None if k == 2 else _grouped(lab)
    if order is not None:
        values, lab = np.take(values, order, axis=1), lab[order]
    rows = cv2.transpose(values, dst=_workspace(n)[1][:, :m] if m == 12 else None)   # (N, m), C-ordered
    out = np.zeros((k, m))
    if k == 2:
        out[1] = np.einsum("ij->j", rows)
        return out
    if k > 9:      # many labels: one bincount over (label, column) bins, in the rows' order, no loop
        bins = (lab[:, None] * m + np.arange(m)).ravel()
        return np.bincount(bins, weights=rows.ravel(), minlength=k * m).reshape(k, m)
    ends = np.cumsum(np.bincount(lab, minlength=k))
    for j in range(1, k):
        if ends[j] > ends[j - 1]:
            out[j] = np.einsum("ij->j", rows[ends[j - 1]:ends[j]])
    return out


def _max_per_label(out: np.ndarray, lab: np.ndarray, values: np.ndarray) -> None:
    """out[j] = max(out[j], values where lab == j) for every label (np.maximum.at, without its slow path)."""
    if not len(lab):
        return
    if len(out) == 2:
        out[1] = np.maximum(out[1], values.max())
        return
    order = _grouped(lab)
    if order is not None:
        lab, values = lab[order], values[order]
    starts = np.flatnonzero(np.concatenate([[True], lab[1:] != lab[:-1]]))
    j = lab[starts]
    out[j] = np.maximum(out[j], np.maximum.reduceat(values, starts))


def merge_bridged(labels: np.ndarray, n: int, binary: np.ndarray, mag: np.ndarray, mask: np.ndarray,
                  merge_n: float, core_px: tuple[np.ndarray, np.ndarray] | None = None
                  ) -> tuple[np.ndarray, int, np.ndarray]:
    """Cores joined by a path of pixels above merge_n (8-connected) become one cluster: one contact
    whose field dips between two peaks (a sliding contact's split shear) is not published twice.
    Clusters are numbered in the order of those paths' components. `core_px`: np.nonzero(labels) when
    the caller has it. Returns (labels, n incl. background, bool per label: made of several cores)."""
    nb, bridged = cv2.connectedComponents((((mag > merge_n) & mask) | (binary > 0)).astype(np.uint8),
                                          connectivity=8)
    cr, cc = np.nonzero(labels) if core_px is None else core_px
    clab = labels[cr, cc]
    of = np.zeros(n, np.int64)                    # each core's bridged component
    of[clab] = bridged[cr, cc]
    present = np.zeros(nb, bool)
    present[of[1:]] = True
    remap = np.cumsum(present) * present          # bridged components holding a core, numbered 1, 2, ...
    new_of = remap[of]
    n_new = int(present.sum()) + 1
    out = np.zeros_like(labels)
    out[cr, cc] = new_of[clab]
    return out, n_new, np.bincount(new_of[1:], minlength=n_new) > 1


def split_peaks(labels: np.ndarray, n: int, mag: np.ndarray, dip: float, keep: np.ndarray | None = None,
                core_px: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, int, tuple[int, ...]]:
    """Cores (labels 1..n-1) holding several significant peaks become one cluster per peak.

    A peak (a local maximum of |f| on a core, 8-neighbourhood) is significant when, at the level
    (1 - dip) x its value, the part of its core above that level that holds it has no higher pixel: the
    field dips by at least `dip` of the peak on every path within the core to a higher one. The highest
    peak of a core always is. Each significant peak's part at its level seeds a cluster, and the rest of
    the core goes to the nearest seed pixel. Labels where `keep` (bool per label) is set stay whole: cores
    merging joined on purpose (merge_bridged). `core_px`: np.nonzero(labels) when the caller has it.
    Returns (labels, n incl. background, labels whose pixels were split)."""
    cr, cc = np.nonzero(labels) if core_px is None else core_px
    clab = labels[cr, cc]
    cval = mag[cr, cc]
    is_peak = cval >= cv2.dilate(mag, np.ones((3, 3), np.uint8))[cr, cc]
    plab = clab[is_peak]                                  # the peaks, raster order
    per = np.bincount(plab, minlength=n)
    if keep is not None:
        per[np.flatnonzero(keep)] = 0
    multi = np.flatnonzero(per[1:] > 1) + 1
    if not len(multi):
        return labels, n, ()
    pr, pc, pval = cr[is_peak], cc[is_peak], cval[is_peak]
    # each peak's level as the comparisons with it round it (to the field's precision)
    plevel = ((1.0 - dip) * pval.astype(np.float64)).astype(mag.dtype)
    out = labels.copy()
    touched = []
    for j in multi:
        inj = clab == j
        low = cval[inj].min()
        on = np.flatnonzero(plab == j)
        order = on[np.argsort(-pval[on], kind="stable")]
        # a peak whose level lies below every pixel of the core has the whole core as its part, which
        # holds the highest peak (or a higher pixel): it cannot seed a cluster
        order = order[np.concatenate([[True], ~(low > plevel[order[1:]])])]
        if len(order) < 2:
            continue
        rows, cols = cr[inj], cc[inj]
        r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
        m, core = mag[r0:r1, c0:c1], labels[r0:r1, c0:c1] == j
        pv, pu = pr[order] - r0, pc[order] - c0
        seeds = [_part_above(m, core, pv[0], pu[0], dip)]     # the highest peak's
        rest = np.flatnonzero(~seeds[0][pv, pu])              # peaks outside it
        for v, u in zip(pv[rest], pu[rest]):
            if any(sd[v, u] for sd in seeds[1:]):         # a plateau's twin, or inside a seed already
                continue
            comp = _part_above(m, core, v, u, dip)
            if float(m[comp].max()) > float(m[v, u]):       # a path to a higher pixel stays above the level
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


def _part_above(m: np.ndarray, core: np.ndarray, v: int, u: int, dip: float) -> np.ndarray:
    """The 8-connected part of `core` above (1 - dip) × m[v, u] that holds pixel (v, u)."""
    p = float(m[v, u])
    _, cl = cv2.connectedComponents(((m > (1.0 - dip) * p) & core).astype(np.uint8), connectivity=8)
    return cl == cl[v, u]


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
    """Mask (uint8) of the weak components whose total force reaches cfg.min_total_n, or None (rule off).
    `strong`: the pixels above cfg.threshold_n within the mask (the cores).

    The exact total (weak_components) is summed only for components that can reach it: |a component's
    total force| <= the sum of its pixels' |force|, and a component holding no strong pixel has no
    pixel above the core threshold, so one with fewer pixels than min_total_n / threshold_n cannot
    (noise specks), nor can any when all weak pixels together fall short (a rest frame); margin for
    rounding. Works on any box of the frame that holds whole components (find_clusters' work box)."""
    if not _light_rule_on(cfg):
        return None
    weak = (mag > cfg.weak_threshold_n) & mask
    bound_n = cfg.min_total_n * (1 - 1e-6)
    if float(mag.sum(where=weak, dtype=np.float64)) < bound_n:    # not even all weak pixels together
        return None
    n, labels, stats, _ = cv2.connectedComponentsWithStats(weak.astype(np.uint8), connectivity=8)
    top = float(np.asarray(cfg.threshold_n, mag.dtype))          # the most a pixel below the cores holds
    can = stats[:, cv2.CC_STAT_AREA] * top >= bound_n
    can[0] = False
    if not can.any():
        return None
    can[labels[strong > 0]] = False               # holds a strong pixel: a core already
    if not can.any():
        return None
    sel = np.flatnonzero(can[labels])             # the candidates' pixels, raster order
    ls = labels.ravel()[sel]
    rr, cc = np.divmod(sel, labels.shape[1])
    tot = np.linalg.norm(np.stack([np.bincount(ls, weights=force_px[i][rr, cc], minlength=n)
                                   for i in range(3)], 1), axis=1)
    keep = tot >= cfg.min_total_n
    return keep[labels].astype(np.uint8) if keep.any() else None


def _without_far_specks(labels: np.ndarray, cr: np.ndarray, cc: np.ndarray, core: np.ndarray,
                        wanted: np.ndarray, cfg: ContactConfig) -> np.ndarray:
    """`labels` without the specks (labels not `wanted`) that cannot take a pixel from a published
    cluster's support: a speck pixel farther than 2 × (1.05 × radius + 3) px (in rows or columns) from
    the published clusters' cores is more than twice the radius from each of them (the chamfer distance
    is within 2 % of the Euclidean one), so no pixel lies within the radius of both. With no support
    growth no speck matters. `cr`, `cc`, `core`: the core pixels and their labels."""
    if wanted[1:].all():
        return labels
    spk = ~wanted[core]
    if cfg.support_radius_px > 0:
        reach = 2 * (int(np.ceil(cfg.support_radius_px * 1.05)) + 3)
        rk, ck = cr[~spk], cc[~spk]
        near = spk & (cr >= rk.min() - reach) & (cr <= rk.max() + reach) & (cc >= ck.min() - reach) & \
            (cc <= ck.max() + reach)
        close = np.zeros(len(wanted), bool)
        close[core[near]] = True
        spk &= ~close[core]
    if not spk.any():
        return labels
    out = labels.copy()
    out[cr[spk], cc[spk]] = 0
    return out


def _support_pixels(labels: np.ndarray, r0: int, c0: int, mag: np.ndarray,
                    cfg: ContactConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixels each cluster sums over, in raster order: (flat index in the image, row, column,
    label). `labels` are the cores on the work box at (r0, c0). The cores are grown onto weaker nearby
    pixels (nearest core pixel within the support radius, above the support floor), so a cluster's
    force includes the tails the detection threshold cuts off.

    The distance transform runs on the cores' bounding box grown by more than the radius: OpenCV's 5×5
    chamfer distance is within 2 % of the Euclidean one and its shortest paths stay inside the box
    spanned by a pixel and its core pixel, so every pixel it can keep gets the same distance and label
    as on the whole image, and every pixel outside is farther than the radius."""
    h, w = mag.shape
    if cfg.support_radius_px <= 0:
        rr, cc = np.nonzero(labels)
        lab = labels[rr, cc]
        rr, cc = rr + r0, cc + c0
        return rr * w + cc, rr, cc, lab
    rows = np.flatnonzero(labels.any(axis=1))
    cols = np.flatnonzero(labels.any(axis=0))
    top, bottom, left, right = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    mm = int(np.ceil(cfg.support_radius_px * 1.05)) + 3
    R0, R1 = max(top + r0 - mm, 0), min(bottom + r0 + mm, h)
    C0, C1 = max(left + c0 - mm, 0), min(right + c0 + mm, w)
    part = labels[top:bottom, left:right]
    free = np.ones((R1 - R0, C1 - C0), np.uint8)            # 0 on core pixels: the transform's seeds
    free[top + r0 - R0:bottom + r0 - R0, left + c0 - C0:right + c0 - C0] = part == 0
    dist, nearest = cv2.distanceTransformWithLabels(free, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    by_seed = np.concatenate([[0], part[part > 0]])  # DIST_LABEL_PIXEL numbers core pixels in raster order
    keep = mag[R0:R1, C0:C1] > cfg.support_floor_n
    keep &= dist <= cfg.support_radius_px
    keep |= free == 0
    fi = np.flatnonzero(keep)
    lab = by_seed[np.take(nearest, fi)]
    rr, cc = np.divmod(fi, C1 - C0)
    rr += R0
    cc += C0
    return rr * w + cc, rr, cc, lab


def _shape_metrics(binary: np.ndarray, labels: np.ndarray, k: int, split: tuple = (),
                   wanted: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Perimeter (contour length, px) and circularity 4πA/P² per label (1 for a disc); the labels in
    `split` (parts of one core, split_peaks) from their own pixels. Labels where `wanted` (bool per
    label) is False are left at 0."""
    perim = np.zeros(k)
    circ = np.zeros(k)
    if wanted is None:
        wanted = np.ones(k, bool)

    def take(c, j):
        p = cv2.arcLength(c, True)
        if p > perim[j]:  # one external contour per 8-connected component; keep the longest
            perim[j] = p
            a = cv2.contourArea(c)
            circ[j] = min(1.0, 4 * np.pi * a / (p * p)) if p > 0 else 0.0

    split_set = set(split)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    for c in contours:
        j = labels[c[0, 0, 1], c[0, 0, 0]]
        if wanted[j] and j not in split_set:
            take(c, j)
    for j in split:
        if wanted[j]:
            for c in cv2.findContours((labels == j).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]:
                take(c, j)
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
