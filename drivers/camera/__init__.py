"""Camera layer: one small interface (`Camera`), a config dataclass per backend, a factory.

    from tensortouch.drivers.camera import camera_from_uri
    with camera_from_uri("replay:runtime/demo?loop=1") as cam:
        frame = cam.read()          # Frame(image=(H, W, 3) uint8 RGB, t=s, index)

See docs/capture.md.
"""
from .camera import Camera, CameraConfig, EndOfStream, Frame
from .factory import SOURCE_FORMS, camera_from_uri, config_from_uri, make_camera
from .opencv import OpenCVCamera, OpenCVCameraConfig
from .replay import ReplayCamera, ReplayCameraConfig

__all__ = ["Camera", "CameraConfig", "EndOfStream", "Frame", "OpenCVCamera", "OpenCVCameraConfig",
           "ReplayCamera", "ReplayCameraConfig", "SOURCE_FORMS", "camera_from_uri", "config_from_uri",
           "make_camera"]
