"""The ROS 2 layer: nodes, message conversions, parameters and markers.

Everything that imports rclpy or the generated messages lives here; the numpy
core (``sonar_ring.geometry``, ``localise``, ...) never does.
"""
