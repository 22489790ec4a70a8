"""The faster contact clustering (runtime/stages/contacts.py) gives exactly the clusters of the frozen
reference (tools/bench/previous_stages.py, the code before the speed work): on the demo unit's real fields
(shipped int8 network on runtime/demo/frames.avi, TWIN-DEMO calibration) under the package's contact
rules and variants of them, and on synthetic touches placed at the image border."""
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from tensortouch.contracts import wire
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.pipeline import PipelineConfig, contact_stage, open_pipeline
from tensortouch.runtime.stages.contacts import ContactConfig, find_clusters, pixel_forces
from tensortouch.runtime.stages.model import find_package
from tensortouch.tools.bench import previous_stages as ref

DEMO = Path(__file__).resolve().parents[1] / "runtime" / "demo" / "frames.avi"


@pytest.fixture(scope="module")
def demo():
    """(calibration, package contact config, [(15, H, W) fields of every demo frame past the baseline])."""
    cal = CalibrationStore().load("TWIN-DEMO")
    pkg = find_package(None)
    pipe = open_pipeline(pkg, cal, precision="int8", threads=1)
    cap = cv2.VideoCapture(str(DEMO))
    fields, k = [], 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        r = pipe.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB), k / 30.0)
        k += 1
        if r.fields is not None:
            fields.append(r.fields.copy())
    cap.release()
    assert len(fields) > 100
    return cal, PipelineConfig.for_package(pkg).contacts, fields


def reference(fields, cal, cfg):
    fp = pixel_forces(fields, cal.pixel_area)
    return ref.find_clusters(fp, cal.surface_xyz, cal.normals, cal.pixel_area, cal.mask, disp=fields[0:3], cfg=cfg)


