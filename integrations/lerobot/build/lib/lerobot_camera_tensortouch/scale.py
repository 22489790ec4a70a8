"""Fixed full scale per field channel: how a field becomes an 8-bit image channel.

    pixel = clip(128 + 127 · value / full_scale, 0, 255)      (value 0 → 128, ±full scale → 1 / 255)

The scales are fixed (not per frame), so the same pixel value means the same physical value in every
frame and every recording. They cover the shipped model's output bounds (exported_models/*/manifest.json).
"""
from __future__ import annotations

import numpy as np

FULL_SCALE = {
    "disp_x": 2.5, "disp_y": 2.5, "disp_z": 2.5,                 # mm
    "sigma_xx": 0.25, "sigma_yy": 0.25, "sigma_zz": 0.25,       # MPa
    "sigma_xy": 0.25, "sigma_xz": 0.25, "sigma_yz": 0.25,       # MPa
    "fn_x": 0.25, "fn_y": 0.25, "fn_z": 0.25,                   # MPa (contact normal traction)
    "fs_x": 0.25, "fs_y": 0.25, "fs_z": 0.25,                   # MPa (contact shear traction)
}


def to_image(data: np.ndarray, channels: tuple[str, ...] | list[str], pick: tuple[str, str, str]) -> np.ndarray:
    """(C, H, W) fields in physical units → (H, W, 3) uint8 with the three `pick` channels as R, G, B."""
    planes = []
    for name in pick:
        if name not in FULL_SCALE:
            raise ValueError(f"channel {name!r}: expected one of {sorted(FULL_SCALE)}")
        try:
            plane = data[list(channels).index(name)]
        except ValueError:
            raise ValueError(f"channel {name!r} is not in the published fields {list(channels)}") from None
        planes.append(128.0 + 127.0 * np.asarray(plane, np.float32) / FULL_SCALE[name])
    return np.clip(np.rint(np.stack(planes, axis=-1)), 0, 255).astype(np.uint8)


def from_image(image: np.ndarray, pick: tuple[str, str, str]) -> np.ndarray:
    """The inverse (to 1/127 of full scale): (H, W, 3) uint8 → (3, H, W) float32 physical values."""
    scale = np.array([FULL_SCALE[n] for n in pick], np.float32)
    return ((np.asarray(image, np.float32) - 128.0) / 127.0 * scale).transpose(2, 0, 1)
