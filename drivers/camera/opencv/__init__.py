"""Live camera through OpenCV (CAP_V4L2 with MJPG by default)."""
from .camera import OpenCVCamera
from .config import OpenCVCameraConfig

__all__ = ["OpenCVCamera", "OpenCVCameraConfig"]
