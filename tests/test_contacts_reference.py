"""runtime/stages/contacts.py gives exactly the clusters of the contacts rule written the plain way
(`reference_clusters` below: every step on the whole image, one np.bincount per quantity, a Python
loop per component and per label, no shortcut), for many fields — one press, two presses joined
above the threshold, light touches, a sliding contact split in two, noise on the gel's rim, many weak
pixels, touches at the image border, random ones — under several ContactConfig settings; and
hand-worked values for its small helpers."""
from dataclasses import replace

import cv2
import numpy as np
import pytest
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.stages.contacts import (
    Cluster,
    ContactConfig,
    ContactTracker,
    _label_sums,
    _max_per_label,
    _work_box,
    find_clusters,
    force_magnitude,
    merge_bridged,
    pixel_forces,
    split_peaks,
)
from tensortouch.runtime.stages.geometry import DomeProfile, equidistant_theta_phi, surface_tables

# ------------------------------------------------------------------------------------------- reference


def reference_clusters(force_px, surface_xyz, normals, pixel_area, mask, disp=None, cfg=ContactConfig()):
    """The contacts rule of docs/runtime.md, plainly: untracked clusters in label order."""
    h, w = mask.shape
    fx, fy, fz = force_px[0], force_px[1], force_px[2]
    mag = np.sqrt(fx * fx + fy * fy + fz * fz)
    binary = ((mag > cfg.threshold_n) & mask).astype(np.uint8)
    # light touches: a component above the weak threshold holding no strong pixel whose |total force|
    # reaches min_total_n is a core
    if not (cfg.weak_threshold_n <= 0 or cfg.min_total_n <= 0 or cfg.weak_threshold_n >= cfg.threshold_n):
        nw, weak = cv2.connectedComponents(((mag > cfg.weak_threshold_n) & mask).astype(np.uint8), connectivity=8)
        idx = np.flatnonzero(weak)
        lab = weak.ravel()[idx]
        tot = np.linalg.norm(np.stack([np.bincount(lab, weights=force_px[i].ravel()[idx], minlength=nw)
                                       for i in range(3)], 1), axis=1)
        light = np.zeros_like(binary)
        for j in range(1, nw):
            part = weak == j
            if not binary[part].any() and tot[j] >= cfg.min_total_n:
                light[part] = 1
        binary = binary | light
    if not binary.any():
        return []
    n, labels = cv2.connectedComponents(binary, connectivity=8)
    # merging: cores joined by a path above merge_n are one cluster, numbered in the order of those paths
    joined = np.zeros(n, bool)
    if n > 2 and cfg.merge_n > 0:
        _, bridged = cv2.connectedComponents((((mag > cfg.merge_n) & mask) | (binary > 0)).astype(np.uint8),
                                             connectivity=8)
        of = [int(bridged[labels == j][0]) for j in range(1, n)]
        comps = sorted(set(of))
        new = np.zeros_like(labels)
        for j, b in enumerate(of, 1):
            new[labels == j] = comps.index(b) + 1
        joined = np.array([False] + [of.count(b) > 1 for b in comps])
        labels, n = new, len(comps) + 1
    # splitting: a core's significant peaks each seed a cluster; the rest of the core goes to the nearest seed
    split = []
    if 0.0 < cfg.split_dip < 1.0:
        dil = cv2.dilate(mag, np.ones((3, 3), np.uint8))
        out = labels.copy()
        for j in range(1, n):
            whole = labels == j
            pv, pu = np.nonzero((mag >= dil) & whole)
            if joined[j] or len(pv) < 2:
                continue
            rows, cols = np.nonzero(whole)
            r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
            m, core = mag[r0:r1, c0:c1], whole[r0:r1, c0:c1]
            seeds = []
            for i in sorted(range(len(pv)), key=lambda i: -mag[pv[i], pu[i]]):
                v, u = pv[i] - r0, pu[i] - c0
                p = float(m[v, u])
                if any(s[v, u] for s in seeds):
                    continue
                _, cl = cv2.connectedComponents(((m > (1.0 - cfg.split_dip) * p) & core).astype(np.uint8),
                                                connectivity=8)
                part = cl == cl[v, u]
                if seeds and float(m[part].max()) > p:
                    continue
                seeds.append(part)
            if len(seeds) < 2:
                continue
            marker = np.zeros(m.shape, np.int32)
            for s_i, s in enumerate(seeds):
                marker[s] = s_i + 1
            _, nearest = cv2.distanceTransformWithLabels((marker == 0).astype(np.uint8), cv2.DIST_L2, 5,
                                                         labelType=cv2.DIST_LABEL_PIXEL)
            seed_of = np.concatenate([[0], marker[marker > 0]])[nearest]
            ids = [0, j] + list(range(n, n + len(seeds) - 1))
            sub = out[r0:r1, c0:c1]
            for s_i in range(1, len(seeds) + 1):
                sub[core & (seed_of == s_i)] = ids[s_i]
            split += [j] + ids[2:]
            n += len(seeds) - 1
        labels = out
    # support: every pixel above the floor within the radius of a core joins its nearest core pixel's cluster
    support = labels
    if cfg.support_radius_px > 0:
        dist, nearest = cv2.distanceTransformWithLabels((labels == 0).astype(np.uint8), cv2.DIST_L2, 5,
                                                        labelType=cv2.DIST_LABEL_PIXEL)
        grown = np.concatenate([[0], labels[labels > 0]])[nearest]
        support = np.where((labels > 0) | ((mag > cfg.support_floor_n) & (dist <= cfg.support_radius_px)), grown, 0)
    ci = np.flatnonzero(labels)
    pixels = np.bincount(labels.ravel()[ci], minlength=n)
    area = np.bincount(labels.ravel()[ci], weights=pixel_area.ravel()[ci], minlength=n)
    idx = np.flatnonzero(support)
    lab = support.ravel()[idx]
    wgt = mag.ravel()[idx]
    rows, cols = np.divmod(idx, w)

    def total(values):
        return np.bincount(lab, weights=values, minlength=n)

    wsum = total(wgt)
    safe = np.where(wsum > 0, wsum, 1.0)
    pos = surface_xyz.reshape(-1, 3)[idx]
    nrm = normals.reshape(-1, 3)[idx]
    indent = np.zeros(n)
    if disp is not None:
        d = disp.reshape(3, -1)[:, idx].T
        pos = pos + d
        np.maximum.at(indent, lab, -np.einsum("ij,ij->i", d, nrm))
    uv = np.stack([total(wgt * (cols + 0.5)), total(wgt * (rows + 0.5))], 1) / safe[:, None]
    centroid = np.stack([total(wgt * pos[:, i]) for i in range(3)], 1) / safe[:, None]
    nsum = np.stack([total(wgt * nrm[:, i]) for i in range(3)], 1) / safe[:, None]
    nsum /= np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-12)
    fvec = np.stack([total(force_px[i].ravel()[idx]) for i in range(3)], 1)
    # shape: the longest external contour of the label's components (of a split label's own pixels)
    perim, circ = np.zeros(n), np.zeros(n)
    contours = [(c, labels[c[0, 0, 1], c[0, 0, 0]]) for c in
                cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]]
    contours = [(c, j) for c, j in contours if j not in split]
    for j in split:
        contours += [(c, j) for c in cv2.findContours((labels == j).astype(np.uint8), cv2.RETR_EXTERNAL,
                                                      cv2.CHAIN_APPROX_NONE)[0]]
    for c, j in contours:
        p = cv2.arcLength(c, True)
        if p > perim[j]:
            perim[j] = p
            circ[j] = min(1.0, 4 * np.pi * cv2.contourArea(c) / (p * p)) if p > 0 else 0.0
    return [Cluster(id=-1, uv_px=(float(uv[j, 0]), float(uv[j, 1])), position_mm=tuple(map(float, centroid[j])),
                    normal=tuple(map(float, nsum[j])), area_mm2=float(area[j]), force_n=tuple(map(float, fvec[j])),
                    force_mag_n=float(np.linalg.norm(fvec[j])), pixels=int(pixels[j]), perimeter_px=float(perim[j]),
                    circularity=float(circ[j]), indentation_mm=float(indent[j]))
            for j in range(1, n) if pixels[j] >= cfg.min_pixels]


