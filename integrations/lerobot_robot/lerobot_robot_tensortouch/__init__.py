"""A TensorTouch sensor as a sensor-only LeRobot robot (type "tensortouch").

LeRobot imports this package when the distribution is installed (its third-party plugin discovery);
importing it registers the robot config, and `make_robot_from_config` then builds `TensorTouchRobot`
from a `TensorTouchRobotConfig`.
"""
from .config_tensortouch import TensorTouchRobotConfig
from .tensortouch import TensorTouchRobot

__all__ = ["TensorTouchRobot", "TensorTouchRobotConfig"]
