"""A subscriber for tests/test_graph_tf.py: decodes /tf, /tf_static, /splat/camera_pose,
/splat/odometry, /splat/pose_graph_updates and /splat/keyframe_markers of a running graph and
prints one JSON line per message (transforms as [parent, child, stamp_ns, tx, ty, tz, qx, qy,
qz, qw])."""
import json
import sys
import time

from splat_slam_ros.ros_env import apply_ros_environment

apply_ros_environment()
import rclpy  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from splat_slam_msgs.msg import PoseGraphUpdate  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from splat_slam_nodes import qos as Q  # noqa: E402
from splat_slam_nodes.node_common import TOPICS  # noqa: E402
from splat_slam_nodes.tf_frames import tf_qos, tf_static_qos  # noqa: E402


def ns(st) -> int:
    return st.sec * 1_000_000_000 + st.nanosec


def emit(d: dict) -> None:
    d["t"] = time.monotonic()
    print(json.dumps(d), flush=True)


def on_tf(topic):
    def cb(m):
        emit({"topic": topic, "tf": [
            [t.header.frame_id, t.child_frame_id, ns(t.header.stamp),
             t.transform.translation.x, t.transform.translation.y, t.transform.translation.z,
             t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
             t.transform.rotation.w] for t in m.transforms]})
    return cb


def main() -> None:
    duration = float(sys.argv[1]) if len(sys.argv) > 1 else 600.0
    rclpy.init()
    node = rclpy.create_node("tf_probe")
    node.create_subscription(TFMessage, "/tf", on_tf("/tf"), tf_qos())
    node.create_subscription(TFMessage, "/tf_static", on_tf("/tf_static"), tf_static_qos())

    def on_pose(m):
        p = m.pose
        emit({"topic": "pose", "frame": m.header.frame_id, "stamp": ns(m.header.stamp),
              "p": [p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y,
                    p.orientation.z, p.orientation.w]})
    node.create_subscription(PoseStamped, TOPICS["camera_pose"], on_pose, Q.pose_qos())

    def on_odom(m):
        p, v = m.pose.pose, m.twist.twist
        emit({"topic": "odom", "frame": m.header.frame_id, "child": m.child_frame_id,
              "stamp": ns(m.header.stamp),
              "p": [p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y,
                    p.orientation.z, p.orientation.w],
              "v": [v.linear.x, v.linear.y, v.linear.z, v.angular.x, v.angular.y, v.angular.z]})
    node.create_subscription(Odometry, TOPICS["odometry"], on_odom, Q.pose_qos())
    node.create_subscription(PoseGraphUpdate, TOPICS["updates"],
                             lambda m: emit({"topic": "update", "reason": m.reason,
                                             "seq": int(m.seq)}), Q.pose_graph_qos())
    node.create_subscription(MarkerArray, TOPICS["keyframe_markers"],
                             lambda m: emit({"topic": "markers", "types": [
                                 [int(k.type), int(k.action)] for k in m.markers],
                                 "frame": m.markers[-1].header.frame_id if m.markers else ""}),
                             Q.status_qos())
    emit({"topic": "probe", "ready": True})
    t_end = time.monotonic() + duration
    try:
        while rclpy.ok() and time.monotonic() < t_end:
            rclpy.spin_once(node, timeout_sec=0.05)
    except (KeyboardInterrupt, Exception):        # SIGTERM/SIGINT shut the context down
        pass
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
