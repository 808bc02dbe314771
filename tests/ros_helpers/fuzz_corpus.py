"""Fuzz corpus for every topic the graph's nodes subscribe to (test_fuzz_nodes.py).

Run as a script with the project's ROS environment: publishes malformed and random messages
(undecodable bytes, wrong sizes, NaN poses, "negative" ids (all bits set), out-of-order and
duplicate sequence numbers, huge arrays and sizes, bad JSON events), then checks that the
graph still works: the tracker acknowledges a valid frame, the mapper's render service
answers. Prints one line ``RESULT {json}``.
"""
import array
import json
import math
import sys
import time

from splat_slam_ros.ros_env import apply_ros_environment

apply_ros_environment()

import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from geometry_msgs.msg import Pose, PoseStamped  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from splat_slam_msgs.msg import FrameAck, Keyframe, PoseGraphUpdate, ProxyDepth  # noqa: E402
from splat_slam_msgs.srv import RenderPose  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from splat_slam_nodes import convert, qos as Q  # noqa: E402
from splat_slam_nodes.node_common import SERVICES, TOPICS, events_qos  # noqa: E402
from splat_slam_ros.types import Intrinsics  # noqa: E402

IMAGE, INFO = sys.argv[1], sys.argv[2]
U32, U64 = 2**32 - 1, 2**64 - 1          # "negative" ids: what -1 looks like on the wire
NAN = float("nan")
rng = np.random.default_rng(int(sys.argv[3]) if len(sys.argv) > 3 else 0)


def pose(x=0.0, qw=1.0):
    p = Pose()
    p.position.x = x
    p.orientation.w = qw
    return p


def garbage():
    """Undecodable / random byte strings, 1 byte to 4 MiB (the empty payload: see main())."""
    out = [b"\x00", b"\x00\x01\x00\x00", b"\x00\x01\x00\x00" + bytes(range(256)) * 4]
    for n in (7, 100, 4096, 4 << 20):
        out.append(b"\x00\x01\x00\x00" + rng.integers(0, 256, n, dtype=np.uint8).tobytes())
    return out


def keyframes(img):
    def kf(kf_id=0, w=64, h=48, **kw):
        k = Keyframe()
        k.kf_id, k.width, k.height = kf_id, w, h
        k.intrinsics = [50.0, 50.0, 31.5, 23.5]
        k.pose = pose()
        k.image = convert.image_to_msg(img, "rgb8")
        k.disp_width, k.disp_height = 8, 6
        k.disparity = array.array("f", [0.5] * 48)
        k.confidence = array.array("f", [1.0] * 48)
        for a, v in kw.items():
            setattr(k, a, v)
        return k
    return [kf(kf_id=U32), kf(kf_id=5, pose=pose(NAN)), kf(kf_id=6, pose=pose(qw=0.0)),
            kf(kf_id=7, intrinsics=[NAN, 50.0, 31.5, 23.5]), kf(kf_id=8, intrinsics=[0.0] * 4),
            kf(kf_id=9, w=100000, h=100000), kf(kf_id=10, w=0, h=0),
            kf(kf_id=11, disparity=array.array("f", [0.5] * 7)),
            kf(kf_id=12, disp_width=100000, disp_height=100000),
            kf(kf_id=13, disparity=array.array("f", [NAN] * 48)),
            kf(kf_id=14, confidence=array.array("f", [1.0] * 5)),
            kf(kf_id=15, has_mono_depth=True, mono_width=8, mono_height=6,
               mono_depth=array.array("f", [1.0] * 3)),
            kf(kf_id=16, batch_id=U32, batch_size=U32),
            kf(kf_id=17, disparity=array.array("f", np.zeros(2_000_000, np.float32).tobytes())),
            kf(kf_id=3), kf(kf_id=3), kf(kf_id=1)]           # out of order + duplicate


def updates():
    def up(seq=1, ids=(0,), poses=None, **kw):
        u = PoseGraphUpdate()
        u.seq, u.reason = seq, 1
        u.kf_ids = array.array("I", ids)
        u.poses = [pose() for _ in ids] if poses is None else poses
        for a, v in kw.items():
            setattr(u, a, v)
        return u
    return [up(seq=U64), up(seq=5, ids=(U32,)), up(seq=6, poses=[pose(NAN)]),
            up(seq=7, ids=(0, 1, 2), poses=[pose()]), up(seq=8, ids=(), poses=[pose()]),
            up(seq=9, reason=250), up(seq=10, disparities=array.array("f", [1.0] * 3),
                                       disp_width=8, disp_height=6),
            up(seq=11, ids=tuple(range(200000)), poses=[]),
            up(seq=4), up(seq=4), up(seq=2), up(seq=0, poses_only=True)]


def proxy_depths():
    def pd(kf_id=0, w=8, h=6, **kw):
        m = ProxyDepth()
        m.kf_id, m.width, m.height = kf_id, w, h
        m.depth = array.array("f", [1.0] * (w * h if w * h < 10**6 else 10))
        m.source = array.array("B", [1] * (w * h if w * h < 10**6 else 10))
        m.pose = pose()
        for a, v in kw.items():
            setattr(m, a, v)
        return m
    return [pd(kf_id=U32), pd(kf_id=0, depth=array.array("f", [1.0] * 5)),
            pd(kf_id=0, w=100000, h=100000), pd(kf_id=0, depth=array.array("f", [NAN] * 48)),
            pd(kf_id=0, pose=pose(NAN)), pd(kf_id=0, revision=U32, update_seq=U64, is_update=True),
            pd(kf_id=0, source=array.array("B", [7, 7, 7])), pd(kf_id=99), pd(kf_id=0), pd(kf_id=0)]


