"""TF from the running graph (splat-slam-launch on a synthetic closed loop, tracking + loop
closure nodes): a subscriber decodes /tf and /tf_static and finds map -> odom -> camera ->
camera_optical; map -> odom is the identity until a loop closure corrects the pose and changes
afterwards; the chain equals /splat/camera_pose; keyframe markers arrive."""
import json
from pathlib import Path

import numpy as np
import pytest

from test_graph_support import PY, isolated_env, need_ros, read_jsonl, run_launch, start

pytestmark = pytest.mark.ros

HELPERS = Path(__file__).resolve().parent / "ros_helpers"

CFG = """
tracking:
  warmup: 4
  motion_filter_thresh: 2.0
  keyframe_thresh: 2.0
  ba_downsample: 4
  loop_closure: true
  global_ba: true
  loop_time_gap: 6
  loop_window: 6
  loop_nms: 3
  global_ba_every: 1000
"""


def loop_trajectory(turns: float = 1.15, radius: float = 0.3, duration: float = 10.0):
    """A camera circling (a bit more than once) in front of the synthetic room's desk area,
    always looking at the same point: the start is revisited, a loop closes."""
    t = np.linspace(0, duration, 400)
    ang = 2 * np.pi * turns * t / duration
    pos = np.stack([0.0 * t, radius * np.cos(ang) - radius, 1.45 + radius * np.sin(ang)], 1)
    z = np.array([1.9, 0.0, 0.75]) - pos
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    P = np.tile(np.eye(4), (len(t), 1, 1))
    P[:, :3, 0], P[:, :3, 1], P[:, :3, 2], P[:, :3, 3] = x, np.cross(z, x), z, pos
    return t, P


@pytest.fixture(scope="module")
def loop_bag(tmp_path_factory):
    need_ros()
    from splat_slam_ros.io.bagio import write_bag
    from splat_slam_ros.io.datasets import open_dataset
    from splat_slam_synth import generate_sequence
    d = tmp_path_factory.mktemp("tf_loop")
    generate_sequence(loop_trajectory(), 60, (192, 144), d / "seq", overwrite=True,
                      progress=False, realism="clean", fps=6.0)
    write_bag(open_dataset(d / "seq"), d / "bag", progress=False)
    (d / "cfg.yaml").write_text(CFG)
    return d / "bag", d / "cfg.yaml"


def _mat(tq):
    from splat_slam_ros.geometry import pose_from_tq
    return pose_from_tq(np.asarray(tq, np.float64)).numpy()


def test_tf_tree_from_the_running_graph(loop_bag, tmp_path):
    bag, cfg = loop_bag
    env = isolated_env()
    probe = start([PY, str(HELPERS / "tf_probe.py"), "900"], env, tmp_path / "probe.log")
    rc = run_launch([PY, "-m", "splat_slam_nodes.tools.launch", "--bag", str(bag), "--out",
                     str(tmp_path / "out"), "--config", str(cfg), "--tracking-only",
                     "--set", "ros.odom_frame=odom_test"], env, tmp_path / "launch.log", probe)
    log = (tmp_path / "launch.log").read_text(errors="replace")
    assert rc == 0, log[-4000:]
    recs = read_jsonl(tmp_path / "probe.log")
    static = [tf for r in recs if r.get("topic") == "/tf_static" for tf in r["tf"]]
    assert [s[:2] for s in static] == [["camera", "camera_optical"]]
    q = np.array(static[0][6:10])
    np.testing.assert_allclose(np.sign(q[3]) * q, [-0.5, 0.5, -0.5, 0.5], atol=1e-9)
    # map -> odom -> camera, every frame (the odom frame name is configurable)
    tfs = [(r["t"], tf) for r in recs if r.get("topic") == "/tf" for tf in r["tf"]]
    edges = {(tf[0], tf[1]) for _, tf in tfs}
    assert edges == {("map", "odom_test"), ("odom_test", "camera")}, edges
    map_odom = [(t, tf[2], _mat(tf[3:])) for t, tf in tfs if tf[1] == "odom_test"]
    odom_cam = {tf[2]: _mat(tf[3:]) for _, tf in tfs if tf[1] == "camera"}
    poses = {r["stamp"]: _mat(r["p"]) for r in recs if r.get("topic") == "pose"}
    assert len(odom_cam) >= 30 and set(poses) == set(odom_cam)
    # the chain map -> odom -> camera -> camera_optical is the published camera pose
    T_cam_opt = _mat(static[0][3:])
    by_stamp = {st: T for _, st, T in map_odom}
    for st, T in poses.items():
        np.testing.assert_allclose(by_stamp[st] @ odom_cam[st] @ T_cam_opt, T, atol=1e-5)
    # identity before the first loop closure; different after it (a correction, not odometry)
    updates = [r for r in recs if r.get("topic") == "update"]
    from splat_slam_msgs.msg import PoseGraphUpdate
    t_loop = min(r["t"] for r in updates if r["reason"] == PoseGraphUpdate.LOOP_CLOSURE)
    before = [T for t, _, T in map_odom if t < t_loop]
    t_final = min(r["t"] for r in updates if r["reason"] == PoseGraphUpdate.FINAL)
    after = [T for t, _, T in map_odom if t_loop < t < t_final]    # the loop, not the final BA
    assert before and after
    assert all(np.allclose(T, np.eye(4), atol=1e-9) for T in before)
    moved = max(np.abs(T - np.eye(4)).max() for T in after)
    assert moved > 1e-4, moved
    # odometry stays continuous across the correction: no frame-to-frame jump above the motion
    st = sorted(odom_cam)
    steps = [np.linalg.norm(odom_cam[b][:3, 3] - odom_cam[a][:3, 3]) for a, b in zip(st, st[1:])]
    assert max(steps) < 0.2, max(steps)
    # odometry: odom -> camera of /tf at increasing stamps, its twist the motion between them
    odo = [r for r in recs if r.get("topic") == "odom"]
    assert len(odo) >= 30 and {(r["frame"], r["child"]) for r in odo} == {("odom_test", "camera")}
    stamps = [r["stamp"] for r in odo]
    assert stamps == sorted(set(stamps)) and set(stamps) <= set(odom_cam)
    for r in odo:
        np.testing.assert_allclose(_mat(r["p"]), odom_cam[r["stamp"]], atol=1e-5)
    from splat_slam_nodes.tf_frames import body_twist
    assert not any(odo[0]["v"])
    for a, b in zip(odo, odo[1:]):
        lin, ang = body_twist(_mat(a["p"]), _mat(b["p"]), (b["stamp"] - a["stamp"]) * 1e-9)
        np.testing.assert_allclose(b["v"], np.concatenate([lin, ang]), atol=1e-4)
    # rviz: keyframe poses as a MarkerArray (DELETEALL, arrows, path)
    marks = [r for r in recs if r.get("topic") == "markers"]
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert marks and marks[-1]["frame"] == "map"
    from visualization_msgs.msg import Marker
    kinds = marks[-1]["types"]
    assert kinds[0][1] == Marker.DELETEALL and [Marker.LINE_STRIP, Marker.ADD] in kinds
    assert kinds.count([Marker.ARROW, Marker.ADD]) == m["keyframes"] >= 6
