"""The workbench's sample table: one row per (time, indenter) sample with the measured force, the
model's raw prediction and every covariate. Built from a session by samples.py, or synthesized
in tests. Stored as `.npz` (no pickle) for the cache and as `residuals.csv` for people.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...contracts.errors import SessionError
from ...contracts.files import atomic_write

log = logging.getLogger(__name__)

# Scalar covariates scanned when no library effect explains the residual (name -> unit).
SCAN_COVARIATES = {
    "depth": "mm", "rate": "mm/s", "slip": "mm", "temperature": "degC", "time": "s",
    "load_history": "mm", "max_depth": "mm", "theta": "rad", "phi": "rad", "rim_distance": "mm",
    "brightness": "-", "force_n": "N", "force_t": "N",
    "vel_x": "mm/s", "vel_y": "mm/s", "vel_z": "mm/s", "acc_x": "mm/s²", "acc_y": "mm/s²", "acc_z": "mm/s²",
}
# Vector covariates scanned as a force along the vector that depends on its magnitude (a drag):
# name -> (per-axis columns, unit of the magnitude)
SCAN_VECTORS = {"velocity": (("vel_x", "vel_y", "vel_z"), "mm/s"),
                "acceleration": (("acc_x", "acc_y", "acc_z"), "mm/s²")}
REQUIRED = ("t", "series", "time")


@dataclass
class SampleTable:
    """cols: 1-D per-sample arrays; meas/model: (N,3) N sensor frame; vec: (N,3)/(N,3,3) arrays."""

    cols: dict[str, np.ndarray]
    meas: np.ndarray
    model: np.ndarray
    vec: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        n = len(self.meas)
        for k in REQUIRED:
            if k not in self.cols:
                raise SessionError(f"sample table: column {k!r} missing")
        for name, arr in list(self.cols.items()) + list(self.vec.items()):
            if len(arr) != n:
                raise SessionError(f"sample table: column {name!r} has {len(arr)} rows, expected {n}")
        if self.model.shape != (n, 3) or self.meas.shape != (n, 3):
            raise SessionError("sample table: meas and model must both be (N, 3)")

    def __len__(self) -> int:
        return len(self.meas)

    def cov(self) -> dict:
        """Covariates for effects (scalar columns + vectors), derived force_n/force_t included."""
        out = dict(self.cols)
        out.update(self.vec)
        if "force_n" not in out and "normal" in self.vec:
            fn = np.sum(self.model * self.vec["normal"], axis=1)
            out["force_n"] = np.abs(fn)
            out["force_t"] = np.linalg.norm(self.model - fn[:, None] * self.vec["normal"], axis=1)
        if "load_history" not in out and "max_depth" in out and "depth" in out:
            out["load_history"] = np.clip(out["max_depth"] - out["depth"], 0.0, None)
        return out

    def with_model(self, model: np.ndarray) -> "SampleTable":
        return SampleTable(self.cols, self.meas, np.asarray(model, dtype=np.float64), self.vec, self.meta)

    # ----- storage -------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        path = Path(path)
        arrays = {f"col__{k}": v for k, v in self.cols.items()}
        arrays.update({f"vec__{k}": v for k, v in self.vec.items()})
        arrays["meas"], arrays["model"] = self.meas, self.model
        arrays["meta_json"] = np.frombuffer(_json(self.meta).encode(), dtype=np.uint8)
        atomic_write(path, lambda fh: np.savez(fh, **arrays))

    @classmethod
    def load(cls, path: str | Path) -> "SampleTable":
        import json

        with np.load(path, allow_pickle=False) as z:
            cols = {k[5:]: z[k] for k in z.files if k.startswith("col__")}
            vec = {k[5:]: z[k] for k in z.files if k.startswith("vec__")}
            meta = json.loads(bytes(z["meta_json"]).decode())
            return cls(cols, z["meas"], z["model"], vec, meta)


def _json(obj) -> str:
    import json

    return json.dumps(obj, sort_keys=True, default=float)


def write_residuals_csv(path: str | Path, table: SampleTable, pred: np.ndarray) -> None:
    """One row per sample: measured, predicted, residual (N) and every scalar covariate."""
    cov = table.cov()
    names = [k for k in cov if np.ndim(cov[k]) == 1]
    res = table.meas - pred
    header = (["fx_meas", "fy_meas", "fz_meas", "fx_pred", "fy_pred", "fz_pred", "rx", "ry", "rz", "r_mag"]
              + names)
    data = np.column_stack([table.meas, pred, res, np.linalg.norm(res, axis=1)]
                           + [np.asarray(cov[k], dtype=np.float64) for k in names])
    def write(fh):
        fh.write((",".join(header) + "\n").encode())
        np.savetxt(fh, data, delimiter=",", fmt="%.6g")

    atomic_write(path, write)


def nearest_index(sorted_t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Index of the nearest element of the sorted array `sorted_t` for each query time in `q`."""
    t = np.asarray(sorted_t)
    nxt = np.clip(np.searchsorted(t, q), 0, len(t) - 1)
    prev = np.clip(nxt - 1, 0, len(t) - 1)
    return np.where(np.abs(t[prev] - q) < np.abs(t[nxt] - q), prev, nxt)
