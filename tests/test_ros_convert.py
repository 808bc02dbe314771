"""numpy / project types <-> ROS 2 message conversions (splat_slam_nodes.convert).

Every round trip goes through real CDR serialisation, as between two processes.
"""
import time
from dataclasses import replace

import numpy as np
import pytest

pytestmark = pytest.mark.ros

import rclpy  # noqa: F401
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo, Image
from splat_slam_msgs.msg import FrameAck, Keyframe, PoseGraphUpdate, ProxyDepth

from splat_slam_nodes import convert as C
from splat_slam_ros.types import Intrinsics, KeyframeData, UpdateEvent
from splat_slam_ros.types import ProxyDepth as CoreProxyDepth


def wire(msg):
    """Serialise and deserialise like DDS would."""
    return deserialize_message(serialize_message(msg), type(msg))


def random_pose(rng):
    from scipy.spatial.transform import Rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    T[:3, 3] = rng.normal(size=3) * 5
    return T


RNG = np.random.default_rng(42)
SAMPLES = {
    "rgb8": RNG.integers(0, 256, (7, 5, 3), dtype=np.uint8),
    "bgr8": RNG.integers(0, 256, (7, 5, 3), dtype=np.uint8),
    "rgba8": RNG.integers(0, 256, (7, 5, 4), dtype=np.uint8),
    "bgra8": RNG.integers(0, 256, (7, 5, 4), dtype=np.uint8),
    "mono8": RNG.integers(0, 256, (7, 5), dtype=np.uint8),
    "16UC1": RNG.integers(0, 65536, (7, 5), dtype=np.uint16),
    "32FC1": RNG.normal(size=(7, 5)).astype(np.float32),
}


# ------------------------------------------------------------------ images
@pytest.mark.parametrize("enc", sorted(SAMPLES))
def test_image_round_trip_every_encoding(enc):
    a = SAMPLES[enc]
    m = wire(C.image_to_msg(a, enc, stamp=12.5, frame_id="cam"))
    assert (m.encoding, m.width, m.height, m.header.frame_id) == (enc, 5, 7, "cam")
    assert m.step == 5 * a.itemsize * (a.shape[2] if a.ndim == 3 else 1)
    b = C.msg_to_image(m)
    assert b.dtype == a.dtype and b.shape == a.shape
    np.testing.assert_array_equal(a, b)
    assert C.from_stamp(m.header.stamp) == 12.5


def test_encoding_guessed_from_shape_and_dtype():
    assert C.image_to_msg(SAMPLES["rgb8"]).encoding == "rgb8"
    assert C.image_to_msg(SAMPLES["rgba8"]).encoding == "rgba8"
    assert C.image_to_msg(SAMPLES["mono8"]).encoding == "mono8"
    assert C.image_to_msg(SAMPLES["16UC1"]).encoding == "16UC1"
    assert C.image_to_msg(SAMPLES["32FC1"]).encoding == "32FC1"
    with pytest.raises(C.UnsupportedEncoding, match="float64"):
        C.image_to_msg(np.zeros((4, 4)))


def test_unsupported_encoding_is_a_clear_error():
    with pytest.raises(C.UnsupportedEncoding, match="nv21"):
        C.image_to_msg(SAMPLES["rgb8"], "nv21")
    m = C.image_to_msg(SAMPLES["rgb8"])
    m.encoding = "8SC3"
    with pytest.raises(C.UnsupportedEncoding, match="8SC3.*supported: rgb8"):
        C.msg_to_image(m)
    assert issubclass(C.UnsupportedEncoding, C.ConversionError)
    assert issubclass(C.ConversionError, ValueError)


def test_array_that_does_not_fit_the_encoding():
    with pytest.raises(C.ConversionError, match="dtype float64"):
        C.image_to_msg(np.zeros((4, 4)), "32FC1")
    with pytest.raises(C.ConversionError, match="shape"):
        C.image_to_msg(SAMPLES["rgb8"], "mono8")
    with pytest.raises(C.ConversionError, match="shape"):
        C.image_to_msg(SAMPLES["rgba8"], "rgb8")


@pytest.mark.parametrize("enc", ["rgb8", "32FC1", "16UC1"])
def test_truncated_or_oversized_data_is_rejected(enc):
    m = C.image_to_msg(SAMPLES[enc], enc)
    full = bytes(m.data)
    m.data = full[:-1]
    with pytest.raises(C.ConversionError, match="bytes, expected"):
        C.msg_to_image(wire(m))
    m.data = full + b"\0" * 7
    with pytest.raises(C.ConversionError, match="bytes, expected"):
        C.msg_to_image(m)
    m.data = full
    m.step = 3                                    # smaller than a row
    with pytest.raises(C.ConversionError, match="step"):
        C.msg_to_image(m)


