"""Single nodes as real processes over DDS: the depth + mapper nodes fed synthetic keyframes
and a pose-graph update (deformation, renders, point cloud, status, services), and the
tracker / depth / mapper nodes fed bad input (they log a clear error and keep running)."""
import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from test_graph_support import (TINY_TRACKING_CFG, PY, isolated_env, need_ros, read_jsonl,
                                start, stop, wait_for)

pytestmark = pytest.mark.ros

FAST_CFG = TINY_TRACKING_CFG + """mapping:
  iters_first: 20
  iters_per_keyframe: 5
  final_refine_iters: 5
  random_views_per_iter: 1
  window_views_per_iter: 3
  kf_covisibility: 1.0
  downsample: 4
  downsample_first: 4
"""

# Spins the script's ``node`` until ``cond()`` holds or ``timeout`` s passed.
SPIN_UNTIL = '''
def spin_until(cond, timeout):
    t0 = time.monotonic()
    while not cond() and time.monotonic() - t0 < timeout:
        rclpy.spin_once(node, timeout_sec=0.05)
    return bool(cond())
'''

# Feeds 3 keyframes of a fronto-parallel plane at 2 m, then a pose-graph update; exercises
# the mapper's topics and services; prints one JSON result line.
FEEDER = r'''
import json, sys, time
from splat_slam_ros.ros_env import apply_ros_environment
apply_ros_environment()
import numpy as np, rclpy
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import Image, PointCloud2
from splat_slam_msgs.msg import Keyframe, PoseGraphUpdate, ProxyDepth, MapperStatus
from splat_slam_msgs.srv import SaveMap, RenderPose
from std_srvs.srv import Trigger
from splat_slam_nodes import convert, qos as Q
from splat_slam_nodes.node_common import TOPICS, SERVICES, pointcloud2_to_arrays
from splat_slam_ros.types import Intrinsics, KeyframeData, UpdateEvent
out_dir = sys.argv[1]
rclpy.init()
node = rclpy.create_node("feeder")
got = {"status": [], "rgb": [], "depth": [], "points": [], "view": [], "pd": [], "info": [],
       "vinfo": []}
from sensor_msgs.msg import CameraInfo
node.create_subscription(CameraInfo, TOPICS["rendered_info"], lambda m: got["info"].append(m), Q.rendered_qos())
node.create_subscription(CameraInfo, TOPICS["view_info"], lambda m: got["vinfo"].append(m), Q.rendered_qos())
node.create_subscription(MapperStatus, TOPICS["status"], lambda m: got["status"].append(m), Q.status_qos())
node.create_subscription(Image, TOPICS["rendered_rgb"], lambda m: got["rgb"].append(m), Q.rendered_qos())
node.create_subscription(Image, TOPICS["rendered_depth"], lambda m: got["depth"].append(m), Q.rendered_qos())
node.create_subscription(PointCloud2, TOPICS["points"], lambda m: got["points"].append(m), Q.status_qos())
node.create_subscription(Image, TOPICS["view_rgb"], lambda m: got["view"].append(m), Q.rendered_qos())
node.create_subscription(ProxyDepth, TOPICS["proxy_depth"], lambda m: got["pd"].append(m), Q.proxy_depth_qos())
pk = node.create_publisher(Keyframe, TOPICS["keyframes"], Q.keyframe_qos())
pu = node.create_publisher(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos())
pr = node.create_publisher(PoseStamped, TOPICS["render_request"], Q.pose_qos())
from std_msgs.msg import String
from splat_slam_nodes.node_common import events_qos
ev = []
node.create_subscription(String, TOPICS["events"], lambda m: ev.append(json.loads(m.data)), events_qos())
pe = node.create_publisher(String, TOPICS["events"], events_qos())
ppd = node.create_publisher(ProxyDepth, TOPICS["proxy_depth"], Q.proxy_depth_qos())
''' + SPIN_UNTIL + r'''T0 = time.monotonic()
ok = spin_until(lambda: pk.get_subscription_count() >= 2 and pu.get_subscription_count() >= 2, 120)
H, W = 48, 64
intr = Intrinsics(50.0, 50.0, 31.5, 23.5, W, H)
rng = np.random.default_rng(0)
tex = (rng.random((H, W + 40, 3)) * 255).astype(np.uint8)
poses = []
for k in range(3):
    P = np.eye(4); P[0, 3] = 0.05 * k
    poses.append(P)
    kf = KeyframeData(k, 10 * k, 100.0 + k, P, np.ascontiguousarray(tex[:, 2 * k: 2 * k + W]), intr,
                      np.full((H // 8, W // 8), 0.5, np.float32), np.ones((H // 8, W // 8), np.float32))
    pk.publish(convert.keyframe_to_msg(kf))
res = {"matched": ok}
res["mapped"] = spin_until(lambda: got["status"] and got["status"][-1].keyframes_mapped >= 3, 120)
res["t_mapped"] = time.monotonic() - T0
s0 = got["status"][-1] if got["status"] else None
res["gaussians0"] = int(s0.gaussian_count) if s0 else 0
res["deform0"] = int(s0.deformations_applied) if s0 else 0
cli_r = node.create_client(RenderPose, SERVICES["render"])
cli_r.wait_for_service(timeout_sec=30)
def render(P):
    rq = RenderPose.Request(); rq.pose = convert.pose_to_msg(P); rq.width = W; rq.height = H
    f = cli_r.call_async(rq); spin_until(lambda: f.done(), 60)
    r = f.result(); return r, convert.msg_to_image(r.depth) if r.success else None
r_before, d_before = render(poses[0])
# pose-graph update: every keyframe moves 10 cm along y (the whole map should follow)
new = [p.copy() for p in poses]
for p in new: p[1, 3] += 0.10
pu.publish(convert.update_to_msg(UpdateEvent(7, "loop_closure", [0, 1, 2], np.stack(new), None)))
res["deformed"] = spin_until(lambda: got["status"] and got["status"][-1].deformations_applied
                             >= res["deform0"] + 3 and got["status"][-1].last_update_seq == 7, 120)
res["t_deformed"] = time.monotonic() - T0
res["pd_updates"] = [int(m.kf_id) for m in got["pd"] if m.is_update and m.update_seq == 7]
r_old, d_old = render(poses[0])
r_new, d_new = render(new[0])
res["render_ok"] = bool(r_before.success and r_new.success)
res["render_msg"] = r_new.message
res["size"] = [int(r_new.rgb.width), int(r_new.rgb.height), r_new.rgb.encoding, r_new.depth.encoding]
valid = d_before > 0
res["depth_same_at_new_pose"] = float(np.abs(d_new - d_before)[valid].mean()) if valid.any() else -1
res["depth_diff_at_old_pose"] = float(np.abs(d_old - d_before)[valid].mean()) if valid.any() else -1
res["rendered_topic"] = [len(got["rgb"]), len(got["depth"])]
if got["rgb"]:
    res["rendered_enc"] = [got["rgb"][-1].encoding, got["depth"][-1].encoding]
res["points"] = 0
if got["points"]:
    pts, cols = pointcloud2_to_arrays(got["points"][-1])
    res["points"] = int(len(pts))
pq = PoseStamped(); pq.header.frame_id = "map"; pq.pose = convert.pose_to_msg(new[1])
spin_until(lambda: pr.get_subscription_count() > 0, 20)
pr.publish(pq)
res["view"] = spin_until(lambda: len(got["view"]) > 0 and len(got["vinfo"]) > 0, 60)
res["infos"] = [[m.header.frame_id, m.width, m.height, list(m.k), m.header.stamp.sec]
                for m in (got["info"][-1:] + got["vinfo"][-1:])]
res["image_frames"] = [got["rgb"][-1].header.frame_id if got["rgb"] else "",
                       got["view"][-1].header.frame_id if got["view"] else ""]
# a final digest naming a revision of keyframe 1 that the mapper never got (as if a DDS
# history had dropped it): the mapper asks the depth node again, then finalises once it has it
last = {}
for m in got["pd"]:
    last[int(m.kf_id)] = max(last.get(int(m.kf_id), -1), int(m.revision))
digest = {str(k): v for k, v in last.items()}
digest["1"] = last[1] + 1
n_pd = len(got["pd"])
spin_until(lambda: ppd.get_subscription_count() >= 1, 20)
pe.publish(String(data=json.dumps({"node": "depth", "event": "finalized", "digest": digest,
                                   "keyframes": 3})))
asks = lambda: [e for e in ev if e.get("event") == "resend_depth" and e.get("node") == "mapper"]
res["asked"] = spin_until(lambda: asks(), 30)
res["asked_ids"] = asks()[0]["kf_ids"] if asks() else None
res["resent"] = spin_until(lambda: any(int(m.kf_id) == 1 and int(m.revision) == last[1]
                                       for m in got["pd"][n_pd:]), 30)
res["final_before"] = any(e.get("event") == "saved" and e.get("node") == "mapper" for e in ev)
m1 = [m for m in got["pd"] if int(m.kf_id) == 1 and int(m.revision) == last[1]][-1]
m1.revision = last[1] + 1
ppd.publish(m1)
res["final_after"] = spin_until(lambda: any(e.get("event") == "saved" and e.get("node") == "mapper"
                                            for e in ev), 120)
cli_s = node.create_client(SaveMap, SERVICES["save_map"]); cli_s.wait_for_service(timeout_sec=30)
f = cli_s.call_async(SaveMap.Request(directory=out_dir)); spin_until(lambda: f.done(), 120)
res["save"] = [f.result().success, f.result().message]
rq = RenderPose.Request(); rq.pose = convert.pose_to_msg(new[0]); rq.width = 4 * W; rq.height = 2 * H
f = cli_r.call_async(rq); spin_until(lambda: f.done(), 60)
res["render_big"] = [f.result().success, f.result().message]
cli_t = node.create_client(Trigger, SERVICES["reset_map"]); cli_t.wait_for_service(timeout_sec=30)
f = cli_t.call_async(Trigger.Request()); spin_until(lambda: f.done(), 60)
res["reset"] = f.result().success
res["after_reset"] = spin_until(lambda: got["status"] and got["status"][-1].gaussian_count == 0, 30)
r_empty, _ = render(new[0])
res["render_empty"] = [r_empty.success, r_empty.message]
print("RESULT " + json.dumps(res), flush=True)
rclpy.try_shutdown()
'''


