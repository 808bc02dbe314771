"""What a ROS test does when rclpy or the project's messages cannot be imported.

Locally it skips with the reason. In CI (``CI=true``, as GitHub Actions / GitLab set it) it
fails: a broken ROS build must not leave CI green with the node graph untested.
"""
import os

import pytest

HINT = "build them with msg_defs/build.sh (./run.sh setup) and run with the venv's python"


def in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def ros_unavailable(why: str, module_level: bool = False) -> None:
    """Skip (locally) or fail (CI) a ROS test because rclpy / splat_slam_msgs are missing."""
    msg = f"rclpy / splat_slam_msgs not importable ({why}); {HINT}"
    if in_ci():
        pytest.fail(f"CI=true and the ROS tests cannot run: {msg}", pytrace=False)
    pytest.skip(msg, allow_module_level=module_level)