VARIANTS = {
    "package": {},
    "no_light_rule": {"weak_threshold_n": 0.0},
    "no_merge": {"merge_n": 0.0},
    "floor": {"support_floor_n": 0.0002, "support_radius_px": 6.0},
    "no_support": {"support_radius_px": 0.0},
    "low_threshold": {"threshold_n": 0.0009, "weak_threshold_n": 0.0004, "min_total_n": 0.02},
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_demo_frames_same_clusters_as_reference(demo, variant):
    cal, cfg, fields = demo
    cfg = replace(cfg, **VARIANTS[variant])
    touched = 0
    for f in fields:
        want = reference(f, cal, cfg)
        got = contact_stage(f, cal, cfg)
        assert got == want                  # every number bit for bit (dataclass equality of floats)
        touched += bool(want)
    assert touched > 20                     # the demo presses: the comparison covered real clusters


def test_touches_at_the_border_and_corners_same_as_reference(demo):
    """Cores at the image edge and in corners (the support box is clipped there), several at once,
    strong and light, with noise: the same clusters as the reference."""
    cal, cfg, _ = demo
    h, w = cal.model_size
    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[0:h, 0:w]
    mask = np.ones((h, w), bool)            # the border pixels count too
    nrm = np.moveaxis(cal.normals, -1, 0)
    for trial in range(40):
        f = np.zeros((15, h, w), np.float32)
        f[0:3] = rng.normal(0, 0.01, (3, h, w))
        for _ in range(rng.integers(1, 5)):
            u, v = rng.choice([0, 2, w // 2, w - 3, w - 1]), rng.choice([1, h // 3, h - 1])
            sigma, force = rng.uniform(1.0, 6.0), rng.uniform(0.05, 2.0)
            g = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma ** 2))
            g = g / (g * cal.pixel_area).sum()
            f[9:12] += (-force * g)[None] * nrm
        f[9:15] += rng.normal(0, 2e-4, (6, h, w)).astype(np.float32) / cal.pixel_area
        for c in (cfg, replace(cfg, merge_n=0.0), replace(cfg, support_radius_px=3.0)):
            fp = pixel_forces(f, cal.pixel_area)
            args = (fp, cal.surface_xyz, cal.normals, cal.pixel_area, mask)
            assert find_clusters(*args, disp=f[0:3], cfg=c) == ref.find_clusters(*args, disp=f[0:3], cfg=c), trial


def test_rest_frame_returns_nothing_before_labelling():
    """Hand-worked: all forces below every threshold → no cluster; one pixel above → a 1-pixel cluster."""
    h = w = 16
    area = np.full((h, w), 0.05, np.float32)
    xyz = np.zeros((h, w, 3), np.float32)
    nrm = np.zeros((h, w, 3), np.float32)
    nrm[..., 2] = 1.0
    mask = np.ones((h, w), bool)
    fp = np.full((3, h, w), 1e-4, np.float32)
    cfg = ContactConfig(threshold_n=0.002, weak_threshold_n=0.001, min_total_n=0.1, min_pixels=1)
    assert find_clusters(fp, xyz, nrm, area, mask, cfg=cfg) == []
    fp[2, 5, 7] = 0.01
    (c,) = find_clusters(fp, xyz, nrm, area, mask, cfg=cfg)
    assert c.pixels == 1 and c.uv_px[0] == pytest.approx(7.5, abs=0.5) and c.area_mm2 == pytest.approx(0.05)


def test_fields_payload_same_bytes_as_before(demo):
    """encode_fields: the same payload, attachment and clipped channels as the frozen encoder on every
    demo frame, and on hand-made frames with subnormals, ±65504, overflow to ±inf, and NaN (refused)."""
    _, _, fields = demo
    for i, f in enumerate(fields):
        assert wire.encode_fields(f, i, 0.25 * i, "TWIN-DEMO") == ref.encode_fields(f, i, 0.25 * i, "TWIN-DEMO")
    f = np.zeros((15, 6, 5), np.float32)
    f[3] = 3e-6                                     # float16 subnormal
    f[4, 0, 0], f[5, 1, 1], f[6, 2, 2] = 65504.0, -65519.0, 65520.0   # kept, kept (rounds), overflows
    f[10, 3, 3], f[11, 4, 4] = -np.inf, 1e9
    got, want = wire.encode_fields(f, 7, 1.5, "s"), ref.encode_fields(f, 7, 1.5, "s")
    assert got == want and got[2] == ("sigma_xy", "fn_y", "fn_z")
    f[0, 0, 0] = np.nan
    with pytest.raises(wire.WireError, match="NaN in channel.*disp_x"):
        wire.encode_fields(f, 7, 1.5, "s")
    with pytest.raises(wire.WireError, match="NaN in channel.*disp_x"):
        ref.encode_fields(f, 7, 1.5, "s")
    f[0, 0, 0] = 0.0
    for t in (np.nan, np.inf):                      # a non-finite time is refused as before
        with pytest.raises(wire.WireError, match="non-finite number"):
            wire.encode_fields(f, 7, t, "s")
        with pytest.raises(wire.WireError, match="non-finite number"):
            ref.encode_fields(f, 7, t, "s")
    assert wire.encode_fields(f, np.int64(7), np.float32(1.5), "s") == ref.encode_fields(f, np.int64(7), np.float32(1.5), "s")


def test_many_touches_same_as_reference(demo):
    """A dozen separate touches (more labels than the per-label pass takes: the sorted path), with
    displacements, against the reference."""
    cal, cfg, _ = demo
    h, w = cal.model_size
    yy, xx = np.mgrid[0:h, 0:w]
    nrm = np.moveaxis(cal.normals, -1, 0)
    rng = np.random.default_rng(9)
    f = np.zeros((15, h, w), np.float32)
    for u in (20, 45, 70, 95):
        for v in (30, 64, 98):
            g = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 2.0 ** 2))
            g = g / (g * cal.pixel_area).sum()
            f[9:12] += (-rng.uniform(0.3, 1.5) * g)[None] * nrm
            f[0:3] += (-0.3 * g / g.max())[None] * nrm
    cfg = replace(cfg, merge_n=0.0, support_radius_px=6.0)
    want = reference(f, cal, cfg)
    assert len(want) >= 10 and contact_stage(f, cal, cfg) == want
