"""The contact clustering and the fields encoder as they were before the speed work of issue #44
(2026-11-28), frozen. `tensortouch bench runtime` times them beside the current runtime/stages/contacts.py
and contracts/wire.encode_fields on the same fields (the stage ratios), and tests/test_contacts_speed.py
checks that the current ones give exactly their results. Benchmark reference only: nothing else runs it."""
from __future__ import annotations

import cv2
import numpy as np

from ...runtime.stages.contacts import Cluster, ContactConfig


def find_clusters(force_px: np.ndarray, surface_xyz: np.ndarray, normals: np.ndarray,
                  pixel_area: np.ndarray, mask: np.ndarray, disp: np.ndarray | None = None,
                  cfg: ContactConfig = ContactConfig()) -> list[Cluster]:
    """Untracked clusters (id = -1) of one frame, in label order."""
    mag = np.sqrt((force_px ** 2).sum(axis=0))
    binary = ((mag > cfg.threshold_n) & mask).astype(np.uint8)
    light = light_cores(force_px, mag, mask, binary, cfg)
    if light is not None:
        binary = binary | light
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    if n <= 1:
        return []
    if n > 2 and cfg.merge_n > 0:
        labels, n, stats = merge_bridged(labels, binary, mag, mask, cfg.merge_n)
    k = n
    support = _support_labels(labels, mag, cfg)
    idx = np.flatnonzero(support)                 # only pixels that belong to some cluster
    lab = support.ravel()[idx]
    w = mag.ravel()[idx]
    wsum = np.bincount(lab, weights=w, minlength=k)
    safe = np.where(wsum > 0, wsum, 1.0)
    wd = mag.shape[1]
    vv, uu = np.divmod(idx, wd)

    def wmean(values):  # force-weighted mean per cluster of (len(idx), ...) values
        values = values.reshape(len(idx), -1)
        return np.stack([np.bincount(lab, weights=w * values[:, i], minlength=k)
                         for i in range(values.shape[1])], 1) / safe[:, None]

    uv = wmean(np.stack([uu + 0.5, vv + 0.5], 1))
    pos = surface_xyz.reshape(-1, 3)[idx]
    indent = np.zeros(k)
    if disp is not None:
        d = disp.reshape(3, -1)[:, idx].T
        pos = pos + d
        # the indenter's depth: the cluster's deepest point, not its force-weighted centroid
        np.maximum.at(indent, lab, -np.einsum("ij,ij->i", d, normals.reshape(-1, 3)[idx]))
    centroid = wmean(pos)
    nsum = wmean(normals.reshape(-1, 3)[idx])
    nsum /= np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-12)
    fvec = np.stack([np.bincount(lab, weights=force_px[i].ravel()[idx], minlength=k) for i in range(3)], 1)
    core = labels.ravel()
    area = np.bincount(core, weights=pixel_area.ravel(), minlength=k)
    perim, circ = _shape_metrics(binary, labels, k)
    out = []
    for j in range(1, k):
        if stats[j, cv2.CC_STAT_AREA] < cfg.min_pixels:
            continue
        out.append(Cluster(
            id=-1, uv_px=(float(uv[j, 0]), float(uv[j, 1])), position_mm=tuple(map(float, centroid[j])),
            normal=tuple(map(float, nsum[j])), area_mm2=float(area[j]), force_n=tuple(map(float, fvec[j])),
            force_mag_n=float(np.linalg.norm(fvec[j])), pixels=int(stats[j, cv2.CC_STAT_AREA]),
            perimeter_px=float(perim[j]), circularity=float(circ[j]), indentation_mm=float(indent[j])))
    return out


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
    labels, tot = weak_components(force_px, mag, mask, strong, cfg.weak_threshold_n)
    keep = tot >= cfg.min_total_n
    return keep[labels].astype(np.uint8) if keep.any() else None


def _support_labels(labels: np.ndarray, mag: np.ndarray, cfg: ContactConfig) -> np.ndarray:
    """Core labels grown onto weaker nearby pixels (nearest core pixel within the support radius),
    so a cluster's force includes the tails the detection threshold cuts off."""
    if cfg.support_radius_px <= 0:
        return labels
    dist, nearest = cv2.distanceTransformWithLabels((labels == 0).astype(np.uint8), cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
    flat = labels.ravel()
    by_seed = np.concatenate([[0], flat[flat > 0]])  # DIST_LABEL_PIXEL numbers core pixels in raster order
    grown = by_seed[nearest]
    keep = (labels > 0) | ((mag > cfg.support_floor_n) & (dist <= cfg.support_radius_px))
    return np.where(keep, grown, 0).astype(np.int32)


def _shape_metrics(binary: np.ndarray, labels: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Perimeter (contour length, px) and circularity 4πA/P² per label (1 for a disc)."""
    perim = np.zeros(k)
    circ = np.zeros(k)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    for c in contours:
        x, y = c[0, 0]
        j = labels[y, x]
        p = cv2.arcLength(c, True)
        a = cv2.contourArea(c)
        if p > perim[j]:  # one external contour per 8-connected component; keep the longest
            perim[j] = p
            circ[j] = min(1.0, 4 * np.pi * a / (p * p)) if p > 0 else 0.0
    return perim, circ


# ---------------------------------------------------------------- the fields encoder before the speed work

def encode_fields(fields, seq, t, sensor_id):
    """contracts/wire.encode_fields as it was (default channels), frozen: the payload reference."""
    from ...contracts import wire, wire_keys

    arr = np.asarray(fields)
    half = wire.to_float16(arr)
    bits = half.view(np.uint16)
    nan = (bits & 0x7FFF) > 0x7C00
    if nan.any():
        bad = nan.reshape(nan.shape[0], -1).any(axis=1)
        raise wire.WireError(f"fields: NaN in channel(s) {[n for n, b in zip(wire.CHANNELS, bad) if b]} cannot be sent")
    over = (bits & 0x7FFF) == 0x7C00
    clipped = ()
    if over.any():
        bad = over.reshape(over.shape[0], -1).any(axis=1)
        clipped = tuple(name for name, b in zip(wire.CHANNELS, bad) if b)
        bits[over] = (bits[over] & 0x8000) | 0x7BFF
    header = {"schema": wire.SCHEMAS["fields"], "sensor_id": wire.check_sensor_id(sensor_id), "seq": int(seq),
              "t": float(t), "shape": list(arr.shape), "dtype": wire.FIELDS_DTYPE,
              "channels": list(wire.CHANNELS), "units": list(wire.CHANNEL_UNITS), "clipped": list(clipped)}
    return half.tobytes(), wire_keys.dumps(header), clipped


def contact_stage(fields, cal, cfg: ContactConfig) -> list[Cluster]:
    """runtime.pipeline.contact_stage with the clustering above."""
    from ...runtime.stages.contacts import pixel_forces

    fp = pixel_forces(fields, cal.pixel_area)
    return find_clusters(fp, cal.surface_xyz, cal.normals, cal.pixel_area, cal.mask, disp=fields[0:3], cfg=cfg)
