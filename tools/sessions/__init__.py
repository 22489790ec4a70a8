"""Session I/O beyond the runtime contract: the session writer and ROS1/ROS2 bag and MCAP readers."""
