"""Preprocess: circular gel crop, mask, INTER_AREA resize, float NCHW, 6-channel model input."""
import cv2
import numpy as np
import pytest
from tensortouch.contracts.errors import CalibrationError, CaptureError
from tensortouch.runtime.stages.preprocess import Preprocessor, model_input, to_chw_float

GEOMETRIES = [  # (frame h, w), center, radius, model size
    ((480, 640), (323.3, 237.9), 220.0, 128),   # one 2x2 halving then INTER_AREA
    ((480, 640), (320.0, 240.0), 256.0, 128),   # window 512: two halvings, exact multiple
    ((720, 1280), (640.6, 361.2), 340.0, 96),   # bigger camera, other model size
    ((120, 160), (80.0, 60.0), 50.0, 128),      # upscaling, no halving
]


def disk_frame(shape, cx, cy, r, value=255):
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.zeros((h, w, 3), np.uint8)
    img[(xx - cx) ** 2 + (yy - cy) ** 2 <= r ** 2] = value
    return img


def centroid(gray):
    yy, xx = np.mgrid[0:gray.shape[0], 0:gray.shape[1]]
    total = gray.sum()
    return (xx * gray).sum() / total, (yy * gray).sum() / total


@pytest.mark.parametrize("exact", [False, True])
@pytest.mark.parametrize("shape,center,radius,size", GEOMETRIES)
def test_shapes_dtypes_and_range(shape, center, radius, size, exact):
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, shape + (3,), dtype=np.uint8)
    p = Preprocessor(*center, radius, size, exact=exact)
    out = p.apply(frame)
    assert out.shape == (3, size, size) and out.dtype == np.float32
    assert 0.0 <= out.min() and out.max() <= 1.0
    small = p.crop(frame)
    assert small.shape == (size, size, 3) and small.dtype == np.uint8
    np.testing.assert_allclose(out, small.transpose(2, 0, 1) / 255.0, atol=1e-6)
    assert abs(p.radius_out - size / 2) <= size / 2 * 0.01  # circle fills the output within 1 %


@pytest.mark.parametrize("exact", [False, True])
@pytest.mark.parametrize("shape,center,radius,size", GEOMETRIES)
def test_outside_circle_is_zero_inside_kept(shape, center, radius, size, exact):
    frame = np.full(shape + (3,), 200, np.uint8)  # uniform light everywhere, also outside the gel
    p = Preprocessor(*center, radius, size, exact=exact)
    small = p.crop(frame)[..., 0].astype(float)
    ccx, ccy = p.to_model(center[0], center[1])
    vv, uu = np.mgrid[0:size, 0:size]
    rho = np.hypot(uu - ccx, vv - ccy)
    margin = 1.5 + p.window / size  # one output pixel footprint plus rounding
    assert np.all(small[rho > p.radius_out + margin] == 0)
    assert np.all(small[rho < p.radius_out - margin] == 200)


@pytest.mark.parametrize("exact", [False, True])
@pytest.mark.parametrize("shape,center,radius,size", GEOMETRIES)
def test_features_land_where_the_mapping_says(shape, center, radius, size, exact):
    p = Preprocessor(*center, radius, size, exact=exact)
    cx, cy = center
    for dx, dy in [(0, 0), (0.5 * radius, 0.0), (-0.3 * radius, 0.4 * radius)]:
        spot_r = max(radius / 12, 3)
        frame = disk_frame(shape, cx + dx, cy + dy, spot_r)
        gray = p.crop(frame)[..., 1].astype(float)
        u, v = centroid(gray)
        eu, ev = p.to_model(cx + dx, cy + dy)
        assert abs(u - eu) < 0.35 and abs(v - ev) < 0.35, (dx, dy, u, v, eu, ev)
    x, y = p.to_raw(*p.to_model(123.4, 56.7))
    assert x == pytest.approx(123.4) and y == pytest.approx(56.7)


