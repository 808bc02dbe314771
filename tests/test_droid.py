"""The DROID-SLAM flow network: checkpoint loading (public layout), correlation lookup,
the FlowPredictor outputs BA consumes, determinism, the tracker / loop closer / ROS nodes
with ``tracking.flow_model``. Checkpoints are written by the tests with random weights."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from splat_slam_ros.cli.common import user_errors
from splat_slam_ros.config import ConfigError, SlamConfig, TrackingConfig
from splat_slam_ros.tracking.droid_flow import (DroidFlowPredictor, FlowModelError,
                                                load_droid_net, resolve_flow_device)
from splat_slam_ros.tracking.droid_net import CorrPyramid, DroidNet, coords_grid
from splat_slam_ros.tracking.flow_frontend import FlowPredictor, make_flow_predictor
from splat_slam_ros.types import Intrinsics

HEADS = ("update.weight.2", "update.delta.2")


def public_state_dict(seed: int = 0, head_bias: float = None):
    """Random weights in the layout of the public droid.pth: DataParallel ``module.``
    prefix, flow/confidence heads stored with 3 output channels."""
    torch.manual_seed(seed)
    sd = {"module." + k: v.clone() for k, v in DroidNet().state_dict().items()}
    for h in HEADS:
        sd[f"module.{h}.weight"] = torch.randn(3, 128, 3, 3) * 0.01
        sd[f"module.{h}.bias"] = torch.randn(3) * 0.01
    if head_bias is not None:          # a confidence head that is sure of nothing / everything
        sd["module.update.weight.2.weight"].zero_()
        sd["module.update.weight.2.bias"].fill_(head_bias)
    return sd


def write_ckpt(path: Path, **kw) -> Path:
    torch.save(public_state_dict(**kw), path)
    return path


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """One torch thread, as the tracker and the loop closer run (tracking.threads)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    return write_ckpt(tmp_path_factory.mktemp("droid") / "droid.pth")


