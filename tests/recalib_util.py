"""Shared helpers for the recalibration tests: a synthetic poke recording for the replay camera.

The "shipped model" is tools.bench.models' difference network (force from image change); the
recording's wrench stream (the twin-gauge stand-in) is the model's own raw force times a
position-dependent bias the model does not know (`true_gain`), so the correction has something
real to learn. Everything goes to pytest's tmp_path.
"""
from pathlib import Path

import cv2
import numpy as np
from tensortouch.contracts.session import STREAM_COLUMNS, new_manifest, write_manifest, write_table
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.pipeline import SensorPipeline
from tensortouch.runtime.stages.correction import ForceCorrection
from tensortouch.runtime.stages.model import FieldModel, load_package
from tensortouch.tools.bench.models import write_difference_package
from tensortouch.tools.recalib.gpr_geometry import model_to_camera
from tensortouch.tools.recalib.pokes import suggest_next

from tests.conftest import dome_calibration

W, H, SIZE, SENSOR, FPS = 160, 120, 32, "TT-RECAL", 30.0


def true_gain(uv_norm):
    """The unit's bias: 25 % stiffer gel, growing towards +u (a shifted centre)."""
    return 1.25 * (1.0 + 0.4 * (np.asarray(uv_norm)[..., 0] - 0.5))


def setup_env(tmp_path: Path):
    pkg = write_difference_package(tmp_path / "models" / "difference-32", SIZE)
    store_root = tmp_path / "calib"
    dome_calibration(store_root, SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    return load_package(pkg), CalibrationStore(store_root)


def poke_positions(cal, n):
    acc, uvs = [], []
    for _ in range(n):
        uv, xyz = suggest_next(cal.mask, cal.theta, cal.surface_xyz, acc)
        acc.append(xyz)
        uvs.append(uv)
    return np.array(uvs), np.array(acc)


def write_recording(folder: Path, package, store, n_pokes=7, rest=40, hold=30, gap=15, extra=None):
    """Frames with n_pokes blobs at the suggested spots (plus `extra` (uv_px, amp) pokes), wrench from
    the model's raw force × true_gain, poses = the true 3D poke points. Returns (folder, uv_px, xyz)."""
    folder.mkdir(parents=True)
    cal = store.load(SENSOR)
    uvs, xyz = poke_positions(cal, n_pokes)
    amps = np.linspace(60, 110, n_pokes)
    plan = [(uv, a, p) for uv, a, p in zip(uvs, amps, xyz)] + list(extra or [])
    cam_xy = model_to_camera(np.array([p[0] for p in plan]), cal.gel_center_px, cal.gel_radius_px, cal.model_size)
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.zeros((H, W, 3), np.float32)
    base[...] = (110, 120, 130)
    base[(xx - W / 2) ** 2 + (yy - H / 2) ** 2 > 50 ** 2] = 0
    rng = np.random.default_rng(0)
    frames, profile = [], []                      # profile: (poke index or -1, amplitude fraction)
    frames += [None] * rest
    profile += [(-1, 0.0)] * rest
    for i in range(len(plan)):
        env = np.r_[np.linspace(0.1, 1, 8), np.ones(hold - 12), np.linspace(1, 0.1, 4)]
        profile += [(i, e) for e in env] + [(-1, 0.0)] * gap
    vw = cv2.VideoWriter(str(folder / "frames.avi"), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
    images = []
    for i, e in profile:
        img = base.copy()
        if i >= 0:
            x, y = cam_xy[i]
            img += plan[i][1] * e * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 5.0 ** 2))[..., None]
        img += rng.normal(0, 0.8, img.shape)
        u8 = np.clip(img, 0, 255).astype(np.uint8)
        images.append(u8)
        vw.write(cv2.cvtColor(u8, cv2.COLOR_RGB2BGR))
    vw.release()
    t = np.arange(len(profile)) / FPS
    # reference = model's raw force on the decoded frames × the bias
    pipe = SensorPipeline(SENSOR, FieldModel(package, "fp32"), cal, correction=ForceCorrection(None, None))
    cap = cv2.VideoCapture(str(folder / "frames.avi"))
    wrench = np.zeros((len(profile), 8))
    poses = np.zeros((len(profile), 9))
    for k, (i, _) in enumerate(profile):
        ok, bgr = cap.read()
        r = pipe.process(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), t[k])
        f = np.linalg.norm(r.force_n)
        uvn = plan[i][0] / SIZE if i >= 0 else np.array([0.5, 0.5])
        wrench[k] = [t[k], 0, 0, 0, -f * true_gain(uvn), 0, 0, 0]
        p = plan[i][2] if i >= 0 else np.array([0, 0, 30.0])
        poses[k] = [t[k], 0, *p, 1, 0, 0, 0]
    write_table(folder / "frames.csv", STREAM_COLUMNS["frames"], np.stack([t, np.arange(len(t))], 1))
    write_table(folder / "wrench.csv", STREAM_COLUMNS["wrench"], wrench)
    write_table(folder / "poses.csv", STREAM_COLUMNS["poses"], poses)
    streams = {"frames": {"file": "frames.csv", "video": "frames.avi"},
               "wrench": {"file": "wrench.csv", "ft_to_indenter": {"rotation_wxyz": [1, 0, 0, 0],
                                                                     "translation_mm": [0, 0, 0]}},
               "poses": {"file": "poses.csv"}}
    write_manifest(folder, new_manifest(SENSOR, streams, provenance={"source": "tests/recalib_util.py synthetic"}))
    return folder, uvs, xyz
