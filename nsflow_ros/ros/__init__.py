"""ROS 2 side of nsflow_ros: the ``tracker`` and replay nodes and what they share.

Importing this package imports no rclpy; the node modules do.
"""
