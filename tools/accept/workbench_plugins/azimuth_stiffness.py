"""A user-written effect plugin (the walkthrough's example): the gel is stiffer on one side.

Drop this file in a folder and pass the folder with --plugins (or TENSORTOUCH_EFFECTS_PATH).
"""
import numpy as np
from tensortouch.runtime.stages.effects import Effect, Param, need, scale_rows


class AzimuthStiffness(Effect):
    name = "azimuth_stiffness"
    summary = "gel thickness/stiffness varies around the dome"
    words = "gel is stiffer on one side"
    equation = "F = F0 * (1 + a * cos(phi - phi0))"
    params = (Param("a", "-", 0.1, 0.0, 1.0, "relative stiffness change", "a"),
              Param("phi0", "rad", 0.0, -3.1416, 3.1416, "azimuth of the stiffest side", "φ0"))
    covariates = ("phi",)
    off = {"a": 0.0}

    def forward(self, x, cov, p):
        phi = need(cov, "phi", self.name)
        return scale_rows(x, 1.0 + p["a"] * np.cos(phi - p["phi0"]))