def images(img):
    out = []
    m = convert.image_to_msg(img, "rgb8"); m.width, m.height = 100000, 100000; out.append(m)
    m = convert.image_to_msg(img, "rgb8"); m.step = 1; out.append(m)
    m = convert.image_to_msg(img, "rgb8"); m.step = U32; out.append(m)
    m = convert.image_to_msg(img, "rgb8"); m.width = 0; out.append(m)
    m = convert.image_to_msg(img, "rgb8"); m.encoding = ""; out.append(m)
    m = convert.image_to_msg(img, "rgb8"); m.data = array.array("B", bytes(4 << 20)); out.append(m)
    return out


def camera_infos():
    out = []
    for k, w, h in (([NAN] * 9, 64, 48), ([0.0] * 9, 64, 48), ([50, 0, 31.5, 0, 50, 23.5, 0, 0, 1], 0, 0),
                    ([50, 0, 31.5, 0, 50, 23.5, 0, 0, 1], 100000, 100000),
                    ([-50, 0, 31.5, 0, -50, 23.5, 0, 0, 1], 64, 48)):
        m = CameraInfo(); m.k = [float(x) for x in k]; m.width, m.height = w, h
        out.append(m)
    m = convert.intrinsics_to_camera_info(Intrinsics(50, 50, 31.5, 23.5, 64, 48))
    m.distortion_model = "plumb_bob"; m.d = [NAN] * 5; out.append(m)
    return out


def render_requests():
    out = []
    for p in (pose(NAN), pose(qw=0.0), pose(1e308), pose(math.inf)):
        m = PoseStamped(); m.header.frame_id = "map"; m.pose = p; out.append(m)
    return out


def events():
    texts = ["", "not json", "[1, 2]", "null", '{"event": 5}', '{"node": [], "event": {}}',
             '{"event": "finalized", "node": null}', '{"event": "end_of_stream", "frames": "x"}',
             '{"event": "finalized", "node": "loop_closure", "seq": "NaN", "kf_ids": 7}',
             "{" * 10000, json.dumps({"event": "x" * 100000})]
    return [String(data=t) for t in texts]


def main():
    rclpy.init()
    node = rclpy.create_node("fuzzer")
    acks = []
    node.create_subscription(FrameAck, TOPICS["ack"], lambda m: acks.append(m), Q.ack_qos())
    spec = {   # topic -> (type, qos, corpus builder)
        IMAGE: (Image, Q.image_qos()), INFO: (CameraInfo, Q.image_qos()),
        TOPICS["keyframes"]: (Keyframe, Q.keyframe_qos()),
        TOPICS["updates"]: (PoseGraphUpdate, Q.pose_graph_qos()),
        TOPICS["proxy_depth"]: (ProxyDepth, Q.proxy_depth_qos()),
        TOPICS["render_request"]: (PoseStamped, Q.pose_qos()),
        TOPICS["events"]: (String, events_qos()),
    }
    pubs = {t: node.create_publisher(c, t, q) for t, (c, q) in spec.items()}
    # an empty payload stalls the Fast DDS writer that sends it (not the reader: measured),
    # so it goes through a publisher of its own
    empty = {t: node.create_publisher(c, t, q) for t, (c, q) in spec.items()}

    def spin_until(cond, timeout):
        t0 = time.monotonic()
        while not cond() and time.monotonic() - t0 < timeout:
            rclpy.spin_once(node, timeout_sec=0.05)
        return bool(cond())
    need = {IMAGE: 1, INFO: 1, TOPICS["keyframes"]: 3, TOPICS["updates"]: 3,
            TOPICS["proxy_depth"]: 1, TOPICS["render_request"]: 1, TOPICS["events"]: 4}
    res = {"matched": spin_until(lambda: all(pubs[t].get_subscription_count() >= n
                                             for t, n in need.items()), 180)}
    img = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    corpus = {IMAGE: images(img), INFO: camera_infos(), TOPICS["keyframes"]: keyframes(img),
              TOPICS["updates"]: updates(), TOPICS["proxy_depth"]: proxy_depths(),
              TOPICS["render_request"]: render_requests(), TOPICS["events"]: events()}
    sent = 0
    for rnd in range(2):                       # the corpus twice: duplicates of everything
        for topic, msgs in corpus.items():
            if rnd == 0:
                empty[topic].publish(b"")
                sent += 1
            for m in garbage():
                pubs[topic].publish(m)
                sent += 1
            for m in msgs:
                pubs[topic].publish(serialize_message(m) if rnd else m)
                sent += 1
            spin_until(lambda: False, 0.3)
    res["sent"] = sent
    spin_until(lambda: False, 3.0)
    # the graph still works: a valid camera_info + frame is acknowledged by the tracker
    pubs[INFO].publish(convert.intrinsics_to_camera_info(Intrinsics(50, 50, 31.5, 23.5, 64, 48)))
    spin_until(lambda: False, 0.5)
    n = len(acks)
    f = convert.image_to_msg(img, "rgb8")
    f.header.stamp = convert.to_stamp(100.0)
    pubs[IMAGE].publish(f)
    res["tracker_ack"] = spin_until(lambda: any(a.consumer == "tracker" for a in acks[n:]), 120)
    cli = node.create_client(RenderPose, SERVICES["render"])
    rq = RenderPose.Request(); rq.pose = pose(); rq.width, rq.height = 64, 48
    res["render_answer"] = None
    if cli.wait_for_service(timeout_sec=60):
        fut = cli.call_async(rq)
        spin_until(lambda: fut.done(), 120)
        if fut.done():
            res["render_answer"] = [fut.result().success, fut.result().message]
    res["nodes"] = sorted(node.get_node_names())
    print("RESULT " + json.dumps(res), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