def _node(name, env, cfg, log, *params):
    args = [PY, "-m", f"splat_slam_nodes.{name}_node", "--ros-args", "-p", f"config_file:={cfg}",
            "-p", "node.loop_closure:=false"]
    for p in params:
        args += ["-p", p]
    return start(args, env, log)


def _result(log: Path) -> dict:
    for line in log.read_text(errors="replace").splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise AssertionError("no result:\n" + log.read_text(errors="replace")[-3000:])


def test_depth_and_mapper_nodes(tmp_path):
    need_ros()
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(FAST_CFG)
    env = isolated_env()
    depth = _node("depth", env, cfg, tmp_path / "depth.log")
    # use_sim_time as under splat-slam-launch --bag: no /clock here, so ROS time stands still
    # (as after the end of a bag); the mapper's checks for lost depth must still run
    mapper = _node("mapper", env, cfg, tmp_path / "mapper.log", f"node.output_dir:={tmp_path}",
                   "node.allow_reset:=true", "use_sim_time:=true")
    feeder = start([PY, "-c", FEEDER, "saved"], env, tmp_path / "feeder.log")
    try:
        assert feeder.wait(timeout=400) == 0, (tmp_path / "feeder.log").read_text()[-3000:]
    finally:
        for p in (feeder, depth, mapper):
            stop(p)
    r = _result(tmp_path / "feeder.log")
    mlog = (tmp_path / "mapper.log").read_text()
    assert r["matched"] and r["mapped"], mlog[-3000:]
    assert r["gaussians0"] > 0
    # the update reached the mapper through the depth node and deformed all 3 keyframes
    assert r["deformed"], mlog[-3000:]
    assert sorted(set(r["pd_updates"])) == [0, 1, 2]
    # the map moved with its keyframes: rendered at the new pose it looks like before at the
    # old one, and differs at the old pose
    assert r["render_ok"] and r["size"] == [64, 48, "rgb8", "32FC1"], r
    assert r["depth_same_at_new_pose"] < 0.05, r
    assert r["depth_diff_at_old_pose"] > 3 * r["depth_same_at_new_pose"], r
    assert r["rendered_topic"][0] >= 1 and r["rendered_topic"][1] >= 1
    assert r["rendered_enc"] == ["rgb8", "32FC1"]
    assert r["points"] == r["gaussians0"] or r["points"] > 0
    assert r["view"]
    # the renders carry their CameraInfo (same stamp) in the optical frame (rviz Camera display)
    assert r["image_frames"] == ["camera_optical", "camera_optical"]
    assert len(r["infos"]) == 2
    for fr, w, h, k, _ in r["infos"]:
        assert (fr, w, h) == ("camera_optical", 64, 48)
        assert np.allclose(k, [50.0, 0, 31.5, 0, 50.0, 23.5, 0, 0, 1])
    # a revision named by the final digest but lost on the way is asked for again (graph
    # event resend_depth), sent again by the depth node, and the mapper finalises once it has it
    assert r["asked"] and r["asked_ids"] == [1], (r, mlog[-3000:])
    assert r["resent"], (r, (tmp_path / "depth.log").read_text()[-3000:])
    assert not r["final_before"] and r["final_after"], (r, mlog[-3000:])
    assert r["save"][0], r["save"]
    saved = tmp_path / "saved"
    for f in ("map.ply", "trajectory_keyframes.txt", "metrics.json", "map_mesh.ply"):
        assert (saved / f).is_file(), f
    assert json.loads((saved / "metrics.json").read_text())["views"] == 3
    assert json.loads((saved / "metrics.json").read_text())["mesh"]["faces"] > 0
    from splat_slam_ros.config import load_config
    from splat_slam_ros.mapping.mapper import Mapper
    from splat_slam_ros.types import Intrinsics
    mp = Mapper.load_ply(saved / "map.ply", load_config(cfg), Intrinsics(50, 50, 31.5, 23.5, 64, 48))
    assert len(mp.map) > 0
    rgb, dep = mp.render(np.eye(4))
    assert (dep > 0).mean() > 0.3
    assert r["reset"] and r["after_reset"]
    # 8x the camera image area: refused with an error response (default bound 4x)
    assert r["render_big"] == [False, "render size 256x96 exceeds the limit of 12288 pixels "
                               "(node.max_render_pixels; default 4x the camera image area)"]
    assert r["render_empty"][0] is False and "empty" in r["render_empty"][1]