def textured(h=96, w=128, seed=0, shift=0):
    rng = np.random.default_rng(seed)
    big = rng.integers(0, 256, (h // 4, (w + 32) // 4, 3), dtype=np.uint8)
    big = np.repeat(np.repeat(big, 4, 0), 4, 1)
    return np.ascontiguousarray(big[:, shift:shift + w])


# ----------------------------------------------------------------------------- loading
def test_public_layout_checkpoint_loads_with_module_prefix_and_sliced_heads(ckpt):
    net = load_droid_net(ckpt)
    raw = torch.load(ckpt, weights_only=True)
    got = net.state_dict()
    assert len(got) == len(raw)
    assert torch.equal(got["fnet.conv1.weight"], raw["module.fnet.conv1.weight"])
    assert torch.equal(got["update.gru.convq_glo.bias"], raw["module.update.gru.convq_glo.bias"])
    assert torch.equal(got["update.weight.2.weight"], raw["module.update.weight.2.weight"][:2])
    assert got["update.delta.2.bias"].shape == (2,)
    assert sum(v.numel() for v in got.values()) > 3_900_000      # the ~4M-parameter model


@pytest.mark.parametrize("how", ["renamed", "misshaped", "missing", "unexpected"])
def test_bad_checkpoint_key_is_named_in_the_error(tmp_path, how):
    sd = public_state_dict()
    key = "module.update.gru.convz.weight"
    if how == "renamed":
        sd["module.update.gru.conv_z.weight"] = sd.pop(key)
    elif how == "misshaped":
        sd[key] = torch.zeros(64, 448, 3, 3)
    elif how == "missing":
        del sd[key]
    else:
        sd["module.update.extra.bias"] = torch.zeros(3)
    p = tmp_path / "bad.pth"
    torch.save(sd, p)
    with pytest.raises(FlowModelError) as ei:
        load_droid_net(p)
    msg = str(ei.value)
    assert "\n" not in msg
    if how == "unexpected":
        assert "'update.extra.bias'" in msg and "unexpected" in msg
    else:
        assert "'update.gru.convz.weight'" in msg
    if how == "renamed":
        assert "'update.gru.conv_z.weight'" in msg
    if how == "misshaped":
        assert "(64, 448, 3, 3)" in msg and "(128, 448, 3, 3)" in msg


def test_missing_or_corrupt_file_is_a_user_error(tmp_path):
    assert issubclass(FlowModelError, ConfigError)
    assert any(issubclass(FlowModelError, c) for c in user_errors())   # CLIs print error: ...
    with pytest.raises(FlowModelError, match="checkpoint not found"):
        load_droid_net(tmp_path / "nope.pth")
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"this is not a checkpoint" * 10)
    with pytest.raises(FlowModelError, match="not a readable torch checkpoint"):
        load_droid_net(junk)
    lst = tmp_path / "list.pth"
    torch.save([torch.zeros(2)], lst)
    with pytest.raises(FlowModelError, match="does not hold a state dict"):
        load_droid_net(lst)
    nan = tmp_path / "nan.pth"
    sd = public_state_dict()
    sd["module.cnet.conv2.bias"][0] = float("nan")
    torch.save(sd, nan)
    with pytest.raises(FlowModelError, match="non-finite"):
        load_droid_net(nan)


def test_settings_are_checked(ckpt):
    with pytest.raises(FlowModelError, match="ba_downsample=8"):
        DroidFlowPredictor.from_checkpoint(ckpt, "cpu", ba_downsample=4)
    with pytest.raises(FlowModelError, match="flow_device"):
        resolve_flow_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(FlowModelError, match="CUDA is not available"):
            resolve_flow_device("cuda")
    assert resolve_flow_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    pred = DroidFlowPredictor.from_checkpoint(ckpt, "cpu")
    with pytest.raises(FlowModelError, match="at least 64x64"):
        pred.prepare(np.zeros((48, 64, 3), np.uint8))


# ----------------------------------------------------------------------------- correlation
def test_correlation_lookup_matches_the_volume_and_finds_a_shift():
    torch.manual_seed(1)
    C, h, w = 16, 12, 16
    fa = torch.randn(C, h, w)
    fb = torch.roll(fa, shifts=2, dims=2)             # b(x + 2) = a(x)
    pyr = CorrPyramid.pair(fa, fb)                     # edges a -> b, b -> a
    vol = CorrPyramid.volume(fa[None], fb[None])[0].view(h, w, h, w)
    c0 = coords_grid(h, w)[None]
    both = pyr.lookup(torch.cat([c0, c0]))             # (2, 196, h, w)
    feats = both[:1]
    y, x = 5, 6
    for dx in (-3, 0, 2, 3):
        for dy in (-1, 0, 3):
            ch = (dx + 3) * 7 + (dy + 3)               # x-offset major, as the reference kernel
            assert torch.allclose(feats[0, ch, y, x], vol[y, x, y + dy, x + dx], atol=1e-5)
    # sub-pixel coordinates interpolate bilinearly; outside the image the samples are 0
    c = c0.clone()
    c[0, y, x] += torch.tensor([0.5, 0.0])
    half = pyr.lookup(torch.cat([c, c0]))[0, 3 * 7 + 3, y, x]
    assert torch.allclose(half, 0.5 * (vol[y, x, y, x] + vol[y, x, y, x + 1]), atol=1e-5)
    assert float(feats[0, :3 * 7, :, 0].abs().max()) < 1e-6   # dx = -3..-1: left of column 0
    # the best match in the level-0 window of a is 2 px to the right; b -> a is the transpose
    best = feats[0, :49, 3:-3, 3:-3].argmax(0)
    assert (best == (2 + 3) * 7 + 3).float().mean() > 0.95
    back = both[1, :49, 3:-3, 3:-3].argmax(0)
    assert (back == (-2 + 3) * 7 + 3).float().mean() > 0.95
    assert len(pyr.levels) == 4 and pyr.levels[3].shape[-2:] == (h // 8, w // 8)
    # the level-k volume is the 2^k average over the target pixels
    lvl1 = vol[y, x].view(1, 1, h, w)
    assert torch.allclose(pyr.levels[1][y * w + x, 0],
                          torch.nn.functional.avg_pool2d(lvl1, 2)[0, 0], atol=1e-5)


# ----------------------------------------------------------------------------- predictor
def test_predictor_outputs_are_what_ba_consumes(ckpt):
    pred = make_flow_predictor(TrackingConfig(flow_model=str(ckpt), flow_device="cpu"))
    assert isinstance(pred, DroidFlowPredictor) and pred.ba_downsample == 8
    assert isinstance(pred, FlowPredictor)
    a, b = textured(), textured(shift=8)
    A, B = pred.prepare(a), pred.prepare(b)
    assert A.fmap.shape == (128, 12, 16) and A.fmap.dtype == torch.float16
    f_ij, w_ij, f_ji, w_ji = pred.predict_pair(A, B)
    for t in (f_ij, w_ij, f_ji, w_ji):
        assert t.shape == (12, 16, 2) and t.dtype == torch.float32 and torch.isfinite(t).all()
        assert not t.requires_grad and not t.is_inference()     # BA may edit them in place
    assert float(w_ij.min()) >= 0.0 and float(w_ij.max()) <= 1.0
    assert float(f_ij.abs().max()) < 64.0
    # an initial flow (induced by the current estimate) shifts the result by about as much
    init = torch.zeros(12, 16, 2)
    init[..., 0] = 1.0
    g_ij, _, g_ji, _ = pred.predict_pair(A, B, init_ij=init)
    assert 0.3 < float((g_ij - f_ij)[..., 0].mean()) < 1.7
    assert -1.7 < float((g_ji - f_ji)[..., 0].mean()) < -0.3      # inverse of the init
    # raw images are accepted too, and predict() is the forward half of predict_pair
    f2, w2 = pred.predict(a, b)
    assert torch.equal(f2, f_ij) and torch.equal(w2, w_ij)


def test_same_checkpoint_loaded_twice_gives_identical_outputs(ckpt, tmp_path):
    a, b = textured(seed=3), textured(seed=3, shift=4)
    outs = []
    for _ in range(2):
        pred = DroidFlowPredictor.from_checkpoint(ckpt, "cpu", iters=3)
        outs.append(pred.predict_pair(pred.prepare(a), pred.prepare(b)))
    for x, y in zip(*outs):
        assert torch.equal(x, y)
    other = DroidFlowPredictor.from_checkpoint(write_ckpt(tmp_path / "o.pth", seed=7), "cpu",
                                               iters=3)
    f_other = other.predict_pair(other.prepare(a), other.prepare(b))[0]
    assert not torch.equal(f_other, outs[0][0])           # the weights matter


# ----------------------------------------------------------------------------- tracker
def _cfg(ckpt, **tracking):
    cfg = SlamConfig()
    tc = cfg.tracking
    tc.flow_model, tc.flow_device, tc.flow_model_iters = str(ckpt), "cpu", 2
    tc.motion_filter_thresh = 0.0
    tc.keyframe_thresh = 0.0
    tc.warmup = 3
    tc.init_iters = 3
    tc.loop_closure = tc.global_ba = False
    for k, v in tracking.items():
        setattr(tc, k, v)
    return cfg


def test_tracker_runs_a_synthetic_sequence_with_the_network(ckpt):
    from test_tracker import make_sequence
    from splat_slam_ros.coordinator import track_sequence
    intr = Intrinsics(90.0, 90.0, 63.5, 47.5, 128, 96)
    frames, _ = make_sequence(7, intr, motion=(0.02, 0.006, 0.004), rot=0.006)
    res = track_sequence(frames, _cfg(ckpt, lost_min_valid=0.0), intr, progress=False)
    assert len(res.poses) == len(frames)
    assert np.isfinite(np.asarray(res.poses)).all()
    assert res.timings["flow"] > 0 and res.timings["ba"] > 0
    assert res.n_keyframes >= 3 and any(e.reason == "local_ba" for e in res.events)
    for e in res.events:
        assert np.isfinite(np.asarray(e.poses)).all()


def test_loop_closer_uses_the_network(ckpt):
    from splat_slam_ros.tracking.loop_closure import LoopCloser
    from splat_slam_ros.types import KeyframeData
    intr = Intrinsics(90.0, 90.0, 63.5, 47.5, 128, 96)
    lc = LoopCloser(_cfg(ckpt, lost_min_valid=0.0, loop_closure=True), intr)
    assert isinstance(lc.flow, DroidFlowPredictor)
    for k in range(2):
        P = np.eye(4)
        P[0, 3] = 0.02 * k
        lc.add_keyframe(KeyframeData(k, 3 * k, 0.1 * k, P, textured(seed=5, shift=2 * k), intr,
                                     np.full((12, 16), 0.5, np.float32),
                                     np.ones((12, 16), np.float32)))
    assert lc.timings["flow"] > 0 and len(lc.graph) >= 1
    with pytest.raises(FlowModelError, match="checkpoint not found"):
        LoopCloser(_cfg("/no/such/droid.pth"), intr)


# ----------------------------------------------------------------------------- ROS nodes
FEED = r'''
import json, sys, time
from splat_slam_ros.ros_env import apply_ros_environment
apply_ros_environment()
import numpy as np, rclpy
from sensor_msgs.msg import Image, CameraInfo
from splat_slam_msgs.msg import FrameAck
from splat_slam_nodes import convert, qos as Q
from splat_slam_nodes.node_common import TOPICS
from splat_slam_ros.types import Intrinsics
n_frames, timeout = int(sys.argv[1]), float(sys.argv[2])
rclpy.init()
node = rclpy.create_node("droid_feed")
acks = []
node.create_subscription(FrameAck, TOPICS["ack"], lambda m: acks.append(m), Q.ack_qos())
pi = node.create_publisher(Image, "/cam/image", Q.image_qos())
pc = node.create_publisher(CameraInfo, "/cam/info", Q.image_qos())
def spin_until(cond, t):
    t0 = time.monotonic()
    while not cond() and time.monotonic() - t0 < t:
        rclpy.spin_once(node, timeout_sec=0.05)
    return bool(cond())
ok = spin_until(lambda: pi.get_subscription_count() and pc.get_subscription_count(), 120)
pc.publish(convert.intrinsics_to_camera_info(Intrinsics(90, 90, 63.5, 47.5, 128, 96)))
spin_until(lambda: False, 0.5)
rng = np.random.default_rng(0)
big = np.repeat(np.repeat(rng.integers(0, 256, (24, 48, 3), dtype=np.uint8), 4, 0), 4, 1)
for i in range(n_frames):
    m = convert.image_to_msg(np.ascontiguousarray(big[:, 2 * i: 2 * i + 128]), "rgb8")
    m.header.stamp = convert.to_stamp(1.0 + 0.1 * i)
    k = len(acks)
    pi.publish(m)
    spin_until(lambda: len(acks) > k, timeout)
print("RESULT " + json.dumps({"matched": ok, "acks": len(acks)}), flush=True)
rclpy.try_shutdown()
'''


def _finish(tmp_path, node, feed, log, expect_exit):
    """Wait for the feeder; the node's exit status (None: still running), its RESULT, its log."""
    from test_graph_support import stop, wait_for
    try:
        assert feed.wait(timeout=300) == 0, (tmp_path / "feed.log").read_text()[-3000:]
        if expect_exit:
            wait_for(lambda: node.poll() is not None, 30)
        rc = node.poll()
    finally:
        stop(feed)
        stop(node)
    res = [json.loads(x[7:]) for x in (tmp_path / "feed.log").read_text().splitlines()
           if x.startswith("RESULT ")]
    assert res, (tmp_path / "feed.log").read_text()[-3000:]
    return res[0], rc, log.read_text(errors="replace")


def _tracker_node(tmp_path, flow_model, n_frames, timeout, expect_exit=False):
    from test_graph_support import PY, isolated_env, need_ros, start
    need_ros()
    env = isolated_env()
    log = tmp_path / "tracker.log"
    node = start([PY, "-m", "splat_slam_nodes.tracker_node", "--ros-args",
                  "-p", "ros.image_topic:=/cam/image", "-p", "ros.camera_info_topic:=/cam/info",
                  "-p", "node.input_qos:=reliable", "-p", "node.loop_closure:=false",
                  "-p", f"tracking.flow_model:={flow_model}", "-p", "tracking.flow_device:=cpu",
                  "-p", "tracking.flow_model_iters:=1"], env, log)
    feed = start([PY, "-c", FEED, str(n_frames), str(timeout)], env, tmp_path / "feed.log")
    return _finish(tmp_path, node, feed, log, expect_exit)


@pytest.mark.ros
def test_tracker_node_takes_the_flow_model_parameter(tmp_path):
    # a network whose confidence head is sure of nothing: every flow is rejected, which the
    # classical DIS front end would never do on this textured, sliding input
    ck = write_ckpt(tmp_path / "unsure.pth", head_bias=-30.0)
    res, rc, log = _tracker_node(tmp_path, ck, 3, 120)
    assert res["matched"] and res["acks"] == 3, log[-3000:]
    assert rc is None, log[-3000:]
    assert "tracker started on 128x96" in log
    assert "tracking lost (low flow confidence (0.00))" in log, log[-3000:]


@pytest.mark.ros
def test_tracker_node_rejects_a_bad_checkpoint_path(tmp_path):
    res, rc, log = _tracker_node(tmp_path, tmp_path / "missing.pth", 1, 20, expect_exit=True)
    assert rc == 2, log[-3000:]
    assert "cannot start the tracker: tracking.flow_model: checkpoint not found" in log, log[-3000:]
    assert "Traceback" not in log


FEED_KF = r'''
import json, sys, time
from splat_slam_ros.ros_env import apply_ros_environment
apply_ros_environment()
import numpy as np, rclpy
from splat_slam_msgs.msg import FrameAck, Keyframe
from splat_slam_nodes import convert, qos as Q
from splat_slam_nodes.node_common import TOPICS
from splat_slam_ros.types import Intrinsics, KeyframeData
n_kf, timeout = int(sys.argv[1]), float(sys.argv[2])
rclpy.init()
node = rclpy.create_node("droid_kf_feed")
acks = []
node.create_subscription(FrameAck, TOPICS["ack"],
                         lambda m: acks.append(m) if m.consumer == "loop_closure" else None,
                         Q.ack_qos())
pk = node.create_publisher(Keyframe, TOPICS["keyframes"], Q.keyframe_qos())
def spin_until(cond, t):
    t0 = time.monotonic()
    while not cond() and time.monotonic() - t0 < t:
        rclpy.spin_once(node, timeout_sec=0.05)
    return bool(cond())
ok = spin_until(lambda: pk.get_subscription_count() >= 1, 120)
spin_until(lambda: False, 0.5)
intr = Intrinsics(90.0, 90.0, 63.5, 47.5, 128, 96)
rng = np.random.default_rng(0)
big = np.repeat(np.repeat(rng.integers(0, 256, (24, 48, 3), dtype=np.uint8), 4, 0), 4, 1)
for k in range(n_kf):
    P = np.eye(4); P[0, 3] = 0.02 * k
    kf = KeyframeData(k, 3 * k, 1.0 + 0.1 * k, P, np.ascontiguousarray(big[:, 4 * k: 4 * k + 128]),
                      intr, np.full((12, 16), 0.5, np.float32), np.ones((12, 16), np.float32))
    pk.publish(convert.keyframe_to_msg(kf))
    spin_until(lambda: False, 0.3)
spin_until(lambda: len(acks) >= n_kf, timeout)
print("RESULT " + json.dumps({"matched": ok, "acks": len(acks)}), flush=True)
rclpy.try_shutdown()
'''


def _loop_node(tmp_path, flow_model, timeout, expect_exit=False):
    from test_graph_support import PY, isolated_env, need_ros, start
    need_ros()
    env = isolated_env()
    log = tmp_path / "loop.log"
    node = start([PY, "-m", "splat_slam_nodes.loop_closure_node", "--ros-args",
                  "-p", f"tracking.flow_model:={flow_model}", "-p", "tracking.flow_device:=cpu",
                  "-p", "tracking.flow_model_iters:=1", "-p", "tracking.global_ba_every:=100"],
                 env, log)
    feed = start([PY, "-c", FEED_KF, "2", str(timeout)], env, tmp_path / "feed.log")
    return _finish(tmp_path, node, feed, log, expect_exit)


@pytest.mark.ros
def test_loop_closure_node_takes_the_flow_model_parameter(tmp_path, ckpt):
    res, rc, log = _loop_node(tmp_path, ckpt, 120)
    assert res["matched"] and res["acks"] == 2 and rc is None, log[-3000:]
    assert "Traceback" not in log and "dropped input" not in log, log[-3000:]


@pytest.mark.ros
def test_loop_closure_node_rejects_a_bad_checkpoint(tmp_path):
    bad = tmp_path / "bad.pth"
    sd = public_state_dict()
    sd["module.update.agg.conv1.weight"] = torch.zeros(1)
    torch.save(sd, bad)
    res, rc, log = _loop_node(tmp_path, bad, 15, expect_exit=True)
    assert rc == 2 and res["acks"] == 0, log[-3000:]
    assert "cannot run the loop_closure stage: tracking.flow_model:" in log, log[-3000:]
    assert "'update.agg.conv1.weight' has shape (1,)" in log, log[-3000:]
