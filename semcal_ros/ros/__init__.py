"""The ROS 2 door into the library: message conversions, QoS, parameters and the nodes.

Only this package imports rclpy and message types; everything it hands on is a library type.
"""
