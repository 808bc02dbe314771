"""rerun logger node: optional (rerun-sdk is an extra). Without it: a clear error, exit 2
(the node and splat-slam-launch --rerun); with it: a .rrd file gets written."""
import importlib.util
import subprocess
import time

import numpy as np
import pytest

from test_graph_support import PY, isolated_env, need_ros, start, stop, wait_for

pytestmark = pytest.mark.ros
HAVE_RERUN = importlib.util.find_spec("rerun") is not None


@pytest.mark.skipif(HAVE_RERUN, reason="rerun-sdk is installed")
def test_missing_rerun_is_a_clear_error(tmp_path):
    need_ros()
    env = isolated_env()
    r = subprocess.run([PY, "-m", "splat_slam_nodes.rerun_logger", "--ros-args", "-p",
                        f"node.rrd:={tmp_path / 'x.rrd'}"], env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2
    assert "needs the optional rerun-sdk package" in r.stdout + r.stderr
    bag = tmp_path / "bag"
    from test_graph_support import write_tiny_bag
    write_tiny_bag(bag, n=2)
    r = subprocess.run([PY, "-m", "splat_slam_nodes.launch", "--bag", str(bag), "--out",
                        str(tmp_path / "out"), "--rerun", str(tmp_path / "x.rrd")], env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "error: --rerun needs the optional rerun-sdk" in r.stderr


FEED = r'''
import sys, time
from splat_slam_ros.ros_env import apply_ros_environment
apply_ros_environment()
import numpy as np, rclpy
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import PointCloud2
from splat_slam_msgs.msg import Keyframe
from splat_slam_nodes import convert, qos as Q
from splat_slam_nodes.node_common import TOPICS, pointcloud2, pose_stamped
from splat_slam_ros.types import Intrinsics, KeyframeData
rclpy.init(); n = rclpy.create_node("feed")
pk = n.create_publisher(Keyframe, TOPICS["keyframes"], Q.keyframe_qos())
pp = n.create_publisher(PoseStamped, TOPICS["camera_pose"], Q.pose_qos())
pc = n.create_publisher(PointCloud2, TOPICS["points"], Q.status_qos())
t0 = time.monotonic()
while pk.get_subscription_count() == 0 and time.monotonic() - t0 < 60:
    rclpy.spin_once(n, timeout_sec=0.05)
time.sleep(0.5)
K = Intrinsics(40, 40, 31.5, 23.5, 64, 48)
img = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
pk.publish(convert.keyframe_to_msg(KeyframeData(0, 0, 1.0, np.eye(4), img, K,
           np.ones((6, 8), np.float32), np.ones((6, 8), np.float32))))
pp.publish(pose_stamped(np.eye(4), 1.0, "map"))
pc.publish(pointcloud2(np.random.rand(100, 3), np.zeros((100, 3), np.uint8), 1.0, "map"))
time.sleep(2.0)
rclpy.try_shutdown()
'''


@pytest.mark.skipif(not HAVE_RERUN, reason="rerun-sdk not installed (optional extra)")
def test_rerun_logger_writes_rrd(tmp_path):
    need_ros()
    env = isolated_env()
    rrd = tmp_path / "run.rrd"
    node = start([PY, "-m", "splat_slam_nodes.rerun_logger", "--ros-args", "-p",
                  f"node.rrd:={rrd}"], env, tmp_path / "rerun.log")
    feed = start([PY, "-c", FEED], env, tmp_path / "feed.log")
    try:
        assert feed.wait(timeout=120) == 0, (tmp_path / "feed.log").read_text()
    finally:
        stop(feed)
        stop(node)
    assert rrd.is_file() and rrd.stat().st_size > 1000, (tmp_path / "rerun.log").read_text()