# The start of a script that feeds the tracker: ROS environment, imports, a node ``node``
# collecting the tracker's FrameAcks in ``acks``, and spin_until.
ACK_FEEDER = r'''
import array, json, sys, time
from splat_slam_ros.ros_env import apply_ros_environment
apply_ros_environment()
import cv2, numpy as np, rclpy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from splat_slam_msgs.msg import FrameAck, Keyframe, ProxyDepth
from splat_slam_nodes import convert, qos as Q
from splat_slam_nodes.node_common import TOPICS
from splat_slam_ros.types import Intrinsics
rclpy.init()
node = rclpy.create_node("feeder")
acks = []
node.create_subscription(FrameAck, TOPICS["ack"], lambda m: acks.append(m), Q.ack_qos())
''' + SPIN_UNTIL

BAD_INPUT = ACK_FEEDER + r'''
pi = node.create_publisher(Image, "/cam/image", Q.image_qos())
pc = node.create_publisher(CameraInfo, "/cam/info", Q.image_qos())
pk = node.create_publisher(Keyframe, TOPICS["keyframes"], Q.keyframe_qos())
pd = node.create_publisher(ProxyDepth, TOPICS["proxy_depth"], Q.proxy_depth_qos())
spin_until(lambda: pi.get_subscription_count() and pc.get_subscription_count() and
           pk.get_subscription_count() >= 2 and pd.get_subscription_count(), 120)
spin_until(lambda: False, 0.5)
rng = np.random.default_rng(0)
img = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
t = [1.0]
def send(m, expect_ack=True):
    n = len(acks)
    m.header.stamp = convert.to_stamp(t[0]); t[0] += 0.1
    pi.publish(m)
    return spin_until(lambda: len(acks) > n, 30) if expect_ack else None
res = {}
res["no_info"] = send(convert.image_to_msg(img, "rgb8"))             # no camera_info yet
pc.publish(convert.intrinsics_to_camera_info(Intrinsics(50, 50, 31.5, 23.5, 64, 48)))
spin_until(lambda: False, 0.5)
bad = convert.image_to_msg(img, "rgb8"); bad.encoding = "8SC3"
res["encoding"] = send(bad)
res["depth_enc"] = send(convert.image_to_msg(img[:, :, 0].astype(np.uint16), "16UC1"))
pi.publish(b"\x00\x01\x00\x00garbage-not-cdr")                         # undecodable bytes
spin_until(lambda: False, 0.5)
m = convert.image_to_msg(img, "rgb8"); m.data = array.array("B", bytes(100))   # short data
res["short"] = send(m)
res["ok1"] = send(convert.image_to_msg(img, "rgb8"))
res["bgr"] = send(convert.image_to_msg(np.ascontiguousarray(img[:, :, ::-1]), "bgr8"))
res["mono"] = send(convert.image_to_msg(img[:, :, 0].copy(), "mono8"))
# a new camera_info with another size, then a frame of that size: the tracker refuses the change
pc.publish(convert.intrinsics_to_camera_info(Intrinsics(25, 25, 15.5, 11.5, 32, 24)))
spin_until(lambda: False, 0.5)
res["size_change"] = send(convert.image_to_msg(np.zeros((24, 32, 3), np.uint8) + 100, "rgb8"))
# garbage for the depth / mapper nodes
pk.publish(b"\x00\x01\x00\x00" + bytes(range(200)))
k = Keyframe(); k.kf_id = 3; k.width = 64; k.height = 48; k.intrinsics = [50.0, 50.0, 31.5, 23.5]
k.image = convert.image_to_msg(img, "rgb8"); k.disp_width = 8; k.disp_height = 6
k.disparity = array.array("f", [0.5] * 7)                               # wrong length
pk.publish(k)
pd.publish(b"\x00\x01\x00\x00" + bytes(50))
spin_until(lambda: False, 2.0)
res["ok2"] = send(convert.image_to_msg(img, "rgb8"))
res["acks"] = len(acks)
print("RESULT " + json.dumps(res), flush=True)
rclpy.try_shutdown()
'''


