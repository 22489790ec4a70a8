"""Pure core of `tensortouch view`: field channel → colour map image + legend, contacts → JSON.

Arrays in, arrays/dicts out; no network, no HTTP. Signed channels use a symmetric diverging map
(blue–white–red, zero = white) so a sign is readable at a glance; magnitudes use a sequential map.
"""
from __future__ import annotations

import base64
import logging

import numpy as np

log = logging.getLogger(__name__)

DERIVED = {"disp_mag": ("mm", (0, 1, 2)), "traction_mag": ("MPa", "traction")}


def _lut(stops: list[tuple[float, tuple[int, int, int]]], n: int = 256) -> np.ndarray:
    x = np.linspace(0.0, 1.0, n)
    pos = np.array([s[0] for s in stops])
    cols = np.array([s[1] for s in stops], dtype=float)
    return np.stack([np.interp(x, pos, cols[:, k]) for k in range(3)], 1).round().astype(np.uint8)


DIVERGING = _lut([(0.0, (33, 62, 140)), (0.25, (80, 140, 210)), (0.5, (247, 247, 247)),
                  (0.75, (225, 110, 80)), (1.0, (150, 20, 30))])
SEQUENTIAL = _lut([(0.0, (12, 7, 40)), (0.3, (90, 20, 110)), (0.6, (210, 70, 60)),
                   (0.85, (250, 170, 40)), (1.0, (252, 250, 190))])


def channel_data(data: np.ndarray, channels, units, name: str) -> tuple[np.ndarray, str, bool]:
    """(H, W) values, unit, signed? for a wire channel name or a derived one."""
    channels = list(channels)
    if name == "disp_mag":
        return np.linalg.norm(data[0:3], axis=0), "mm", False
    if name == "traction_mag":
        fn = data[channels.index("fn_x"):channels.index("fn_x") + 3]
        fs = data[channels.index("fs_x"):channels.index("fs_x") + 3]
        return np.linalg.norm(fn + fs, axis=0), "MPa", False
    if name not in channels:
        raise KeyError(f"channel {name!r}: expected one of {channels + list(DERIVED)}")
    k = channels.index(name)
    return data[k], units[k], True


def value_range(values: np.ndarray, signed: bool, floor: float = 1e-9) -> tuple[float, float]:
    """Colour scale: symmetric [-m, m] for signed channels, [0, max] for magnitudes (NaN ignored)."""
    finite = values[np.isfinite(values)]
    m = float(np.max(np.abs(finite))) if finite.size else 0.0
    m = max(m, floor)
    return (-m, m) if signed else (0.0, m)


def colorize(values: np.ndarray, vmin: float, vmax: float, signed: bool) -> np.ndarray:
    """(H, W) floats → (H, W, 3) uint8 RGB; NaN → mid grey."""
    lut = DIVERGING if signed else SEQUENTIAL
    span = max(vmax - vmin, 1e-12)
    idx = np.clip((np.nan_to_num(values, nan=np.nan) - vmin) / span, 0.0, 1.0)
    nan = ~np.isfinite(idx)
    idx = np.where(nan, 0.5, idx)
    rgb = lut[(idx * (len(lut) - 1)).round().astype(int)]
    rgb[nan] = (128, 128, 128)
    return rgb


def png_base64(rgb: np.ndarray) -> str:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise ValueError("PNG encoding failed")
    return base64.b64encode(buf.tobytes()).decode("ascii")


def downsample(values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Block-mean (H, W[, C]) down to `shape` (H and W divisible by it, else nearest sampling)."""
    h, w = values.shape[:2]
    gh, gw = shape
    if h % gh == 0 and w % gw == 0:
        return values.reshape(gh, h // gh, gw, w // gw, *values.shape[2:]).mean(axis=(1, 3))
    ys = (np.arange(gh) * h / gh).astype(int)
    xs = (np.arange(gw) * w / gw).astype(int)
    return values[ys][:, xs]


def frame_view(fields, contacts, channel: str, grid: tuple[int, int] | None = None) -> dict:
    """FieldsFrame (+ ContactsFrame or None) → JSON-ready dict for the page."""
    values, unit, signed = channel_data(fields.data, fields.channels, fields.units, channel)
    vmin, vmax = value_range(values, signed)
    h, w = values.shape
    out = {"sensor_id": fields.sensor_id, "seq": fields.seq, "t": fields.t, "channel": channel, "unit": unit,
           "signed": signed, "vmin": vmin, "vmax": vmax, "width": w, "height": h,
           "png": png_base64(colorize(values, vmin, vmax, signed)), "clipped": list(fields.clipped),
           "contacts": [], "channels": list(fields.channels) + list(DERIVED)}
    if contacts is not None:
        out["contacts"] = [{"id": c.id, "uv_px": list(c.uv_px), "position_mm": list(c.position_mm),
                            "normal": list(c.normal), "force_n": list(c.force_n), "force_mag_n": c.force_mag_n,
                            "area_mm2": c.area_mm2, "age_frames": c.age_frames} for c in contacts.contacts]
        out["contacts_seq"] = contacts.seq
    if grid is not None:
        out["grid_values"] = np.round(downsample(values, grid), 6).ravel().tolist()
        disp = np.moveaxis(fields.data[0:3], 0, -1)
        out["grid_disp_mm"] = np.round(downsample(disp, grid), 5).reshape(-1).tolist()
    return out


def lut_json() -> dict:
    return {"diverging": DIVERGING.tolist(), "sequential": SEQUENTIAL.tolist()}
