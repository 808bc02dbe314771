"""rerun logger node: a feed process publishes every kind of message it logs (the camera as
image_transport's compressed topic); the .rrd it writes is read back with rerun's own reader
and holds the expected entities and data."""
import socket
import time
from pathlib import Path

import pytest

from test_graph_support import PY, isolated_env, need_ros, start, stop

pytestmark = pytest.mark.ros

FEED = r'''
import sys, time
from splat_slam_ros.ros_env import apply_ros_environment
apply_ros_environment()
import numpy as np, rclpy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
import cv2
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from splat_slam_msgs.msg import Keyframe, PoseGraphUpdate
from splat_slam_nodes import convert, qos as Q
from splat_slam_nodes.node_common import TOPICS, path_msg, pointcloud2, pose_stamped
from splat_slam_ros.types import Intrinsics, KeyframeData, UpdateEvent
rclpy.init(); n = rclpy.create_node("feed")
pk = n.create_publisher(Keyframe, TOPICS["keyframes"], Q.keyframe_qos())
pu = n.create_publisher(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos())
pp = n.create_publisher(PoseStamped, TOPICS["camera_pose"], Q.pose_qos())
pt = n.create_publisher(Path, TOPICS["trajectory"], Q.status_qos())
pc = n.create_publisher(PointCloud2, TOPICS["points"], Q.status_qos())
pr = n.create_publisher(Image, TOPICS["rendered_rgb"], Q.rendered_qos())
pd = n.create_publisher(Image, TOPICS["rendered_depth"], Q.rendered_qos())
pi = n.create_publisher(CompressedImage, "/cam/image/compressed", Q.image_qos())
pn = n.create_publisher(CameraInfo, "/cam/info", Q.image_qos())
t0 = time.monotonic()
while (pk.get_subscription_count() == 0 or pi.get_subscription_count() == 0 or
       pr.get_subscription_count() == 0) and time.monotonic() - t0 < 60:
    rclpy.spin_once(n, timeout_sec=0.05)
time.sleep(0.5)
K = Intrinsics(40, 40, 31.5, 23.5, 64, 48)
rng = np.random.default_rng(0)
img = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
poses = [np.eye(4) for _ in range(4)]
for i, T in enumerate(poses):
    T[0, 3] = 0.1 * i
for i in range(4):
    pn.publish(convert.intrinsics_to_camera_info(K, 1.0 + i, "camera_optical"))
    m = CompressedImage(format="rgb8; png compressed bgr8",
                        data=cv2.imencode(".png", img[:, :, ::-1])[1].tobytes())
    m.header.stamp = convert.to_stamp(1.0 + i)
    pi.publish(m)
    pp.publish(pose_stamped(poses[i], 1.0 + i, "map"))
    time.sleep(0.05)
pk.publish(convert.keyframe_to_msg(KeyframeData(0, 0, 1.0, np.eye(4), img, K,
           np.ones((6, 8), np.float32), np.ones((6, 8), np.float32))))
pt.publish(path_msg([1.0, 2.0, 3.0, 4.0], np.stack(poses), "map", 4.0))
pc.publish(pointcloud2(rng.random((100, 3)), np.full((100, 3), 200, np.uint8), 4.0, "map"))
pr.publish(convert.image_to_msg(img, "rgb8", 4.0, "camera_optical"))
pd.publish(convert.image_to_msg(np.full((48, 64), 2.0, np.float32), "32FC1", 4.0, "camera_optical"))
T = np.eye(4); T[1, 3] = 0.5
pu.publish(convert.update_to_msg(UpdateEvent(7, "loop_closure", [0], T[None]), 5.0))
time.sleep(2.0)
rclpy.try_shutdown()
'''