def test_bad_input_is_logged_and_nodes_keep_running(tmp_path):
    need_ros()
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(FAST_CFG)
    env = isolated_env()
    tracker = _node("tracker", env, cfg, tmp_path / "tracker.log", "ros.image_topic:=/cam/image",
                    "ros.camera_info_topic:=/cam/info", "node.input_qos:=reliable",
                    "node.camera_info_timeout:=1.0")
    depth = _node("depth", env, cfg, tmp_path / "depth.log")
    mapper = _node("mapper", env, cfg, tmp_path / "mapper.log")
    feeder = start([PY, "-c", BAD_INPUT], env, tmp_path / "feeder.log")
    try:
        assert feeder.wait(timeout=300) == 0, (tmp_path / "feeder.log").read_text()[-3000:]
        alive = [p.poll() is None for p in (tracker, depth, mapper)]
    finally:
        for p in (feeder, tracker, depth, mapper):
            stop(p)
    r = _result(tmp_path / "feeder.log")
    tlog = (tmp_path / "tracker.log").read_text()
    dlog = (tmp_path / "depth.log").read_text()
    mlog = (tmp_path / "mapper.log").read_text()
    assert alive == [True, True, True], (tlog[-2000:], dlog[-2000:], mlog[-2000:])
    # every frame is acknowledged (consumed), dropped or not
    for k in ("no_info", "encoding", "depth_enc", "short", "ok1", "bgr", "mono", "size_change",
              "ok2"):
        assert r[k], (k, tlog[-3000:])
    assert r["acks"] == 9
    assert "no camera_info received on /cam/info" in tlog
    assert "unsupported image encoding '8SC3'" in tlog
    assert "image encoding '16UC1' is not a colour image" in tlog
    assert "cannot be deserialised" in tlog
    assert "image data has 100 bytes" in tlog
    assert "image size changed: 32x24, the tracker runs on 64x48" in tlog
    assert "tracker started on 64x48" in tlog
    assert "cannot be deserialised" in dlog and "keyframe 3 disparity: 7 values" in dlog
    assert "cannot be deserialised" in mlog and "ProxyDepth" in mlog


