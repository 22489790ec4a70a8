"""The contracts every part of TensorTouch shares: errors, units, field channels, the session
format, the wire formats (ours and ROS 2's), the CAN frame, the calibration store and its
files and locations. Imports nothing of ours; drivers import only this.
"""
