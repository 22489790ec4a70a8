"""Dataset directory contract (docs/train.md) and a synthetic-field generator for tests/benchmarks.

```
<dataset>/
  index.json        {"schema": "tensortouch.dataset", "schema_version": 1, "size": [H, W],
                     "input_channels": [...6], "output_channels": [...15], "source": "...",
                     "samples": [{"file": "samples/000000.npz", "sha256": "...", "split": "train"}]}
  bounds.json       per-channel [lo, hi] (tools.train.fields.write_bounds)
  samples/*.npz     input uint8 (6, H, W) baseline RGB + current RGB; target float32 (15, H, W) in [0, 1]
```
The dataset hash recorded in model manifests is the SHA-256 of index.json (which lists every sample's
SHA-256). The synthetic generator is NOT physics: image-space contacts whose 15 channels are smooth,
distinct functions of the contact parameters, and whose "current" image is the baseline warped by the
displacement and shaded by its slope — enough structure to exercise training, export and
quantization; every figure made with it says so.
"""
from __future__ import annotations

import hashlib
import io
import json
import logging
from pathlib import Path

import numpy as np
from scipy import ndimage

from ....contracts.errors import TensorTouchError
from ....contracts.fields import CHANNELS, INPUT_CHANNELS, N_CHANNELS
from ....contracts.files import atomic_write, finish_partial, partial_path

log = logging.getLogger(__name__)
SCHEMA = "tensortouch.dataset"


class DatasetError(TensorTouchError):
    """A dataset directory violates the dataset contract."""



def write_sample(root: Path, i: int, inp: np.ndarray, target: np.ndarray, compress: bool = True) -> dict:
    """Write samples/<i>.npz atomically; returns its index entry (without split). `compress` = False stores
    the arrays as they are (a distilled set's dense teacher targets compress little and slowly)."""
    if inp.dtype != np.uint8 or inp.shape[0] != 6 or target.shape != (N_CHANNELS,) + inp.shape[1:]:
        raise DatasetError(f"sample {i}: input must be uint8 (6,H,W) and target (15,H,W); got "
                           f"{inp.dtype}{inp.shape} and {target.shape}")
    buf = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buf, input=inp, target=target.astype(np.float32))
    rel = f"samples/{i:06d}.npz"
    data = buf.getvalue()
    atomic_write(Path(root) / rel, data)
    return {"file": rel, "sha256": hashlib.sha256(data).hexdigest()}


def write_index(root: Path, entries: list[dict], size: tuple[int, int], source: str) -> str:
    doc = {"schema": SCHEMA, "schema_version": 1, "size": list(size), "input_channels": list(INPUT_CHANNELS),
           "output_channels": list(CHANNELS), "source": source, "samples": entries}
    data = json.dumps(doc, indent=1).encode()
    atomic_write(Path(root) / "index.json", data)
    return hashlib.sha256(data).hexdigest()


def read_index(root: str | Path) -> dict:
    path = Path(root) / "index.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot read dataset index ({exc})") from None
    if doc.get("schema") != SCHEMA or doc.get("output_channels") != list(CHANNELS):
        raise DatasetError(f"{path}: schema must be {SCHEMA!r} with output_channels in docs/fields.md order")
    return doc


def data_hash(root: str | Path) -> str:
    return hashlib.sha256((Path(root) / "index.json").read_bytes()).hexdigest()


def load_sample(root: Path, entry: dict) -> tuple[np.ndarray, np.ndarray]:
    path = Path(root) / entry["file"]
    try:
        with np.load(path, allow_pickle=False) as z:
            return z["input"], z["target"]
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(f"{path}: unreadable sample ({exc})") from None


def spread_indices(count: int, n: int | None) -> list[int]:
    """`n` indices spread evenly over range(count), first and last included (all when n >= count)."""
    if n is None or n >= count:
        return list(range(count))
    if n <= 0:
        return []
    return sorted(set(np.linspace(0, count - 1, n).round().astype(int).tolist()))


