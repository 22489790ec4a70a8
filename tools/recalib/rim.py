"""The rim re-centring core lives in runtime/calib/rim.py (`tensortouch calib init` needs it in a deploy
install); this module keeps the recalibration's import path."""
from ...runtime.calib.rim import (
                         RimConfig,
                         RimFit,
                         circle_lsq,
                         crop_changes,
                         edge_points,
                         fit_rim,
                         recrop,
                         rest_image,
)

__all__ = ["RimConfig", "RimFit", "circle_lsq", "crop_changes", "edge_points", "fit_rim", "recrop", "rest_image"]