COMPRESSED_INPUT = ACK_FEEDER + r'''
topic = sys.argv[1]
pz = node.create_publisher(CompressedImage, topic, Q.image_qos())
pc = node.create_publisher(CameraInfo, "/cam/info", Q.image_qos())
spin_until(lambda: pc.get_subscription_count(), 120)
pc.publish(convert.intrinsics_to_camera_info(Intrinsics(50, 50, 31.5, 23.5, 64, 48)))
spin_until(lambda: False, 0.5)
rng = np.random.default_rng(0)
img = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
png = cv2.imencode(".png", img[:, :, ::-1])[1].tobytes()
jpg = cv2.imencode(".jpg", img[:, :, ::-1])[1].tobytes()
t = [1.0]
def send(fmt, data, tries=1):
    n = len(acks)
    m = CompressedImage(format=fmt, data=data)
    m.header.stamp = convert.to_stamp(t[0]); t[0] += 0.1
    for _ in range(tries):           # until the tracker's subscription has the camera's type
        pz.publish(m)
        if spin_until(lambda: len(acks) > n, 30 / tries):
            return True
    return False
res = {"png": send("rgb8; png compressed bgr8", png, tries=30)}
spin_until(lambda: False, 1.0)                          # (a retried copy: acked as a replay)
res.update(torn=send("jpeg", jpg[:100]), jpeg=send("rgb8; jpeg compressed bgr8", jpg))
n = len(acks)                                           # a driver that never stamps
pz.publish(CompressedImage(format="png", data=png))
res["unstamped"] = spin_until(lambda: len(acks) > n, 30)
res["unstamped_ack_s"] = acks[-1].header.stamp.sec if len(acks) > n else None
print("RESULT " + json.dumps(res), flush=True)
rclpy.try_shutdown()
'''


