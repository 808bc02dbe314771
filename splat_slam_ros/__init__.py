"""splat_slam_ros: the ROS-free core library of Splat-SLAM (importable without rclpy)."""
import os as _os

__version__ = "0.1.0"

# Idle OpenMP threads sleep instead of spinning. libgomp reads this once, when torch loads it,
# so it is set here, before any submodule imports torch; the nodes get the same value from
# ros_env.ros_environment(). Without it the in-process pipeline (splat-slam-run) spent 2.6x
# the CPU and 3x the wall time of the same mapping work on a loaded 2-core machine
# (measured: 19.4 vs 7.5 CPU-s) - the in-process vs mapper-node gap
# (docs/mapping.md "OpenMP wait policy").
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
