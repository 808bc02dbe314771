"""splat_slam_ros: the ROS-free core library of Splat-SLAM (importable without rclpy)."""
__version__ = "0.1.0"