def _read_rrd(path):
    """Entities -> archetypes, and rows per entity, with rerun's own RRD reader."""
    from rerun.chunk import RrdReader
    store = RrdReader(path).stream().collect()
    arch = {}
    for c in store.schema().component_columns():
        arch.setdefault(c.entity_path, set()).add(c.archetype)
    rows, batches = {}, {}
    for ch in store.stream():
        rows[ch.entity_path] = rows.get(ch.entity_path, 0) + ch.num_rows
        batches.setdefault(ch.entity_path, []).append(ch.to_record_batch())
    return arch, rows, batches


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_rerun_logger_writes_a_readable_rrd(tmp_path):
    """The node writes the .rrd file and, at the same time, streams to a viewer address (here a
    headless `rerun --save` server standing in for a viewer on another machine)."""
    need_ros()
    env = isolated_env()
    rrd = tmp_path / "run.rrd"
    port = _free_port()
    import rerun_cli                      # the viewer binary itself (the script wrapper would
    cli = Path(rerun_cli.__file__).parent / "rerun"           # leave it orphaned on terminate)
    viewer = start([str(cli), "--port", str(port), "--save", str(tmp_path / "viewer.rrd")], env,
                   tmp_path / "viewer.log")
    time.sleep(2.0)
    node = start([PY, "-m", "splat_slam_nodes.tools.rerun_logger", "--ros-args", "-p",
                  f"node.rrd:={rrd}", "-p", f"node.connect:=rerun+http://127.0.0.1:{port}/proxy",
                  "-p", "node.image_every:=2", "-p", "ros.image_topic:=/cam/image/compressed",
                  "-p", "ros.camera_info_topic:=/cam/info"], env, tmp_path / "rerun.log")
    feed = start([PY, "-c", FEED], env, tmp_path / "feed.log")
    try:
        assert feed.wait(timeout=180) == 0, (tmp_path / "feed.log").read_text()
        time.sleep(1.0)
    finally:
        stop(feed)
        stop(node)
        time.sleep(1.0)
        stop(viewer)
    assert rrd.is_file(), (tmp_path / "rerun.log").read_text()
    arch, rows, batches = _read_rrd(rrd)
    want = {
        "/world": "rerun.archetypes.ViewCoordinates",
        "/world/camera": "rerun.archetypes.Transform3D",
        "/world/camera/image": "rerun.archetypes.EncodedImage",
        "/world/trajectory": "rerun.archetypes.LineStrips3D",
        "/world/keyframes/0": "rerun.archetypes.Transform3D",
        "/world/keyframes/0/image": "rerun.archetypes.Pinhole",
        "/world/map/points": "rerun.archetypes.Points3D",
        "/rendered/rgb": "rerun.archetypes.Image",
        "/rendered/depth": "rerun.archetypes.DepthImage",
    }
    for ent, a in want.items():
        assert a in arch.get(ent, set()), (ent, arch.get(ent), sorted(arch))
    assert "rerun.archetypes.Pinhole" in arch["/world/camera/image"]
    assert rows["/world/camera"] == 4                      # every camera pose
    assert rows["/world/keyframes/0"] == 2                 # the keyframe, then its loop update
    # input images: every 2nd of 4 frames (+ 1 pinhole row)
    img_rows = sum(b.num_rows for b in batches["/world/camera/image"]
                   if any("EncodedImage" in n for n in b.schema.names))
    assert img_rows == 2, [b.schema.names for b in batches["/world/camera/image"]]
    # the Gaussian centres with their colours
    pts = [b for b in batches["/world/map/points"] if any("positions" in n for n in b.schema.names)]
    col = [n for n in pts[0].schema.names if n.endswith("Points3D:positions")][0]
    assert len(pts[0].column(col)[0]) == 100
    # the viewer address received the same recording
    varch, vrows, _ = _read_rrd(tmp_path / "viewer.rrd")
    for ent in want:
        assert ent in varch, (ent, sorted(varch), (tmp_path / "viewer.log").read_text()[-2000:])
    assert vrows["/world/camera"] == 4
