"""ROS 2 side of nsflow_ros: the ``tracker`` node, image decoding and the node benchmark.

Importing this package imports no rclpy; the node modules do.
"""