@pytest.mark.parametrize("topic", ["/cam/image/compressed", "/cam/image"])
def test_a_compressed_camera_topic_is_decoded(tmp_path, topic):
    """CompressedImage on image_transport's ``/compressed`` topic, and on a name without it
    (where the tracker first takes Image, then follows the type the camera publishes): PNG
    and JPEG decoded, a torn frame dropped with its reason, a frame without a stamp stamped
    at arrival."""
    need_ros()
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(FAST_CFG)
    env = isolated_env()
    tracker = _node("tracker", env, cfg, tmp_path / "tracker.log", f"ros.image_topic:={topic}",
                    "ros.camera_info_topic:=/cam/info", "node.input_qos:=reliable",
                    "node.mapping:=false")
    feeder = start([PY, "-c", COMPRESSED_INPUT, topic], env, tmp_path / "feeder.log")
    try:
        assert feeder.wait(timeout=300) == 0, (tmp_path / "feeder.log").read_text()[-3000:]
        alive = tracker.poll() is None
    finally:
        for p in (feeder, tracker):
            stop(p)
    r = _result(tmp_path / "feeder.log")
    tlog = (tmp_path / "tracker.log").read_text()
    assert alive, tlog[-3000:]
    assert abs(r.pop("unstamped_ack_s") - time.time()) < 300, (r, tlog[-3000:])  # arrival
    assert r == {"png": True, "torn": True, "jpeg": True, "unstamped": True}, (r, tlog[-3000:])
    switched = f"{topic} is published as sensor_msgs/msg/CompressedImage, not " \
               "sensor_msgs/msg/Image: subscribed as that"
    assert (switched in tlog) == (topic == "/cam/image"), tlog[-3000:]
    assert "tracker started on 64x48" in tlog
    assert "cannot decode the compressed image (100 bytes, format 'jpeg')" in tlog
    assert tlog.count("dropped") == 1, tlog[-3000:]
    assert f"frames on {topic} have no header stamp: stamped at arrival" in tlog


# A node whose spin loses the race between a SIGTERM's shutdown and the executor's wait-set
# creation (rclpy raises RCLError there), or raises the same error while the context is live.
SPIN_RACE = r'''
import sys
from splat_slam_ros.ros_env import apply_ros_environment
apply_ros_environment()
import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from splat_slam_nodes.node_common import SplatNode
rclpy.init()
n = SplatNode("spin_race", {})
ctx = rclpy.get_default_context()

def racing_spin(node):
    if sys.argv[1] == "shutdown":
        rclpy.try_shutdown()
    with ctx.handle:
        _rclpy.WaitSet(0, 0, 0, 0, 0, 0, ctx.handle)
    raise RuntimeError("a live context makes a wait set")
rclpy.spin = racing_spin
print("rc", n.spin(), flush=True)
'''


def test_shutdown_racing_the_executor_is_a_clean_stop(tmp_path):
    need_ros()
    import subprocess
    script = tmp_path / "race.py"
    script.write_text(SPIN_RACE)
    out = subprocess.run([PY, str(script), "shutdown"], env=isolated_env(), capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0 and "rc 0" in out.stdout, out.stderr[-3000:]
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    # the same error while the context is still valid is a real fault: it is not swallowed
    live = subprocess.run([PY, str(script), "live"], env=isolated_env(), capture_output=True,
                          text=True, timeout=120)
    assert live.returncode != 0 and "a live context makes a wait set" in live.stderr
