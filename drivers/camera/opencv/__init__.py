"""Live camera through OpenCV (CAP_V4L2 with MJPG by default)."""
from drivers.camera.opencv.camera import OpenCVCamera
from drivers.camera.opencv.config import OpenCVCameraConfig

__all__ = ["OpenCVCamera", "OpenCVCameraConfig"]