def test_row_padding_and_big_endian():
    a = SAMPLES["16UC1"]
    m = Image(height=7, width=5, encoding="16UC1", is_bigendian=1, step=16)
    padded = np.zeros((7, 16), np.uint8)
    padded[:, :10] = a.astype(">u2").view(np.uint8).reshape(7, 10)
    m.data = padded.tobytes()
    b = C.msg_to_image(wire(m))
    assert b.dtype == np.uint16 and b.dtype.isnative
    np.testing.assert_array_equal(a, b)
    # rgb8 with a padded step
    c = SAMPLES["rgb8"]
    m = Image(height=7, width=5, encoding="rgb8", step=20)
    p = np.zeros((7, 20), np.uint8)
    p[:, :15] = c.reshape(7, 15)
    m.data = p.tobytes()
    np.testing.assert_array_equal(C.msg_to_image(m), c)


def test_msg_to_rgb_converts_channel_orders():
    rgb = SAMPLES["rgb8"]
    np.testing.assert_array_equal(C.msg_to_rgb(C.image_to_msg(rgb[:, :, ::-1].copy(), "bgr8")), rgb)
    rgba = np.concatenate([rgb, np.full((7, 5, 1), 9, np.uint8)], 2)
    np.testing.assert_array_equal(C.msg_to_rgb(C.image_to_msg(rgba, "rgba8")), rgb)
    bgra = np.ascontiguousarray(rgba[:, :, [2, 1, 0, 3]])
    np.testing.assert_array_equal(C.msg_to_rgb(C.image_to_msg(bgra, "bgra8")), rgb)
    g = SAMPLES["mono8"]
    out = C.msg_to_rgb(C.image_to_msg(g))
    assert out.shape == (7, 5, 3) and (out == g[:, :, None]).all()
    with pytest.raises(C.UnsupportedEncoding, match="not a colour image"):
        C.msg_to_rgb(C.image_to_msg(SAMPLES["32FC1"]))


def test_copy_false_gives_a_view_of_the_message():
    m = wire(C.image_to_msg(SAMPLES["32FC1"]))
    v = C.msg_to_image(m, copy=False)
    c = C.msg_to_image(m)
    v[0, 0] = 123.0
    assert C.msg_to_image(m)[0, 0] == 123.0 and c[0, 0] != 123.0


def test_large_image_conversion_is_fast():
    """The numpy -> sequence-field slow path takes 37-92 ms for 640x480; ours well under."""
    img = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    dep = np.random.default_rng(0).random((480, 640), dtype=np.float32)
    t_to, t_from = [], []
    for _ in range(5):
        t0 = time.perf_counter()
        mi, md = C.image_to_msg(img), C.image_to_msg(dep)
        t1 = time.perf_counter()
        C.msg_to_image(mi), C.msg_to_image(md)
        t_to.append(t1 - t0)
        t_from.append(time.perf_counter() - t1)
    assert min(t_to) < 0.015 and min(t_from) < 0.015, (t_to, t_from)


# ------------------------------------------------------------------ stamps, camera info, poses
def test_stamp_round_trip_to_the_nanosecond():
    for t in (0.0, 1.5, 1403715273.262143, 1e-9, 59.999999999):
        s = C.to_stamp(t)
        assert 0 <= s.nanosec < 1_000_000_000
        assert abs(C.from_stamp(s) - t) < 5e-7
    assert C.to_stamp(1403715273.262142976).nanosec // 1000 == 262142
    with pytest.raises(C.ConversionError, match="negative"):
        C.to_stamp(-1.0)


def test_camera_info_round_trip():
    intr = Intrinsics(458.654, 457.296, 367.215, 248.375, 752, 480, "plumb_bob",
                      [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])
    m = wire(C.intrinsics_to_camera_info(intr, stamp=3.0, frame_id="cam0"))
    assert m.k[0] == intr.fx and m.k[2] == intr.cx and m.p[5] == intr.fy and m.k[8] == 1.0
    back = C.camera_info_to_intrinsics(m)
    assert back == intr
    eq = Intrinsics(100, 100, 50, 40, 100, 80, "equidistant", [0.1, 0.01, 0.0, 0.0])
    assert C.camera_info_to_intrinsics(wire(C.intrinsics_to_camera_info(eq))) == eq
    with pytest.raises(C.ConversionError, match="uncalibrated"):
        C.camera_info_to_intrinsics(CameraInfo(width=10, height=10))


