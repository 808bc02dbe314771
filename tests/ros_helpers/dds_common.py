"""Shared by the DDS test scripts: importing it applies the project's ROS environment, so
import it before rclpy. Topic table and argument parsing."""
import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from splat_slam_ros.ros_env import apply_ros_environment  # noqa: E402

apply_ros_environment()

KINDS = ("keyframe", "pose_graph", "proxy_depth", "image")


def topic_types():
    from sensor_msgs.msg import Image
    from splat_slam_msgs.msg import Keyframe, PoseGraphUpdate, ProxyDepth
    from splat_slam_nodes import qos
    return {
        "keyframe": (Keyframe, qos.keyframe_qos()),
        "pose_graph": (PoseGraphUpdate, qos.pose_graph_qos()),
        "proxy_depth": (ProxyDepth, qos.proxy_depth_qos()),
        "image": (Image, qos.image_qos()),
    }


def topic_name(ns: str, kind: str) -> str:
    return f"/{ns}/{kind}"


def parse_args(**options):
    """``--ns NAME`` plus ``--OPTION`` (dashes for underscores) with the given defaults,
    typed like the default."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--ns", required=True)
    for name, default in options.items():
        ap.add_argument("--" + name.replace("_", "-"), type=type(default), default=default)
    return ap.parse_args()
