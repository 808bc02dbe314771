"""Helpers for the node-graph tests (no tests here): tiny bags, isolated DDS environments,
subprocess start/stop, a probe process that records topics."""
from __future__ import annotations

import itertools
import json
import os
import random
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import pytest

from splat_slam_ros import ros_env


REPO = Path(__file__).resolve().parents[1]
PY = sys.executable


def ros_missing_reason() -> str:
    """'' when rclpy and splat_slam_msgs import in a fresh interpreter (as the node
    processes do), else the last line of the error."""
    r = subprocess.run([PY, "-c", "import rclpy; from splat_slam_msgs.msg import Keyframe"],
                       capture_output=True, text=True, timeout=120)
    return "" if r.returncode == 0 else (r.stderr.strip().splitlines() or ["?"])[-1]


_WHY = None


def need_ros():
    """Fail (never skip) when the node processes could not import rclpy / splat_slam_msgs:
    both are requirements (run.sh installs rclpy and builds the messages)."""
    global _WHY
    if _WHY is None:
        _WHY = ros_missing_reason()
    if _WHY:
        pytest.fail(f"rclpy / splat_slam_msgs not importable ({_WHY}); build the messages with "
                    "msg_defs/build.sh and run with the venv's python")


_DOMAINS = None


def _domain_id() -> int:
    """A ROS_DOMAIN_ID no recent test of this process used: the ids of this process's share of
    1..101 (under ``pytest -n N``: id % N == worker index, so tests running at once never
    share a domain) in turn, from a random start. Random picks repeated an id within a few
    tests now and then, and a process still shutting down from the earlier test (its
    TRANSIENT_LOCAL graph events: 'tracker saved') then ended the new test's run."""
    global _DOMAINS
    if _DOMAINS is None:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "")
        n = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
        pool = list(range(1, 102))
        if worker.startswith("gw") and n > 1:
            i = int(worker[2:]) % n
            pool = [d for d in pool if d % n == i]
        k = random.SystemRandom().randrange(len(pool))
        _DOMAINS = itertools.cycle(pool[k:] + pool[:k])
    return next(_DOMAINS)


def isolated_env(**extra) -> Dict[str, str]:
    """Project DDS env with a random ROS_DOMAIN_ID (parallel runs do not cross-talk)."""
    base = {k: v for k, v in os.environ.items()
            if k not in ("FASTRTPS_DEFAULT_PROFILES_FILE", ros_env.OVERRIDE_ENV)}
    base["ROS_DOMAIN_ID"] = str(_domain_id())
    base["PYTHONUNBUFFERED"] = "1"
    base.update(extra)
    return ros_env.ros_environment(base)


def start(args: List[str], env, log: Path) -> subprocess.Popen:
    f = open(log, "wb")
    return subprocess.Popen(args, env=env, stdout=f, stderr=subprocess.STDOUT, cwd=str(REPO))


def stop(p: subprocess.Popen, timeout: float = 8.0) -> None:
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


# tracking settings that initialise on the tiny synthetic test sequences (no loop closure)
TINY_TRACKING_CFG = """
tracking:
  warmup: 4
  motion_filter_thresh: 2.0
  keyframe_thresh: 2.0
  loop_closure: false
  global_ba: false
"""


TINY_LOOP_TRACKING_CFG = TINY_TRACKING_CFG.replace("false", "true")   # + loop closure, global BA
# the whole method, fastest schedule (a run of a few seconds on a tiny bag)
TINY_FAST_RUN_CFG = """
tracking: {warmup: 4, motion_filter_thresh: 2.0, keyframe_thresh: 2.0, ba_downsample: 4,
           loop_closure: false, global_ba: false}
mapping: {iters_first: 20, iters_per_keyframe: 3, final_refine_iters: 5,
          random_views_per_iter: 1, window_views_per_iter: 2}
"""


def run_launch(args: List[str], env, log: Path, probe: Optional[subprocess.Popen] = None,
               timeout: float = 900) -> int:
    """Run a launcher command to its end, then stop ``probe`` (a listener started just
    before, if any)."""
    if probe is not None:
        time.sleep(1.0)
    launch = start(args, env, log)
    try:
        return launch.wait(timeout=timeout)
    finally:
        stop(launch)
        if probe is not None:
            time.sleep(0.5)
            stop(probe)


def launch_ok(args: List[str], env, log: Path, timeout: float = 900) -> str:
    """Run a launcher command to its end; assert it exited 0; its log text."""
    rc = run_launch(args, env, log, timeout=timeout)
    text = log.read_text(errors="replace")
    assert rc == 0, text[-4000:]
    return text


