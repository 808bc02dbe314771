"""Topic table shared by the DDS test scripts (import after apply_ros_environment())."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

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