# ------------------------------------------------------------------------------------------------ fields

PACKAGE = ContactConfig(threshold_n=0.0015, weak_threshold_n=0.0006, min_total_n=0.06356, support_radius_px=20.0,
                        support_floor_n=0.0, merge_n=0.0012, split_dip=0.5)
CONFIGS = {
    "package": PACKAGE,
    "student threshold": replace(PACKAGE, threshold_n=0.00125),
    "defaults": ContactConfig(),
    "no support, specks kept": replace(PACKAGE, support_radius_px=0.0, min_pixels=1),
    "floor and radius 6": replace(PACKAGE, support_floor_n=0.0002, support_radius_px=6.0),
    "split without merging": replace(PACKAGE, merge_n=0.0, split_dip=0.3),
    "deep split, low thresholds": ContactConfig(threshold_n=0.0009, weak_threshold_n=0.0004, min_total_n=0.02,
                                                merge_n=0.0007, split_dip=0.8, support_radius_px=10.0),
    "light rule only": ContactConfig(threshold_n=0.002, weak_threshold_n=0.0006, min_total_n=0.04),
}


@pytest.fixture(scope="module")
def demo_cal():
    return CalibrationStore().load("TWIN-DEMO")


def small_dome(size=64):
    """A 64² nominal dome whose mask covers the whole image (cores on the image border)."""
    th, ph = equidistant_theta_phi((size, size), np.deg2rad(100))
    t = surface_tables(th, ph, DomeProfile(radius_mm=16.0))
    return {"surface_xyz": t["surface_xyz"], "normals": t["normals"], "pixel_area": t["pixel_area"],
            "mask": np.ones((size, size), bool)}


