"""The sensor's correction on table rows, evaluated exactly but cheaply inside diagnosis.

Diagnosis evaluates the deployed prediction thousands of times per candidate (grid, folds, finite
differences), and each evaluation ran the correction forest (ONNX, runtime/stages/correction.py) over
every row. For the workbench's correction (`random_forest_gain` on |F|, θ, u, v) a row's gain only
changes when |F| crosses one of the forest's split thresholds on |F|: θ, u, v are the row's fixed
cluster position. So the gain is memoized per (row, |F| interval between consecutive thresholds),
with the intervals computed exactly as the tree ensemble compares (float32 input, BRANCH_LEQ or
BRANCH_LT). A miss runs the same ONNX session on the same float32 features as
`ForceCorrection.__call__`, so the numbers are identical (tests/test_workbench_fastpost.py checks
bit equality). Corrections the memo cannot describe (other force features, other outputs, another
graph) fall back to the direct evaluation.
"""
from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

FORCE_FEATURES = ("fx", "fy", "fz", "fmag")


def magnitude_thresholds(onnx_path, feature: int) -> tuple[np.ndarray, str] | None:
    """Sorted distinct float32 split thresholds of input column `feature` in the file's single tree
    ensemble, and the branch mode; None when the graph is not a plain LEQ/LT tree ensemble."""
    import onnx

    model = onnx.load(str(onnx_path))
    trees = [n for n in model.graph.node if n.op_type in ("TreeEnsembleRegressor", "TreeEnsemble")]
    others = [n for n in model.graph.node if n not in trees and n.op_type not in ("Cast", "Identity")]
    if len(trees) != 1 or others:
        return None
    attrs = {a.name: a for a in trees[0].attribute}
    if not {"nodes_modes", "nodes_featureids", "nodes_values"} <= set(attrs):
        return None
    modes = np.array([s.decode() for s in attrs["nodes_modes"].strings])
    branch = set(modes.tolist()) - {"LEAF"}
    if len(branch) != 1 or branch.issubset({"BRANCH_LEQ", "BRANCH_LT"}) is False:
        return None
    feats = np.asarray(attrs["nodes_featureids"].ints)
    vals = np.asarray(attrs["nodes_values"].floats, dtype=np.float32)
    return np.unique(vals[(feats == feature) & (modes != "LEAF")]), branch.pop()


class MemoGain:
    """Callable: forces (runtime sign, rows of the table) -> corrected forces, memoized per row and
    |F| interval. `rows` are table row indices (fixed θ, u, v per row)."""

    def __init__(self, corr, uv: np.ndarray, theta_phi: np.ndarray, thresholds: np.ndarray, mode: str):
        self.corr, self.uv, self.tp = corr, uv, theta_phi
        self.t = thresholds
        self.side = "left" if mode == "BRANCH_LEQ" else "right"
        self.stride = np.int64(len(thresholds) + 1)
        self.keys = np.zeros(0, np.int64)
        self.gains = np.zeros(0, np.float64)
        self.stats = {"calls": 0, "rows": 0, "evaluated": 0}

    def __call__(self, forces: np.ndarray, rows: np.ndarray) -> np.ndarray:
        from ...runtime.stages.correction import apply_output, feature_matrix

        forces = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
        mag = np.linalg.norm(forces, axis=1).astype(np.float32)   # as feature_matrix computes it
        key = rows.astype(np.int64) * self.stride + np.searchsorted(self.t, mag, side=self.side)
        pos = np.searchsorted(self.keys, key)
        hit = pos < len(self.keys)
        hit[hit] = self.keys[pos[hit]] == key[hit]
        gain = np.empty(len(forces))
        gain[hit] = self.gains[pos[hit]]
        miss = np.flatnonzero(~hit)
        if len(miss):
            new, first = np.unique(key[miss], return_index=True)
            sel = miss[first]
            x = feature_matrix(forces[sel], self.uv[rows[sel]], self.tp[rows[sel]], self.corr.spec["inputs"])
            g = np.asarray(self.corr.session.run(None, {self.corr.input_name: x})[0], np.float64).reshape(len(sel), -1)[:, 0]
            gain[miss] = g[np.searchsorted(new, key[miss])]
            keys = np.concatenate([self.keys, new])
            order = np.argsort(keys, kind="stable")
            self.keys, self.gains = keys[order], np.concatenate([self.gains, g])[order]
            self.stats["evaluated"] += len(sel)
        self.stats["calls"] += 1
        self.stats["rows"] += len(forces)
        return apply_output(forces, gain[:, None], "gain", self.corr.max_gain)


def memo_gain(corr, uv: np.ndarray, theta_phi: np.ndarray) -> MemoGain | None:
    """A MemoGain for this correction, or None when it is not a |F|-only gain forest."""
    spec = corr.spec or {}
    inputs = list(spec.get("inputs", []))
    force_inputs = [n for n in inputs if n in FORCE_FEATURES]
    if corr.kind != "gain" or force_inputs != ["fmag"] or corr.path is None:
        return None
    try:
        found = magnitude_thresholds(corr.path, inputs.index("fmag"))
    except Exception as exc:  # an unreadable graph: the direct evaluation still works
        log.info("%s: correction not memoizable (%s)", corr.path, exc)
        return None
    return MemoGain(corr, uv, theta_phi, *found) if found else None


def correction_post(table, cal, memoize: bool = True):
    """The sensor's correction on table rows (table sign convention), or None when it has none.
    `memoize`: the exact memoized evaluation of tools/workbench/fastpost.py where it applies."""
    from ...runtime.stages.correction import ForceCorrection

    corr = ForceCorrection.from_calibration(cal)
    if not corr.enabled or "corr_uv" not in table.vec:
        return None
    uv, tp = table.vec["corr_uv"], table.vec["corr_theta_phi"]
    memo = memo_gain(corr, uv, tp) if memoize else None

    def post(forces: np.ndarray) -> np.ndarray:
        f = np.asarray(forces, dtype=np.float64)
        out = f.copy()
        nz = np.flatnonzero(np.any(f != 0.0, axis=1))   # zero stays zero: only rows with a force
        if len(nz):
            out[nz] = -(memo(-f[nz], nz) if memo is not None else corr(-f[nz], uv[nz], tp[nz]))
        return out

    post.memo = memo
    return post
