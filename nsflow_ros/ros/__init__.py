"""ROS 2 side of nsflow_ros: the ``tracker`` node and its parameter table, the replay node, image decoding,
clean shutdown on signals, the DDS transport profile and the node benchmark.

Importing this package imports no rclpy; the node modules do.
"""
