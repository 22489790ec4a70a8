"""TensorTouch for LeRobot: fields as a camera (type "tensortouch"), wrench and top-K contacts as floats.

LeRobot imports this package when the distribution is installed (its third-party plugin discovery);
importing it registers the camera config, and `make_cameras_from_configs` then builds
`TensorTouchCamera` from a `TensorTouchCameraConfig`. Both readers here share reading.ZenohReader;
the sensor-only robot (distribution lerobot_robot_tensortouch) builds on `TensorTouchTactile`.
"""
from .camera_tensortouch import TensorTouchCamera
from .configuration_tensortouch import TensorTouchCameraConfig
from .scale import FULL_SCALE, from_image, to_image
from .tactile import TensorTouchTactile, TensorTouchTactileConfig, feature_names

__all__ = ["FULL_SCALE", "TensorTouchCamera", "TensorTouchCameraConfig", "TensorTouchTactile",
           "TensorTouchTactileConfig", "feature_names", "from_image", "to_image"]