def touches(geo, spots, noise_n=2e-4, seed=0, dtype=np.float32):
    """(3, H, W) force per pixel (N): Gaussian presses [(u, v, |F| N, σ px)] into the gel plus noise."""
    h, w = geo["mask"].shape
    yy, xx = np.mgrid[0:h, 0:w]
    rng = np.random.default_rng(seed)
    fp = np.zeros((3, h, w))
    nrm = np.moveaxis(geo["normals"], -1, 0)
    for u, v, f, s in spots:
        g = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * s * s))
        fp -= f * g / g.sum() * nrm
    fp += rng.normal(0.0, noise_n, fp.shape)
    return fp.astype(dtype)


def rim_noise(geo, count=25, level=(0.0010, 0.0020), noise_n=2e-4, seed=0):
    """Noise plus `count` pixels on the mask's rim reading `level` N each (a network's rest-frame rim)."""
    mask = geo["mask"]
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    rim = np.argwhere(mask & ~inner.astype(bool))
    rng = np.random.default_rng(seed)
    fp = touches(geo, [], noise_n, seed)
    for v, u in rim[rng.choice(len(rim), count, replace=False)]:
        fp[:, v, u] = np.float32(rng.uniform(*level)) * np.array([0.3, 0.2, -0.93], np.float32)
    return fp


def displacement(geo, seed=0):
    h, w = geo["mask"].shape
    return (np.random.default_rng(seed + 100).normal(0.0, 0.05, (3, h, w))).astype(np.float32)


