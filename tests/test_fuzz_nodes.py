"""Fuzzing: malformed and random messages on every topic the graph's nodes subscribe to never
crash a node; they are logged and dropped, and the graph still works afterwards."""
from pathlib import Path

import pytest

from test_graph_support import TINY_LOOP_TRACKING_CFG, PY, isolated_env, need_ros, start, stop
from test_graph_nodes import _result

pytestmark = pytest.mark.ros

FUZZER = Path(__file__).resolve().parent / "ros_helpers" / "fuzz_corpus.py"
CFG = TINY_LOOP_TRACKING_CFG + """mapping:
  iters_first: 10
  iters_per_keyframe: 3
  final_refine_iters: 3
  random_views_per_iter: 1
  window_views_per_iter: 2
  downsample: 4
  downsample_first: 4
"""
NODES = ("tracker", "loop_closure", "depth", "mapper")


def test_fuzz_corpus_on_every_topic_leaves_every_node_alive(tmp_path):
    need_ros()
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(CFG)
    env = isolated_env()
    procs = {}
    for name in NODES:
        args = [PY, "-m", f"splat_slam_nodes.{name}_node", "--ros-args", "-r", f"__node:={name}",
                "-p", f"config_file:={cfg}", "-p", "node.loop_closure:=true"]
        if name == "tracker":
            args += ["-p", "ros.image_topic:=/fuzz/image", "-p", "ros.camera_info_topic:=/fuzz/info",
                     "-p", "node.input_qos:=reliable", "-p", "node.camera_info_timeout:=1.0"]
        procs[name] = start(args, env, tmp_path / f"{name}.log")
    fuzzer = start([PY, str(FUZZER), "/fuzz/image", "/fuzz/info"], env, tmp_path / "fuzzer.log")
    try:
        assert fuzzer.wait(timeout=600) == 0, (tmp_path / "fuzzer.log").read_text()[-3000:]
        alive = {n: p.poll() is None for n, p in procs.items()}
    finally:
        for p in [fuzzer] + list(procs.values()):
            stop(p)
    logs = {n: (tmp_path / f"{n}.log").read_text(errors="replace") for n in NODES}
    r = _result(tmp_path / "fuzzer.log")
    assert r["matched"], logs
    assert alive == {n: True for n in NODES}, {n: logs[n][-3000:] for n in NODES}
    assert r["sent"] > 150
    # still answering: the tracker acknowledges a valid frame, the mapper's service answers
    assert r["tracker_ack"], logs["tracker"][-3000:]
    assert r["render_answer"] is not None, logs["mapper"][-3000:]
    assert set(NODES) <= set(r["nodes"]), r["nodes"]
    # the bad input was logged (and dropped) by every node, never by an unexpected exception
    for n in NODES:
        assert "cannot be deserialised" in logs[n], (n, logs[n][-3000:])
        assert "Traceback" not in logs[n], (n, logs[n][-5000:])
    assert "keyframe id 4294967295 is out of range" in logs["mapper"]


def test_message_checks_refuse_implausible_messages():
    need_ros()
    import array
    from splat_slam_msgs.msg import Keyframe, PoseGraphUpdate, ProxyDepth
    from splat_slam_nodes import msg_checks as C
    from splat_slam_nodes.convert import ConversionError

    def kf(**kw):
        k = Keyframe(kf_id=3, width=64, height=48, disp_width=8, disp_height=6,
                     intrinsics=[50.0, 50.0, 31.5, 23.5])
        for a, v in kw.items():
            setattr(k, a, v)
        return k
    assert C.check_keyframe(kf()) is not None
    bad_pose = kf(); bad_pose.pose.position.x = float("nan")
    zero_q = kf(); zero_q.pose.orientation.w = 0.0
    cases = [(kf(kf_id=2**32 - 1), "out of range"), (bad_pose, "NaN"), (zero_q, "zero quaternion"),
             (kf(intrinsics=[0.0] * 4), "fx, fy > 0"), (kf(width=100000), "outside 1..16384"),
             (kf(disparity=array.array("f", [float("inf")] * 48)), "disparity contains NaN"),
             (kf(batch_size=2**32 - 1), "batch")]
    for msg, text in cases:
        with pytest.raises(ConversionError, match=text):
            C.check_keyframe(msg)
    with pytest.raises(ConversionError, match="seq"):
        C.check_update(PoseGraphUpdate(seq=2**64 - 1))
    with pytest.raises(ConversionError, match="keyframe id 4294967295"):
        C.check_update(PoseGraphUpdate(seq=3, kf_ids=[0, 2**32 - 1]))
    C.check_update(PoseGraphUpdate(seq=3, kf_ids=[0, 1]))
    with pytest.raises(ConversionError, match="out of range"):
        C.check_proxy_depth(ProxyDepth(kf_id=2**32 - 1, width=8, height=6))
    C.check_proxy_depth(ProxyDepth(kf_id=1, width=8, height=6))
    ok = ProxyDepth(kf_id=1, width=2, height=2, source=array.array("B", [0, 1, 2, 3]))
    C.check_proxy_depth(ok)
    with pytest.raises(ConversionError, match="source values must be 0..3"):
        C.check_proxy_depth(ProxyDepth(kf_id=1, width=2, height=2,
                                       source=array.array("B", [0, 1, 7, 3])))