def write_tiny_bag(path: Path, n: int = 12, w: int = 64, h: int = 48, with_depth: bool = True,
                   with_gt: bool = True, t0: float = 1000.0, fps: float = 30.0,
                   images=None) -> Path:
    """A rosbag2 MCAP with n frames of camera_info + rgb8 image (+ depth, gt pose)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from splat_slam_ros.io import bagio
    from splat_slam_ros.types import Intrinsics
    ts = bagio.make_typestore(project_types=False)
    K = Intrinsics(0.8 * w, 0.8 * w, (w - 1) / 2, (h - 1) / 2, w, h)
    rng = np.random.default_rng(0)
    wr = Writer(path, version=8, storage_plugin=StoragePlugin.MCAP)
    wr.open()
    ci = wr.add_connection("/camera/camera_info", bagio.T_INFO, typestore=ts)
    im = wr.add_connection("/camera/image_raw", bagio.T_IMAGE, typestore=ts)
    de = wr.add_connection("/camera/depth", bagio.T_IMAGE, typestore=ts) if with_depth else None
    gp = wr.add_connection("/ground_truth/pose", bagio.T_POSE, typestore=ts) if with_gt else None
    for i in range(n):
        ns = int(round((t0 + i / fps) * 1e9))
        img = images[i] if images is not None else rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        for c, m, tn in ((ci, bagio.camera_info_msg(ts, K, ns), bagio.T_INFO),
                         (im, bagio.image_msg(ts, img, ns), bagio.T_IMAGE)):
            wr.write(c, ns, ts.serialize_cdr(m, tn))
        if de is not None:
            wr.write(de, ns, ts.serialize_cdr(bagio.depth_msg(ts, np.full((h, w), 2.0, np.float32),
                                                              ns), bagio.T_IMAGE))
        if gp is not None:
            T = np.eye(4)
            T[0, 3] = 0.01 * i
            wr.write(gp, ns, ts.serialize_cdr(bagio.pose_msg(ts, T, ns), bagio.T_POSE))
    wr.close()
    return path


# A probe process: subscribes to topics (raw, any type), acks frames like a tracker would
# (optionally with a delay), records what it saw as JSON lines on stdout.
# the start of a script (``python -c``) that calls services of the graph:
# ``call(srv, name, req)`` -> [success, message] (a request that got no answer: false)
SERVICE_CALLER = r'''
import json, math, sys, time
from splat_slam_ros.ros_env import apply_ros_environment
apply_ros_environment()
import rclpy
from splat_slam_nodes.node_common import SERVICES
rclpy.init()
node = rclpy.create_node("caller")
def call(srv, name, req, timeout=300):
    c = node.create_client(srv, SERVICES[name])
    assert c.wait_for_service(timeout_sec=120), name
    f = c.call_async(req)
    t0 = time.monotonic()
    while not f.done() and time.monotonic() - t0 < timeout:
        rclpy.spin_once(node, timeout_sec=0.1)
    r = f.result()
    return [False, "no answer"] if r is None else [r.success, r.message]
'''


PROBE = r'''
import json, sys, time
from splat_slam_ros.ros_env import apply_ros_environment
apply_ros_environment()
import rclpy
from rclpy.serialization import deserialize_message
spec = json.loads(sys.argv[1])
rclpy.init()
node = rclpy.create_node(spec.get("name", "probe"))
from splat_slam_nodes import qos as Q
from splat_slam_nodes.node_common import TOPICS, events_qos
from splat_slam_msgs.msg import FrameAck
from std_msgs.msg import String
ack_pub = node.create_publisher(FrameAck, TOPICS["ack"], Q.ack_qos())
ev_pub = node.create_publisher(String, TOPICS["events"], events_qos())
from splat_slam_nodes.tools.msg_types import message_class as imp
pending = []
def make_cb(topic, cls):
    def cb(raw):
        m = deserialize_message(raw, cls)
        st = getattr(getattr(m, "header", None), "stamp", None)
        if st is None and hasattr(m, "clock"):
            st = m.clock
        rec = {"topic": topic, "t": time.monotonic(), "bytes": len(raw)}
        if st is not None:
            rec["stamp"] = st.sec * 1_000_000_000 + st.nanosec
        if hasattr(m, "data") and isinstance(m.data, str):
            rec["data"] = m.data
        print(json.dumps(rec), flush=True)
        if topic == spec.get("ack_topic"):
            pending.append((time.monotonic() + spec.get("ack_delay", 0.0), m, rec.get("stamp")))
    return cb
for topic, tname, qname in spec["subs"]:
    cls = imp(tname)
    prof = events_qos() if qname == "events" else Q.qos(qname)
    node.create_subscription(cls, topic, make_cb(topic, cls), prof, raw=True)
ev_pub.publish(String(data=json.dumps({"node": spec.get("name", "probe"), "event": "ready"})))
n_kf = 0
n_acks = 0
t_end = time.monotonic() + spec.get("duration", 60)
try:
    while rclpy.ok() and time.monotonic() < t_end:
        rclpy.spin_once(node, timeout_sec=0.01)
        while pending and pending[0][0] <= time.monotonic():
            _, m, stamp = pending.pop(0)
            a = FrameAck(); a.header.stamp = m.header.stamp; a.consumer = "tracker"
            every = spec.get("kf_every", 0)
            if every and n_acks % every == 0:
                a.is_keyframe = True; a.kf_id = n_kf; n_kf += 1
            n_acks += 1
            ack_pub.publish(a)
            print(json.dumps({"acked": stamp, "t": time.monotonic(), "kf": a.is_keyframe}), flush=True)
except Exception:
    pass
rclpy.try_shutdown()
'''


def start_probe(spec: dict, env, log: Path) -> subprocess.Popen:
    return start([PY, "-c", PROBE, json.dumps(spec)], env, log)


def read_jsonl(path: Path) -> List[dict]:
    out = []
    for line in Path(path).read_text(errors="replace").splitlines():
        line = line.strip()
        if line.startswith("{"):
            try:
                out.append(json.loads(line))
            except ValueError:
                pass
    return out


def wait_for(pred, timeout: float, step: float = 0.1) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if pred():
            return True
        time.sleep(step)
    return pred()
