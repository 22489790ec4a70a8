"""What runs the pipeline live: the frame loop, the whole hand, the Zenoh publisher and
subscriber, ROS 2 mode and where processes meet.
"""