def test_pose_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(10):
        T = random_pose(rng)
        m = wire(C.pose_to_msg(T))
        q = np.array([m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w])
        assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0
        np.testing.assert_allclose(C.msg_to_pose(m), T, atol=1e-12)
    Ts = np.stack([random_pose(rng) for _ in range(6)])
    np.testing.assert_allclose(C.msgs_to_poses(C.poses_to_msgs(Ts)), Ts, atol=1e-12)
    with pytest.raises(C.ConversionError, match="4x4"):
        C.pose_to_msg(np.eye(3))
    with pytest.raises(C.ConversionError, match="non-finite"):
        C.pose_to_msg(np.full((4, 4), np.nan))


# ------------------------------------------------------------------ project messages
def make_keyframe(rng, mono=True, H=24, W=32):
    return KeyframeData(
        kf_id=7, frame_index=41, timestamp=1403715273.262143, pose=random_pose(rng),
        image=rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
        intrinsics=Intrinsics(30.0, 31.0, 15.5, 11.5, W, H),
        disparity=rng.random((H // 4, W // 4), dtype=np.float32),
        confidence=rng.random((H // 4, W // 4), dtype=np.float32),
        mono_depth=rng.random((H, W), dtype=np.float32) if mono else None)


@pytest.mark.parametrize("mono", [True, False])
def test_keyframe_round_trip(mono):
    kf = make_keyframe(np.random.default_rng(2), mono)
    kf.batch_id, kf.batch_size = 5, 3                  # third of the warm-up batch 5, 6, 7
    m = wire(C.keyframe_to_msg(kf, frame_id="world"))
    assert isinstance(m, Keyframe) and m.header.frame_id == "world" and m.image.encoding == "rgb8"
    assert (m.disp_width, m.disp_height, m.width, m.height) == (8, 6, 32, 24)
    assert m.has_mono_depth == mono
    k2 = C.msg_to_keyframe(m)
    assert (k2.kf_id, k2.frame_index, k2.batch_id, k2.batch_size) == (7, 41, 5, 3)
    single = C.msg_to_keyframe(wire(C.keyframe_to_msg(make_keyframe(np.random.default_rng(2)))))
    assert (single.batch_id, single.batch_size) == (7, 1)       # a batch of its own
    assert abs(k2.timestamp - kf.timestamp) < 5e-7
    np.testing.assert_allclose(k2.pose, kf.pose, atol=1e-12)
    np.testing.assert_array_equal(k2.image, kf.image)
    np.testing.assert_array_equal(k2.disparity, kf.disparity)
    np.testing.assert_array_equal(k2.confidence, kf.confidence)
    assert k2.intrinsics == kf.intrinsics
    if mono:
        np.testing.assert_array_equal(k2.mono_depth, kf.mono_depth)
    else:
        assert k2.mono_depth is None and len(m.mono_depth) == 0


def test_keyframe_errors():
    rng = np.random.default_rng(3)
    kf = make_keyframe(rng)
    kf.confidence = kf.confidence[:-1]
    with pytest.raises(C.ConversionError, match="confidence shape"):
        C.keyframe_to_msg(kf)
    kf = make_keyframe(rng)
    kf.intrinsics = Intrinsics(30, 31, 15, 11, 64, 48)
    with pytest.raises(C.ConversionError, match="intrinsics are for 64x48"):
        C.keyframe_to_msg(kf)
    m = C.keyframe_to_msg(make_keyframe(rng))
    m.disparity = m.disparity[:-3]                 # truncated array on the wire
    with pytest.raises(C.ConversionError, match="disparity: 45 values, expected 48"):
        C.msg_to_keyframe(wire(m))


@pytest.mark.parametrize("with_disp", [True, False])
def test_pose_graph_update_round_trip(with_disp):
    rng = np.random.default_rng(4)
    n = 5
    ev = UpdateEvent(seq=12, reason="loop_closure", kf_ids=[0, 3, 4, 9, 10],
                     poses=np.stack([random_pose(rng) for _ in range(n)]),
                     disparities=rng.random((n, 6, 8), dtype=np.float32) if with_disp else None)
    m = wire(C.update_to_msg(ev, stamp=5.0))
    assert isinstance(m, PoseGraphUpdate)
    assert m.reason == PoseGraphUpdate.LOOP_CLOSURE and m.poses_only == (not with_disp)
    e2 = C.msg_to_update(m)
    assert (e2.seq, e2.reason, list(e2.kf_ids)) == (12, "loop_closure", [0, 3, 4, 9, 10])
    np.testing.assert_allclose(e2.poses, ev.poses, atol=1e-12)
    if with_disp:
        np.testing.assert_array_equal(e2.disparities, ev.disparities)
    else:
        assert e2.disparities is None
    for code, name in enumerate(UpdateEvent.REASONS):
        ev.reason = name
        assert C.update_to_msg(ev).reason == code
    assert (PoseGraphUpdate.LOCAL_BA, PoseGraphUpdate.GLOBAL_BA, PoseGraphUpdate.FINAL) == (0, 2, 3)


def test_pose_graph_update_errors():
    rng = np.random.default_rng(5)
    ev = UpdateEvent(1, "bundle", [1], random_pose(rng)[None])
    with pytest.raises(C.ConversionError, match="unknown update reason 'bundle'"):
        C.update_to_msg(ev)
    ev = UpdateEvent(1, "local_ba", [1, 2], random_pose(rng)[None])
    with pytest.raises(C.ConversionError, match="2 kf_ids but 1 poses"):
        C.update_to_msg(ev)
    ev = UpdateEvent(1, "local_ba", [1], random_pose(rng)[None], np.zeros((2, 3, 3), np.float32))
    with pytest.raises(C.ConversionError, match="N x h x w with N=1"):
        C.update_to_msg(ev)
    m = C.update_to_msg(UpdateEvent(1, "global_ba", [1], random_pose(rng)[None],
                                    np.zeros((1, 3, 3), np.float32)))
    m.reason = 9
    with pytest.raises(C.ConversionError, match="unknown reason code 9"):
        C.msg_to_update(m)


def test_proxy_depth_round_trip_and_errors():
    rng = np.random.default_rng(6)
    d = rng.random((12, 16), dtype=np.float32) * 4
    s = rng.integers(0, 4, (12, 16)).astype(np.uint8)
    T = random_pose(rng)
    pd = CoreProxyDepth(4, d, s, T, update_seq=9, is_update=True, timestamp=2.25, revision=7)
    m = wire(C.proxy_depth_to_msg(pd))
    assert isinstance(m, ProxyDepth) and (m.width, m.height) == (16, 12)
    assert ProxyDepth.SOURCE_MULTIVIEW == CoreProxyDepth.SOURCE_MULTIVIEW == 1
    assert ProxyDepth.SOURCE_BA == CoreProxyDepth.SOURCE_BA == 3 and (s == 3).any()
    p = C.msg_to_proxy_depth(m)
    assert (p.kf_id, p.update_seq, p.is_update, p.timestamp, p.revision) == (4, 9, True, 2.25, 7)
    np.testing.assert_array_equal(p.depth, d)
    np.testing.assert_array_equal(p.source, s)
    np.testing.assert_allclose(p.pose, T, atol=1e-12)
    m2 = wire(C.proxy_depth_to_msg(p))
    assert bytes(m2.source) == bytes(m.source) and m2.update_seq == 9
    with pytest.raises(C.ConversionError, match="source mask values"):
        C.proxy_depth_to_msg(replace(pd, source=s + 4))
    with pytest.raises(C.ConversionError, match="source mask shape"):
        C.proxy_depth_to_msg(replace(pd, source=s[:-1]))
    m.source = bytes(m.source)[:-2]
    with pytest.raises(C.ConversionError, match="source: 190 values, expected 192"):
        C.msg_to_proxy_depth(m)


def test_frame_ack():
    m = wire(C.frame_ack_msg(17, "tracker", stamp=3.5, kf_id=4))
    assert isinstance(m, FrameAck)
    assert (m.frame_index, m.consumer, m.is_keyframe, m.kf_id) == (17, "tracker", True, 4)
    m = C.frame_ack_msg(18, "tracker")
    assert not m.is_keyframe and m.kf_id == 0


# ------------------------------------------------------------------ QoS presets
def test_qos_presets():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

    from splat_slam_nodes import qos
    for name in ("keyframe", "pose_graph", "proxy_depth"):
        p = qos.qos(name)
        assert p.reliability == ReliabilityPolicy.RELIABLE
        assert p.durability == DurabilityPolicy.TRANSIENT_LOCAL
        assert p.history == HistoryPolicy.KEEP_LAST and p.depth >= 100
    assert qos.image_qos().reliability == ReliabilityPolicy.RELIABLE
    assert qos.image_qos().durability == DurabilityPolicy.VOLATILE
    assert qos.sensor_qos().reliability == ReliabilityPolicy.BEST_EFFORT
    assert qos.ack_qos().durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert qos.rendered_qos().depth == 1 and qos.status_qos().depth == 1
    assert qos.keyframe_qos() is not qos.keyframe_qos()          # fresh, mutable copies
    assert all(spec.why for spec in qos.PRESETS.values())
    with pytest.raises(KeyError, match="unknown QoS preset 'nope'"):
        qos.qos("nope")