def load_split(root: str | Path, split: str | None = None, limit: int | None = None,
               spread: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """All samples of a split as (N, 6, H, W) uint8 and (N, 15, H, W) float32 arrays: the first
    `limit` of them, or with `spread` `limit` samples spread evenly over the whole split (every unit
    and loading kind of a dataset written session by session, e.g. for the int8 quantization samples)."""
    doc = read_index(root)
    entries = [e for e in doc["samples"] if split is None or e.get("split") == split]
    entries = [entries[i] for i in spread_indices(len(entries), limit)] if spread else entries[:limit]
    if not entries:
        raise DatasetError(f"{Path(root) / 'index.json'}: no samples in split {split!r}")
    # filled in place: a list of samples + np.stack would hold every sample twice at the peak (a 15k-sample
    # 128² set is 15 GB of float32 targets once)
    return _fill(Path(root), entries, lambda shape, dtype: np.empty(shape, dtype))


def _fill(root: Path, entries: list[dict], alloc) -> tuple[np.ndarray, np.ndarray]:
    """The samples of `entries` written into two arrays `alloc(shape, dtype)` gives (inputs, targets)."""
    x0, y0 = load_sample(root, entries[0])
    x, y = alloc((len(entries), *x0.shape), x0.dtype), alloc((len(entries), *y0.shape), y0.dtype)
    x[0], y[0] = x0, y0
    for i, e in enumerate(entries[1:], 1):
        xi, yi = load_sample(root, e)
        if xi.shape != x0.shape or yi.shape != y0.shape:
            raise DatasetError(f"{root / e['file']}: sample shapes {xi.shape}, {yi.shape}; the first sample "
                               f"of the split has {x0.shape}, {y0.shape}")
        x[i], y[i] = xi, yi
    return x, y


def stacked_split(root: str | Path, split: str) -> tuple[np.ndarray, np.ndarray]:
    """`load_split(root, split)` as read-only memory maps of two .npy files under `<root>/stack/`, written once
    per dataset (named by its index hash) and reused: fits of one dataset running side by side share its pages
    instead of each holding a copy (a 11k-sample 128² set is 12 GB). The values and order are load_split's."""
    import fcntl

    root = Path(root)
    key = data_hash(root)[:16]
    folder = root / "stack"
    paths = [folder / f"{split}-{key}-{part}.npy" for part in ("input", "target")]
    folder.mkdir(exist_ok=True)
    with open(folder / f".{split}.lock", "a") as lock:        # two fits starting at once write it once
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not all(p.is_file() for p in paths):
            doc = read_index(root)
            entries = [e for e in doc["samples"] if e.get("split") == split]
            if not entries:
                raise DatasetError(f"{root / 'index.json'}: no samples in split {split!r}")
            for old in folder.glob(f"{split}-*.npy"):           # an earlier version of the dataset
                old.unlink()
            targets = iter(partial_path(p) for p in paths)      # input first, then target: _fill's order
            arrays = list(_fill(root, entries, lambda shape, dtype: np.lib.format.open_memmap(
                next(targets), "w+", dtype, shape)))
            for a in arrays:
                a.flush()
            arrays.clear()
            for p in paths:
                finish_partial(partial_path(p), p)
    return tuple(np.load(p, mmap_mode="r") for p in paths)


def load_measured(root: str | Path, split: str | None = None, limit: int | None = None,
                  contacts: bool = False) -> np.ndarray:
    """(N, 3) float32: the rig's measured total force (N) of a split's samples, in `load_split`'s order
    (index entries' `force_n`, written by a distilled dataset); DatasetError when a sample has none. With
    `contacts`, (N, 13): the total, then the two indenters' [fx, fy, fz, u, v] of a sample where two press
    at once (`contacts_n`, distill.contact_pixels), NaN elsewhere."""
    doc = read_index(root)
    entries = [e for e in doc["samples"] if split is None or e.get("split") == split][:limit]
    out = np.full((len(entries), 13 if contacts else 3), np.nan, np.float32)
    for i, e in enumerate(entries):
        f = e.get("force_n")
        if not (isinstance(f, list) and len(f) == 3 and all(isinstance(v, (int, float)) and np.isfinite(v) for v in f)):
            raise DatasetError(f"{Path(root) / 'index.json'}: sample {e.get('file')} has no measured force "
                               "(force_n: 3 finite numbers); rebuild the dataset (a distilled build records it)")
        out[i, :3] = f
        two = e.get("contacts_n") if contacts else None
        if two is not None:
            a = np.asarray(two, float) if isinstance(two, list) else np.zeros(0)
            if a.shape != (2, 5) or not np.isfinite(a).all():
                raise DatasetError(f"{Path(root) / 'index.json'}: sample {e.get('file')}: contacts_n must be two "
                                   f"[fx, fy, fz, u, v] of finite numbers, got {two!r}"[:300])
            out[i, 3:] = a.ravel()
    return out


# ---------------------------------------------------------------- synthetic fields (not physics)

def _baseline(size: int, rng: np.random.Generator) -> np.ndarray:
    yy, xx = (np.mgrid[0:size, 0:size] + 0.5 - size / 2) / (size / 2)
    r, a = np.hypot(xx, yy), np.arctan2(yy, xx)
    img = np.stack([0.55 + 0.25 * r * np.cos(a - 2 * np.pi * k / 3) for k in range(3)])
    dots = (np.sin(xx * size / 3.0) * np.sin(yy * size / 3.0)) > 0.85          # marker dots
    img = img * (1 - 0.35 * dots) * (r < 1)
    return img + rng.normal(0, 0.004, img.shape)


def synthetic_sample(rng: np.random.Generator, size: int = 128, base: np.ndarray | None = None,
                     max_contacts: int = 2, min_contacts: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """One (input uint8 (6,H,W), target physical float32 (15,H,W)) pair with min..max_contacts contacts."""
    base = _baseline(size, rng) if base is None else base
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    fields = np.zeros((N_CHANNELS, size, size))
    px_per_mm = size / 32.0
    for _ in range(rng.integers(min_contacts, max_contacts + 1)):
        rad = rng.uniform(0, 0.6) * size / 2
        ang = rng.uniform(-np.pi, np.pi)
        cx, cy = size / 2 + rad * np.cos(ang), size / 2 + rad * np.sin(ang)
        w = rng.uniform(0.06, 0.14) * size
        d = rng.uniform(0.2, 2.0)                     # mm
        sx, sy = rng.normal(0, 0.25 * d, 2)           # mm
        dx, dy = (xx - cx) / w, (yy - cy) / w
        g = np.exp(-0.5 * (dx ** 2 + dy ** 2))
        p = 0.06 * d * np.sqrt(np.clip(1 - (dx ** 2 + dy ** 2) / 1.5, 0, None))   # MPa
        fields[0] += sx * g; fields[1] += sy * g; fields[2] += -d * g
        fields[3] += -0.5 * p + 0.02 * sx * dx * g; fields[4] += -0.5 * p + 0.02 * sy * dy * g
        fields[5] += -p
        fields[6] += 0.01 * (sx * dy + sy * dx) * g; fields[7] += 0.03 * sx * g; fields[8] += 0.03 * sy * g
        fields[9] += -0.2 * p * dx * 0.3; fields[10] += -0.2 * p * dy * 0.3; fields[11] += -p
        fields[12] += p * sx / (d + 0.2) * 0.5; fields[13] += p * sy / (d + 0.2) * 0.5
        fields[14] += -0.1 * p * (sx * dx + sy * dy) / (d + 0.2)
    mask = np.hypot(xx - size / 2, yy - size / 2) < size / 2
    fields *= mask
    # current image: baseline advected by the in-plane displacement, shaded by the surface slope
    shift = fields[:2] * px_per_mm * 2.0
    coords = np.stack([yy - 0.5 - shift[1], xx - 0.5 - shift[0]])
    cur = np.stack([ndimage.map_coordinates(base[c], coords, order=1, mode="nearest") for c in range(3)])
    gz_y, gz_x = np.gradient(fields[2] * px_per_mm / 4)
    for c in range(3):
        la = 2 * np.pi * c / 3
        cur[c] *= 1 + 1.5 * (np.cos(la) * gz_x + np.sin(la) * gz_y)
    cur = cur * mask + rng.normal(0, 0.004, cur.shape)
    inp = np.clip(np.concatenate([base, cur]) * 255 + 0.5, 0, 255).astype(np.uint8)
    return inp, fields.astype(np.float32)


def write_synthetic_dataset(root: str | Path, n: int, size: int = 128, seed: int = 0,
                            val_fraction: float = 0.1, min_contacts: int = 0) -> str:
    """Generate n synthetic samples (one baseline per 'session' of 20 samples); returns the data hash."""
    from ..fields import compute_bounds, normalize_global, write_bounds

    root = Path(root)
    rng = np.random.default_rng(seed)
    pairs, base = [], None
    for i in range(n):
        if i % 20 == 0:
            base = _baseline(size, rng)
        pairs.append(synthetic_sample(rng, size, base, min_contacts=min_contacts))
    bounds = compute_bounds(p[1] for p in pairs)
    write_bounds(root / "bounds.json", bounds)
    n_val = max(1, int(round(n * val_fraction))) if n > 1 else 0
    entries = []
    for i, (inp, tgt) in enumerate(pairs):
        e = write_sample(root, i, inp, normalize_global(tgt, bounds))
        e["split"] = "val" if i >= n - n_val else "train"
        entries.append(e)
    h = write_index(root, entries, (size, size), f"synthetic (tools.train.model.data, seed {seed}; not physics)")
    log.info("wrote %d synthetic samples to %s (hash %s)", n, root, h[:12])
    return h