def structured(geo):
    """name → (3, H, W) force per pixel: the cases the rules were written for."""
    h, w = geo["mask"].shape
    return {
        "one press": touches(geo, [(0.3 * w, 0.5 * h, 1.5, 4.0)]),
        "press and light touch": touches(geo, [(0.3 * w, 0.5 * h, 1.5, 4.0), (0.7 * w, 0.47 * h, 0.2, 5.5)], seed=1),
        "two presses joined": touches(geo, [(0.5 * w - 11, 0.5 * h, 4.0, 6.0), (0.5 * w + 11, 0.5 * h, 3.0, 6.0)],
                                      seed=2),
        "three presses joined": touches(geo, [(0.45 * w - 10, 0.42 * h, 3.0, 5.0), (0.45 * w + 10, 0.42 * h, 2.5, 5.0),
                                              (0.45 * w, 0.42 * h + 17.4, 2.0, 5.0)], seed=3),
        "sliding contact split": touches(geo, [(0.45 * w, 0.5 * h, 1.0, 2.0), (0.45 * w + 12, 0.5 * h, 0.6, 2.0),
                                               (0.45 * w + 6, 0.5 * h, 0.045, 3.0)], seed=4),
        "rim noise": rim_noise(geo, seed=5),
        "press and rim noise": rim_noise(geo, seed=6) + touches(geo, [(0.6 * w, 0.4 * h, 2.0, 5.0)], 0.0),
        "many weak pixels": touches(geo, [(0.5 * w, 0.5 * h, 0.8, 6.0)], noise_n=6e-4, seed=7),
        "rest": touches(geo, [], seed=8),
        "border and corner": touches(geo, [(0, 0, 1.0, 3.0), (w - 1, 0.5 * h, 1.5, 4.0), (0.5 * w, h - 1, 0.4, 6.0)],
                                     seed=9),
    }


def random_field(geo, seed):
    rng = np.random.default_rng(seed)
    h, w = geo["mask"].shape
    spots = [(rng.uniform(-3, w + 2), rng.uniform(-3, h + 2), rng.uniform(0.05, 4.0), rng.uniform(1.0, 7.0))
             for _ in range(rng.integers(0, 5))]
    fp = touches(geo, spots, noise_n=rng.choice([1e-4, 3e-4, 6e-4]), seed=seed)
    if rng.random() < 0.3:
        fp = fp + rim_noise(geo, count=int(rng.integers(5, 40)), noise_n=0.0, seed=seed)
    return fp


def same(got, want):
    return [c.to_dict() for c in got] == [c.to_dict() for c in want]


# ---------------------------------------------------------------------------------------- equal outputs


def _cases(cal):
    return {"demo": {"surface_xyz": cal.surface_xyz, "normals": cal.normals, "pixel_area": cal.pixel_area,
                     "mask": cal.mask}, "small": small_dome()}


@pytest.mark.parametrize("config", list(CONFIGS))
def test_structured_fields_give_the_reference_clusters(demo_cal, config):
    cfg = CONFIGS[config]
    found = 0
    for geo_name, geo in _cases(demo_cal).items():
        args = (geo["surface_xyz"], geo["normals"], geo["pixel_area"], geo["mask"])
        for name, fp in structured(geo).items():
            for disp in (None, displacement(geo)):
                want = reference_clusters(fp, *args, disp=disp, cfg=cfg)
                assert same(find_clusters(fp, *args, disp=disp, cfg=cfg), want), (geo_name, name)
                found += len(want)
    assert found > 20


def test_the_structured_fields_exercise_every_rule(demo_cal):
    """The comparison above covers splitting, merging, light touches and specks, not only plain cores."""
    geo = _cases(demo_cal)["demo"]
    args = (geo["surface_xyz"], geo["normals"], geo["pixel_area"], geo["mask"])
    f = structured(geo)

    def count(name, cfg):
        return len(reference_clusters(f[name], *args, cfg=cfg))

    assert count("two presses joined", PACKAGE) == 2 and count("two presses joined", replace(PACKAGE, split_dip=0)) == 1
    assert count("three presses joined", PACKAGE) == 3 and count("three presses joined", replace(PACKAGE, split_dip=0)) == 1
    merging = ContactConfig(merge_n=0.0012)
    assert count("sliding contact split", merging) == 1 and count("sliding contact split", ContactConfig()) == 2
    assert count("press and light touch", CONFIGS["light rule only"]) == 2
    assert count("press and light touch", ContactConfig()) == 1
    assert count("rim noise", CONFIGS["no support, specks kept"]) > 3


@pytest.mark.parametrize("config", list(CONFIGS))
def test_random_fields_give_the_reference_clusters(demo_cal, config):
    cfg = CONFIGS[config]
    for geo_name, geo in _cases(demo_cal).items():
        args = (geo["surface_xyz"], geo["normals"], geo["pixel_area"], geo["mask"])
        for seed in range(25):
            fp = random_field(geo, seed)
            disp = displacement(geo, seed) if seed % 2 else None
            assert same(find_clusters(fp, *args, disp=disp, cfg=cfg),
                        reference_clusters(fp, *args, disp=disp, cfg=cfg)), (geo_name, seed)