def test_exact_mode_is_a_single_inter_area_of_the_masked_window():
    shape, (cx, cy), r, size = (480, 640), (320.0, 240.0), 200.0, 128
    rng = np.random.default_rng(1)
    frame = rng.integers(0, 256, shape + (3,), dtype=np.uint8)
    p = Preprocessor(cx, cy, r, size, exact=True)
    n = p.window
    assert n == 400
    win = frame[p.y0:p.y0 + n, p.x0:p.x0 + n].copy()
    yy, xx = np.mgrid[p.y0:p.y0 + n, p.x0:p.x0 + n]
    win[(xx - cx) ** 2 + (yy - cy) ** 2 > r ** 2] = 0
    expect = cv2.resize(win, (size, size), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(p.crop(frame), expect)


def test_fast_path_matches_single_inter_area_on_smooth_image():
    shape, center, r, size = (480, 640), (318.2, 244.7), 221.0, 128
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    frame = np.stack([(127 + 100 * np.sin(xx / 37.0 + c) * np.cos(yy / 23.0)) for c in range(3)], -1)
    frame = frame.astype(np.uint8)
    fast = Preprocessor(*center, r, size).crop(frame).astype(float)
    exact = Preprocessor(*center, r, size, exact=True).crop(frame).astype(float)
    inner = np.hypot(*np.mgrid[-63.5:64.5, -63.5:64.5]) < 60  # away from the rim
    assert np.abs(fast - exact)[inner].mean() < 2.0  # 0-255 levels


def test_circle_partly_outside_frame_is_padded_with_zeros():
    shape = (480, 640)
    frame = np.full(shape + (3,), 255, np.uint8)
    p = Preprocessor(600.0, 240.0, 200.0, 64)  # right half of the circle is off the frame
    small = p.crop(frame)[..., 0]
    u_edge, _ = p.to_model(shape[1] - 1, 240)
    assert small[32, int(np.ceil(u_edge)) + 1:].max() == 0
    assert small[32, 5:int(u_edge) - 1].min() == 255


def test_bad_calibration_and_frames_are_clear_errors():
    with pytest.raises(CalibrationError, match="radius"):
        Preprocessor(10, 10, 0, 128)
    with pytest.raises(CalibrationError, match="outside"):
        Preprocessor(5000, 5000, 100, 128).apply(np.zeros((480, 640, 3), np.uint8))
    p = Preprocessor(320, 240, 200, 128)
    with pytest.raises(CaptureError, match="uint8"):
        p.apply(np.zeros((480, 640, 3), np.float32))
    with pytest.raises(CaptureError, match="expected"):
        p.apply(np.zeros((480, 640), np.uint8))


def test_precomputed_once_per_frame_size():
    p = Preprocessor(320, 240, 200, 64)
    frame = np.zeros((480, 640, 3), np.uint8)
    p.apply(frame)
    mask, buf = p._mask, p._buf
    p.apply(frame + 1)
    assert p._mask is mask and p._buf is buf
    p.apply(np.zeros((600, 800, 3), np.uint8))  # camera switched resolution: recomputed
    assert p._buf is not buf


def test_non_square_model_size():
    p = Preprocessor(320, 240, 200, (96, 128))
    assert p.apply(np.zeros((480, 640, 3), np.uint8)).shape == (3, 96, 128)


def test_model_input_stacks_baseline_then_current():
    base = np.full((3, 8, 8), 0.25, np.float32)
    cur = np.full((3, 8, 8), 0.75, np.float32)
    x = model_input(base, cur)
    assert x.shape == (1, 6, 8, 8) and x.dtype == np.float32 and x.flags.c_contiguous
    assert np.all(x[0, :3] == 0.25) and np.all(x[0, 3:] == 0.75)
    with pytest.raises(CaptureError):
        model_input(base, cur[:, :4])
    u8 = np.arange(2 * 2 * 3, dtype=np.uint8).reshape(2, 2, 3)
    np.testing.assert_allclose(to_chw_float(u8), u8.transpose(2, 0, 1) / 255.0, rtol=1e-6)
