"""The 15 field channels (docs/fields.md): names, units and modality groups, in model output order."""
from __future__ import annotations

CHANNELS = (
    "disp_x", "disp_y", "disp_z",
    "sigma_xx", "sigma_yy", "sigma_zz",
    "sigma_xy", "sigma_xz", "sigma_yz",
    "fn_x", "fn_y", "fn_z",
    "fs_x", "fs_y", "fs_z",
)
CHANNEL_UNITS = ("mm",) * 3 + ("MPa",) * 12

# The seed's five modalities, each a consecutive triple of channels.
MODALITIES = {
    "displacement": slice(0, 3),
    "normal_stress": slice(3, 6),
    "shear_stress": slice(6, 9),
    "contact_normal": slice(9, 12),
    "contact_shear": slice(12, 15),
}
N_CHANNELS = len(CHANNELS)
INPUT_CHANNELS = ("baseline_r", "baseline_g", "baseline_b", "current_r", "current_g", "current_b")
