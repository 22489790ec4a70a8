"""`tensortouch view` colour-map core (tools/view/render.py): maps, ranges, derived channels, downsampling."""
import base64

import cv2
import numpy as np
import pytest
from tensortouch.contracts.wire import FieldsFrame
from tensortouch.tools.view.render import DIVERGING, SEQUENTIAL, channel_data, colorize, downsample, frame_view, value_range


def test_colour_maps_and_ranges():
    v = np.array([[-2.0, 0.0, 2.0, np.nan]])
    lo, hi = value_range(v, signed=True)
    assert (lo, hi) == (-2.0, 2.0)
    rgb = colorize(v, lo, hi, signed=True)
    assert tuple(rgb[0, 0]) == tuple(DIVERGING[0]) and tuple(rgb[0, 2]) == tuple(DIVERGING[-1])
    assert tuple(rgb[0, 1]) == tuple(DIVERGING[128]) and rgb[0, 1].min() > 240     # zero is white
    assert tuple(rgb[0, 3]) == (128, 128, 128)                                   # NaN is grey
    assert value_range(np.abs(v), signed=False) == (0.0, 2.0)
    assert tuple(colorize(np.array([[3.0]]), 0, 2, False)[0, 0]) == tuple(SEQUENTIAL[-1])   # clipped


def test_derived_channels_and_downsample():
    rng = np.random.default_rng(0)
    data = rng.normal(size=(15, 8, 8)).astype(np.float32)
    from tensortouch.contracts.fields import CHANNEL_UNITS, CHANNELS

    mag, unit, signed = channel_data(data, CHANNELS, CHANNEL_UNITS, "traction_mag")
    np.testing.assert_allclose(mag, np.linalg.norm(data[9:12] + data[12:15], axis=0), rtol=1e-6)
    assert unit == "MPa" and not signed
    z, unit, signed = channel_data(data, CHANNELS, CHANNEL_UNITS, "disp_z")
    assert unit == "mm" and signed and np.array_equal(z, data[2])
    with pytest.raises(KeyError, match="nope"):
        channel_data(data, CHANNELS, CHANNEL_UNITS, "nope")
    d = downsample(data[0], (4, 4))
    assert d.shape == (4, 4) and d[1, 2] == pytest.approx(data[0, 2:4, 4:6].mean())
    f = FieldsFrame("S", 3, 1.5, data)
    out = frame_view(f, None, "fn_z", (4, 4))
    img = cv2.imdecode(np.frombuffer(base64.b64decode(out["png"]), np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (8, 8, 3) and out["unit"] == "MPa" and len(out["grid_values"]) == 16
    assert len(out["grid_disp_mm"]) == 48 and out["vmin"] == -out["vmax"]
