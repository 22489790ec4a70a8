"""The rim re-centring core lives in runtime/rim.py (`tensortouch calib init` needs it in a deploy
install); this module keeps the recalibration's import path."""
from runtime.rim import (
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