def test_float64_forces_and_one_opencv_thread_give_the_reference_clusters(demo_cal):
    """The runtime runs OpenCV on one thread, the tests on the default: the same labels either way."""
    geo = _cases(demo_cal)["demo"]
    args = (geo["surface_xyz"], geo["normals"], geo["pixel_area"], geo["mask"])
    threads = cv2.getNumThreads()
    try:
        for t in (1, threads):
            cv2.setNumThreads(t)
            for seed in range(10):
                fp = random_field(geo, 100 + seed).astype(np.float64)
                for cfg in (PACKAGE, CONFIGS["deep split, low thresholds"]):
                    assert same(find_clusters(fp, *args, cfg=cfg), reference_clusters(fp, *args, cfg=cfg)), seed
    finally:
        cv2.setNumThreads(threads)


def test_tracked_ids_over_a_sliding_press_match_the_reference(demo_cal):
    geo = _cases(demo_cal)["demo"]
    args = (geo["surface_xyz"], geo["normals"], geo["pixel_area"], geo["mask"])
    new, ref = ContactTracker(PACKAGE), ContactTracker(PACKAGE)
    for k in range(30):
        fp = touches(geo, [(20 + k, 70, 2.0, 4.0), (95, 20 + k, 1.0 + 0.1 * k, 5.0)], seed=k)
        if k % 7 == 3:
            fp = rim_noise(geo, seed=k) + fp
        got = new.update(find_clusters(fp, *args, cfg=PACKAGE))
        want = ref.update(reference_clusters(fp, *args, cfg=PACKAGE))
        assert same(got, want), k
    assert {c.id for c in got} == {0, 1}


# --------------------------------------------------------------------------------------- small helpers


def test_pixel_forces_and_magnitude_hand_values():
    f = np.zeros((15, 2, 2), np.float32)
    f[9:12, 0, 0] = (1.0, 2.0, 4.0)
    f[12:15, 0, 0] = (2.0, 2.0, 8.0)            # normal + shear = (3, 4, 12)
    fp = pixel_forces(f, np.full((2, 2), 0.5, np.float32))
    assert fp.dtype == np.float32 and fp[:, 0, 0].tolist() == [1.5, 2.0, 6.0]
    assert pixel_forces(f, np.full((2, 2), 0.5)).dtype == np.float64     # promoted as before, not in place
    mag = force_magnitude(fp)
    assert mag.dtype == np.float32 and mag[0, 0] == 6.5 and mag[1, 1] == 0.0
    assert np.array_equal(f[9:12, 0, 0], [1.0, 2.0, 4.0])                 # the fields are left as they were


def test_work_box_grows_one_pixel_from_an_even_corner():
    mag = np.zeros((10, 12), np.float32)
    mask = np.ones((10, 12), bool)
    cfg = ContactConfig(threshold_n=0.002)
    assert _work_box(mag, mask, cfg) is None
    mag[3, 5] = 0.003
    assert _work_box(mag, mask, cfg) == (2, 5, 4, 7)           # rows 2..4, columns 4..6 (3-1=2, 5-1=4)
    mag[6, 8] = 0.003
    assert _work_box(mag, mask, cfg) == (2, 8, 4, 10)
    mag[9, 11] = 0.001                                          # weak: counts only with the light-touch rule
    assert _work_box(mag, mask, cfg) == (2, 8, 4, 10)
    assert _work_box(mag, mask, replace(cfg, weak_threshold_n=0.0005, min_total_n=0.1)) == (2, 10, 4, 12)
    assert _work_box(mag, mask, replace(cfg, merge_n=0.0005)) == (2, 10, 4, 12)
    mag[0, 1] = 0.003
    assert _work_box(mag, mask, cfg) == (0, 8, 0, 10)
    mask[0, 1] = False                                          # masked pixels do not count
    assert _work_box(mag, mask, cfg) == (2, 8, 4, 10)


