"""Pure core of `tensortouch view`: field channel → colour map image + legend, contacts → JSON.

Arrays in, arrays/dicts out; no network, no HTTP. Signed channels use a symmetric diverging map
(blue–white–red, zero = white) so a sign is readable at a glance; magnitudes use a sequential map.
"""
from __future__ import annotations

import base64
import logging

import numpy as np

log = logging.getLogger(__name__)

def _lut(stops: list[tuple[float, tuple[int, int, int]]], n: int = 256) -> np.ndarray:
    x = np.linspace(0.0, 1.0, n)
    pos = np.array([s[0] for s in stops])
    cols = np.array([s[1] for s in stops], dtype=float)
    return np.stack([np.interp(x, pos, cols[:, k]) for k in range(3)], 1).round().astype(np.uint8)


DIVERGING = _lut([(0.0, (33, 62, 140)), (0.25, (80, 140, 210)), (0.5, (247, 247, 247)),
                  (0.75, (225, 110, 80)), (1.0, (150, 20, 30))])
SEQUENTIAL = _lut([(0.0, (12, 7, 40)), (0.3, (90, 20, 110)), (0.6, (210, 70, 60)),
                   (0.85, (250, 170, 40)), (1.0, (252, 250, 190))])


# the wire channels each derived channel is computed from (looked up by name, in any order)
DERIVED_FROM = {"disp_mag": ("disp_x", "disp_y", "disp_z"),
                "traction_mag": ("fn_x", "fn_y", "fn_z", "fs_x", "fs_y", "fs_z")}


class ChannelAbsent(KeyError):
    """The chosen channel is not in what the sensor publishes (or a derived one lacks a component)."""

    def __str__(self) -> str:
        return str(self.args[0])


def available(channels) -> list[str]:
    """The wire channels a frame carries plus the derived ones it has every component of."""
    channels = list(channels)
    return channels + [d for d, need in DERIVED_FROM.items() if all(c in channels for c in need)]


def _pick(data: np.ndarray, channels: list, names) -> np.ndarray:
    return np.stack([data[channels.index(n)] for n in names])


def channel_data(data: np.ndarray, channels, units, name: str) -> tuple[np.ndarray, str, bool]:
    """(H, W) values, unit, signed? for a wire channel name or a derived one; ChannelAbsent when the
    frame does not carry it (or a component of it)."""
    channels = list(channels)
    if name in DERIVED_FROM:
        missing = [c for c in DERIVED_FROM[name] if c not in channels]
        if missing:
            raise ChannelAbsent(f"channel {name!r} is absent: this sensor does not publish {', '.join(missing)}")
        if name == "disp_mag":
            return np.linalg.norm(_pick(data, channels, DERIVED_FROM[name]), axis=0), "mm", False
        parts = _pick(data, channels, DERIVED_FROM[name])
        return np.linalg.norm(parts[:3] + parts[3:], axis=0), "MPa", False
    if name not in channels:
        raise ChannelAbsent(f"channel {str(name)[:40]!r} is absent: this sensor publishes {', '.join(available(channels))}")
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
           "contacts": [], "channels": available(fields.channels)}
    if contacts is not None:
        out["contacts"] = [{"id": c.id, "uv_px": list(c.uv_px), "position_mm": list(c.position_mm),
                            "normal": list(c.normal), "force_n": list(c.force_n), "force_mag_n": c.force_mag_n,
                            "area_mm2": c.area_mm2, "age_frames": c.age_frames} for c in contacts.contacts]
        out["contacts_seq"] = contacts.seq
    if grid is not None:
        out["grid_values"] = np.round(downsample(values, grid), 6).ravel().tolist()
        names = DERIVED_FROM["disp_mag"]
        disp = (np.moveaxis(_pick(fields.data, list(fields.channels), names), 0, -1)
                if all(n in fields.channels for n in names) else np.zeros((h, w, 3), np.float32))
        out["grid_disp_mm"] = np.round(downsample(disp, grid), 5).reshape(-1).tolist()
    return out


def checked_surface(geo, max_side: int) -> dict:
    """A sensor's info `gel_surface` as the page draws it, or ValueError naming what is wrong: `grid`
    [gh, gw] integers in 2..max_side, `xyz_mm` gh*gw*3 numbers within +-1000 mm (null off the gel),
    `mask` gh*gw booleans. Only these members are kept."""
    if not isinstance(geo, dict):
        raise ValueError(f"gel_surface is a {type(geo).__name__}, expected an object")
    grid = geo.get("grid")
    if not (isinstance(grid, list) and len(grid) == 2
            and all(isinstance(n, int) and not isinstance(n, bool) and 2 <= n <= max_side for n in grid)):
        raise ValueError(f"gel_surface grid {str(grid)[:40]}: expected [rows, cols], each 2..{max_side}")
    n = grid[0] * grid[1]
    xyz, mask = geo.get("xyz_mm"), geo.get("mask")
    if not (isinstance(xyz, list) and len(xyz) == 3 * n
            and all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool) and abs(v) <= 1000.0)
                    for v in xyz)):
        raise ValueError(f"gel_surface xyz_mm: expected {3 * n} numbers in mm for grid {grid}")
    if not (isinstance(mask, list) and len(mask) == n and all(isinstance(v, bool) for v in mask)):
        raise ValueError(f"gel_surface mask: expected {n} booleans for grid {grid}")
    return {"grid": list(grid), "xyz_mm": xyz, "mask": mask, "nominal": False}


def lut_json() -> dict:
    return {"diverging": DIVERGING.tolist(), "sequential": SEQUENTIAL.tolist()}
