"""Force correction hook: the sensor's zero-constrained correction model (ONNX) on cluster forces.

The calibration store names a `correction.onnx` (e.g. a scikit-learn random forest converted with
skl2onnx by `tensortouch recalibrate`); onnxruntime evaluates it, so the runtime needs no
scikit-learn. Contract (calibration.json → "correction"):

    {"file": "correction.onnx",
     "inputs": ["fmag", "u", "v"],        # feature names, in column order (FEATURES below)
     "output": "gain" | "gain3" | "force"}

- "gain":  model returns (N, 1): F' = g · F          (direction kept)
- "gain3": model returns (N, 3): F'_i = g_i · F_i    (per axis)
- "force": model returns (N, 3): F' = model output
Zero constraint: a cluster whose predicted force is exactly zero stays exactly zero whatever the
model says; gains are clipped to [0, max_gain] so a bad correction cannot flip or explode a force.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ...contracts.errors import CalibrationError

log = logging.getLogger(__name__)

FEATURES = ("fx", "fy", "fz", "fmag", "u", "v", "theta", "phi")
OUTPUT_KINDS = {"gain": 1, "gain3": 3, "force": 3}


def feature_matrix(forces: np.ndarray, uv_norm: np.ndarray, theta_phi: np.ndarray,
                   names: list[str]) -> np.ndarray:
    """Columns named by `names` from cluster forces (N,3) N, positions (N,2) in [0,1], angles (N,2) rad."""
    cols = {"fx": forces[:, 0], "fy": forces[:, 1], "fz": forces[:, 2],
            "fmag": np.linalg.norm(forces, axis=1), "u": uv_norm[:, 0], "v": uv_norm[:, 1],
            "theta": theta_phi[:, 0], "phi": theta_phi[:, 1]}
    return np.stack([cols[n] for n in names], axis=1).astype(np.float32)


def apply_output(forces: np.ndarray, out: np.ndarray, kind: str, max_gain: float) -> np.ndarray:
    """Pure core: combine the model output with the predicted forces under the zero constraint."""
    forces = np.asarray(forces, dtype=np.float64)
    out = np.asarray(out, dtype=np.float64).reshape(len(forces), -1)
    if kind == "gain":
        corrected = forces * np.clip(out[:, :1], 0.0, max_gain)
    elif kind == "gain3":
        corrected = forces * np.clip(out[:, :3], 0.0, max_gain)
    elif kind == "force":
        corrected = out[:, :3].copy()
    else:
        raise ValueError(f"unknown correction output kind {kind!r}")
    zero = ~np.any(forces != 0.0, axis=1)
    corrected[zero] = 0.0
    return corrected


class ForceCorrection:
    """An ONNX correction model from a calibration version (or the identity when there is none)."""

    def __init__(self, path: Path | None, spec: dict | None, max_gain: float = 5.0):
        self.path, self.spec, self.max_gain = path, spec or {}, max_gain
        self.session = None
        if path is None:
            return
        import onnxruntime as ort

        names = self.spec.get("inputs", [])
        bad = [n for n in names if n not in FEATURES]
        if not names or bad:
            raise CalibrationError(f"{path}: correction.inputs {names!r} must be a non-empty list of {FEATURES}")
        kind = self.spec.get("output", "gain")
        if kind not in OUTPUT_KINDS:
            raise CalibrationError(f"{path}: correction.output {kind!r}, expected one of {sorted(OUTPUT_KINDS)}")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:
            raise CalibrationError(f"{path}: onnxruntime cannot load the correction model "
                                   f"({type(exc).__name__}: {str(exc).splitlines()[0][:200]})") from None
        inp = self.session.get_inputs()[0]
        if len(inp.shape) != 2 or (isinstance(inp.shape[1], int) and inp.shape[1] != len(names)):
            raise CalibrationError(f"{path}: model input shape {inp.shape}, expected [N, {len(names)}]")
        self.input_name = inp.name
        self.kind = kind

    @property
    def enabled(self) -> bool:
        return self.session is not None

    def __call__(self, forces: np.ndarray, uv_norm: np.ndarray, theta_phi: np.ndarray) -> np.ndarray:
        forces = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
        if self.session is None or len(forces) == 0:
            return forces
        x = feature_matrix(forces, np.asarray(uv_norm).reshape(-1, 2), np.asarray(theta_phi).reshape(-1, 2),
                           self.spec["inputs"])
        out = self.session.run(None, {self.input_name: x})[0]
        return apply_output(forces, out, self.kind, self.max_gain)

    @classmethod
    def from_calibration(cls, cal) -> "ForceCorrection":
        spec = cal.meta.get("correction")
        return cls(cal.correction_path if spec else None, spec)
