"""The ROS 2 side: nodes, message conversions, parameter descriptors (imports rclpy)."""
