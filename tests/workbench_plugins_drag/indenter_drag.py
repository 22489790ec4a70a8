"""A user-written effect plugin (the guide's example): the F/T reads a drag on the moving indenter.

Drop this file in a folder and pass the folder with --plugins (or TENSORTOUCH_EFFECTS_PATH).
"""
import numpy as np
from tensortouch.runtime.stages.effects import Effect, Param, need


class IndenterDrag(Effect):
    name = "indenter_drag"
    summary = "a force on the indenter against its velocity (cable, air, bearing)"
    words = "the reference reads a drag on the moving indenter"
    equation = "F_ref = F - c v"
    stage = "measurement"
    params = (Param("c", "N s/mm", 0.0005, 0.0, 0.05, "drag per unit of indenter velocity", "c"),)
    covariates = ("vel_x", "vel_y", "vel_z")
    off = {"c": 0.0}  # noqa: RUF012 (the plugin contract writes class attributes)
    linear = True

    def forward(self, x, cov, p):
        v = np.column_stack([need(cov, k, self.name) for k in ("vel_x", "vel_y", "vel_z")])
        return np.asarray(x, dtype=np.float64) - p["c"] * v