def test_label_sums_add_pixel_after_pixel_like_bincount():
    # 1e16 + 1 rounds back to 1e16, so the pixels' order decides: 0 in this order, 1 by another
    values = np.array([[1e16, 5.0, 1.0, 7.0, -1e16, 2.0],
                       [0.5, 0.0, 0.25, -0.0, 1.0, 3.0]])
    lab = np.array([1, 2, 1, 2, 1, 3])
    got = _label_sums(values, lab, 4)
    assert got.tolist() == [[0.0, 0.0], [0.0, 1.75], [12.0, 0.0], [2.0, 3.0]]
    for i in range(2):
        assert got[:, i].tolist() == np.bincount(lab, weights=values[i], minlength=4).tolist()
    one = _label_sums(np.array([[1e16, 1.0, -1e16], [0.5, 0.25, -0.0]]), np.ones(3, int), 2)
    assert one.tolist() == [[0.0, 0.0], [0.0, 0.75]]
    assert _label_sums(np.array([[1e16, 1.0, -1e16]]), np.ones(3, int), 2).tolist() == [[0.0], [0.0]]


def test_label_sums_equal_bincount_on_wide_ranging_values():
    rng = np.random.default_rng(0)
    for n in (1, 2, 7, 8, 9, 16, 17, 100, 3000):
        values = rng.normal(size=(12, n)) * np.exp(rng.normal(size=(12, n)) * 8)
        for k in (2, 3, 6, 40):
            lab = rng.integers(1, k, n)
            got = _label_sums(values, lab, k)
            want = np.stack([np.bincount(lab, weights=v, minlength=k) for v in values], 1)
            assert np.array_equal(got, want), (n, k)


def test_max_per_label_hand_values():
    out = np.zeros(4)
    _max_per_label(out, np.array([1, 3, 1, 3, 3]), np.array([-1.0, 2.0, -0.5, 5.0, 1.0]))
    assert out.tolist() == [0.0, 0.0, 0.0, 5.0]                 # label 1's maxima are below the 0 it starts at
    out = np.full(2, -np.inf)
    _max_per_label(out, np.array([1, 1]), np.array([-1.0, -0.5]))
    assert out.tolist() == [-np.inf, -0.5]


def test_merge_bridged_hand_case():
    binary = np.zeros((3, 9), np.uint8)
    binary[1, [0, 4, 8]] = 1                                     # three single-pixel cores
    mag = np.zeros((3, 9), np.float32)
    mag[1, :] = [5, 1, 1, 1, 5, 0, 0, 0, 5]                      # the first two bridged at 1, the third not
    mag[binary > 0] = 5
    n, labels = cv2.connectedComponents(binary, connectivity=8)
    assert n == 4
    new, n2, joined = merge_bridged(labels, n, binary, mag, np.ones((3, 9), bool), 0.5)
    assert n2 == 3 and new[1].tolist() == [1, 0, 0, 0, 1, 0, 0, 0, 2] and joined.tolist() == [False, True, False]


def test_split_peaks_hand_case():
    # one core along a row: 10, 6, 4, 3, 9. At dip 0.5 the peak 9 is cut off from 10 below 4.5 (the
    # 3 and 4 between them), so it seeds a cluster; 10's part is {10, 6}; 4 goes to 6, 3 to 9.
    mag = np.zeros((3, 7), np.float32)
    mag[1, 1:6] = [10, 6, 4, 3, 9]
    labels = (mag > 0).astype(np.int32)
    new, n, split = split_peaks(labels, 2, mag, 0.5)
    assert n == 3 and split == (1, 2) and new[1].tolist() == [0, 1, 1, 1, 2, 2, 0]
    # at dip 0.8 the level of 9 is 1.8: its part holds the 10, so one cluster
    same_labels, n, split = split_peaks(labels, 2, mag, 0.8)
    assert n == 2 and split == () and np.array_equal(same_labels, labels)
    # a label merging joined stays whole
    assert split_peaks(labels, 2, mag, 0.5, keep=np.array([False, True]))[1] == 2
