"""Independent alteration of a recorded session's measurements (written separately from the
twin's effect code and from runtime/effects): copies a session WITHOUT its truth/ folder and
provenance, and changes wrench.csv the way a hidden physical effect would.

  viscoelastic  each force channel through the linear system H(s) = (tau s + 1 - g) / (tau s + 1)
                (scipy.signal.lsim, first-order hold), per indenter, in the F/T frame
  azimuth       force scaled by 1 + a cos(phi - phi0) with phi the azimuth of the indenter tip
                (an effect NOT in the library)
  temperature   force scaled by 1 - alpha (T - t_ref), T from the session's temperature stream
  ft_bias       F/T reading + (bx, by, bz) * t (F/T frame)
  strain        force scaled by 1 + k (d / h)^2, d = indentation of the mocap tip below the rest cap
                sphere (params "radius", "center_z" of the gel, mm), h = center_z + radius
  rim           force scaled by 1 + a exp(-s / w), s = arc length from the tip's point on the cap
                down to the rim (cap sphere + "skirt" height, mm)
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from scipy import signal

from runtime.session import STREAM_COLUMNS, load_session, write_table


def copy_without_truth(src: Path, dst: Path) -> Path:
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("truth", ".partial"))
    manifest = json.loads((dst / "session.json").read_text())
    manifest["provenance"] = {"source": "altered copy (tests/workbench_alter.py)"}
    manifest.pop("truth", None)
    (dst / "session.json").write_text(json.dumps(manifest, indent=2))
    return dst


def alter_session(src: Path, dst: Path, kind: str, params: dict) -> Path:
    dst = copy_without_truth(Path(src), Path(dst))
    s = load_session(dst, check_frames=False)
    w = s.table("wrench").copy()
    poses = s.table("poses")
    for k in np.unique(w[:, 1]):
        m = w[:, 1] == k
        t = w[m, 0]
        f = w[m, 2:5]
        if kind == "viscoelastic":
            g, tau = params["g1"], params["tau"]
            lti = signal.lti([tau, 1.0 - g], [tau, 1.0])
            f0 = f[0].copy()  # filter the change from the first reading (the unloaded state)
            f = np.column_stack([signal.lsim(lti, f[:, j] - f0[j], t, interp=True)[1] for j in range(3)]) + f0
        elif kind == "temperature":
            tt = s.table("temperature")
            f = f * (1.0 - params["alpha"] * (np.interp(t, tt[:, 0], tt[:, 1]) - params["t_ref"]))[:, None]
        elif kind == "ft_bias":
            f = f + np.outer(t, [params["bx"], params["by"], params["bz"]])
        elif kind in ("strain", "rim"):
            p = poses[poses[:, 1] == k]
            tip = np.column_stack([np.interp(t, p[:, 0], p[:, 2 + j]) for j in range(3)])
            v = tip - np.array([0.0, 0.0, params["center_z"]])
            r = np.linalg.norm(v, axis=1)
            if kind == "strain":
                d = np.clip(params["radius"] - r, 0.0, None)
                f = f * (1.0 + params["k"] * (d / (params["center_z"] + params["radius"])) ** 2)[:, None]
            else:
                polar = np.arccos(np.clip(v[:, 2] / np.maximum(r, 1e-9), -1, 1))
                edge = np.arccos(np.clip((params["skirt"] - params["center_z"]) / params["radius"], -1, 1))
                arc = params["radius"] * np.clip(edge - polar, 0.0, None) + params["skirt"]
                f = f * (1.0 + params["a"] * np.exp(-arc / params["w"]))[:, None]
        elif kind == "azimuth":
            p = poses[poses[:, 1] == k]
            phi = np.arctan2(np.interp(t, p[:, 0], p[:, 3]), np.interp(t, p[:, 0], p[:, 2]))
            f = f * (1.0 + params["a"] * np.cos(phi - params["phi0"]))[:, None]
        else:
            raise ValueError(kind)
        w[m, 2:5] = f
    write_table(dst / "wrench.csv", STREAM_COLUMNS["wrench"], w)
    return dst
