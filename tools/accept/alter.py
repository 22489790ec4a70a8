"""Independent alteration of a recorded session's measurements (written separately from the
twin's effect code and from runtime/effects): copies a session WITHOUT its truth/ folder and
provenance, and changes wrench.csv the way a hidden physical effect would.

  viscoelastic  each force channel through the linear system H(s) = (tau s + 1 - g) / (tau s + 1)
                (scipy.signal.lsim, first-order hold), per indenter, in the F/T frame; the gel cannot
                pull: where the reading shows no contact (change from the first reading within 3 noise
                sigmas of the manifest's F/T noise) the reading is left as it is, and where the
                filtered force points against the unfiltered one the contact is lost (first reading)
  azimuth       force scaled by 1 + a cos(phi - phi0) with phi the azimuth of the indenter tip
                (an effect NOT in the library)
  temperature   force scaled by 1 - alpha (T - t_ref), T from the session's temperature stream
  ft_bias       F/T reading + (bx, by, bz) * t (F/T frame)
  strain        force scaled by 1 + k (d / h)^2, d = indentation of the mocap tip below the rest cap
                sphere (params "radius", "center_z" of the gel, mm), h = center_z + radius
  rim           force scaled by 1 + a exp(-s / w), s = arc length from the tip's point on the cap
                down to the rim (cap sphere + "skirt" height, mm)
  mullins       force scaled by 1 - r erf((D - d) / m): d = indentation of the mocap tip (as for
                strain), D = the largest d of this indenter so far in the session (the damage stays:
                unloading and every later shallower contact are softer)
  friction      the shear part of the reading (perpendicular to the cap sphere's normal at the tip,
                rotated into the F/T frame through the tip pose and the F/T mount) capped at mu |F_n|
  led           frames.avi re-encoded with every pixel times 1 + c t (LED dimming; MJPG as recorded);
                the F/T stream is left as it is
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from scipy import signal
from scipy.special import erf

from ...contracts.files import finish_partial
from ...contracts.session import load_session, rewrite_in_units, write_manifest, write_stream


def copy_without_truth(src: Path, dst: Path) -> Path:
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("truth", ".partial"))
    manifest = json.loads((dst / "session.json").read_text())
    manifest["provenance"] = {"source": "altered copy (tools/accept/alter.py)"}
    manifest.pop("truth", None)
    (dst / "session.json").write_text(json.dumps(manifest, indent=2))
    rewrite_in_units(dst)     # the streams this script rewrites are written in house units
    return dst


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions w, x, y, z -> (N, 3, 3) rotation matrices."""
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def _dim_video(dst: Path, c: float) -> None:
    import cv2

    manifest = json.loads((dst / "session.json").read_text())
    info = manifest["streams"]["frames"]
    times = np.loadtxt(dst / info["file"], delimiter=",", skiprows=1, ndmin=2)[:, 0]
    src = dst / info["video"]
    tmp = src.with_name(".tmp-" + src.name)      # the name keeps the extension OpenCV picks the container by
    cap = cv2.VideoCapture(str(src))
    out = None
    for t in times:
        ok, img = cap.read()
        if not ok:
            break
        if out is None:
            out = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"MJPG"), float(info["fps"]),
                                  (img.shape[1], img.shape[0]))
            out.set(cv2.VIDEOWRITER_PROP_QUALITY, float(info.get("quality", 90)))
        out.write(np.clip(img.astype(np.float32) * (1.0 + c * (t - times[0])), 0, 255).astype(np.uint8))
    cap.release()
    out.release()
    finish_partial(tmp, src)
    info["bytes"] = src.stat().st_size
    write_manifest(dst, manifest)


def alter_session(src: Path, dst: Path, kind: str, params: dict) -> Path:
    dst = copy_without_truth(Path(src), Path(dst))
    if kind == "led":
        _dim_video(dst, params["c"])
        return dst
    s = load_session(dst, check_frames=False)
    mount = json.loads((dst / "session.json").read_text())["streams"]["wrench"]["ft_to_indenter"]
    r_mount = _quat_matrix(np.array([mount["rotation_wxyz"]], float))[0]
    noise = float(s.streams["wrench"].get("noise", {}).get("force_n", 0.02))
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
            e = f - f0
            q = np.column_stack([signal.lsim(lti, e[:, j], t, interp=True)[1] for j in range(3)])
            touching = np.linalg.norm(e, axis=1) > 3.0 * noise
            lost = touching & (np.sum(q * e, axis=1) <= 0.0)
            f = np.where(touching[:, None], f0 + q, f)
            f[lost] = f0
        elif kind == "temperature":
            tt = s.table("temperature")
            f = f * (1.0 - params["alpha"] * (np.interp(t, tt[:, 0], tt[:, 1]) - params["t_ref"]))[:, None]
        elif kind == "ft_bias":
            f = f + np.outer(t, [params["bx"], params["by"], params["bz"]])
        elif kind in ("strain", "rim", "mullins", "friction"):
            p = poses[poses[:, 1] == k]
            tip = np.column_stack([np.interp(t, p[:, 0], p[:, 2 + j]) for j in range(3)])
            v = tip - np.array([0.0, 0.0, params["center_z"]])
            r = np.linalg.norm(v, axis=1)
            if kind == "mullins":
                d = np.clip(params["radius"] - r, 0.0, None)
                most = np.empty_like(d)
                run = 0.0
                for i, di in enumerate(d):
                    run = max(run, di)
                    most[i] = run
                f = f * (1.0 - params["r"] * erf((most - d) / params["m"]))[:, None]
            elif kind == "friction":
                # nearest pose sample: orientations are not interpolated (120 Hz mocap, 200 Hz F/T)
                j = np.clip(np.searchsorted(p[:, 0], t), 0, len(p) - 1)
                rot = _quat_matrix(p[j, 5:9]) @ r_mount                    # F/T frame -> sensor frame
                n_ft = np.einsum("nji,nj->ni", rot, v / np.maximum(r, 1e-9)[:, None])
                fn = np.sum(f * n_ft, axis=1, keepdims=True) * n_ft
                ft = f - fn
                mag, cap = np.linalg.norm(ft, axis=1), params["mu"] * np.linalg.norm(fn, axis=1)
                f = fn + ft * np.where(mag > cap, cap / np.maximum(mag, 1e-12), 1.0)[:, None]
            elif kind == "strain":
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
    write_stream(dst, "wrench", w)       # as read: a rig calibration of the stream is in the numbers now
    return dst
