"""Deterministic test payloads shared by the DDS test's publisher and subscriber scripts."""
import numpy as np

from splat_slam_ros.types import Intrinsics, KeyframeData, ProxyDepth, UpdateEvent

H, W = 480, 640          # image / mono depth / proxy depth resolution
h, w = 60, 80            # BA resolution


def _pose(rng):
    from scipy.spatial.transform import Rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    return T


def keyframe(i: int) -> KeyframeData:
    rng = np.random.default_rng(1000 + i)
    return KeyframeData(kf_id=i, frame_index=3 * i, timestamp=100.0 + i / 30,
                        pose=_pose(rng), image=rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                        intrinsics=Intrinsics(500.0, 501.0, 319.5, 239.5, W, H),
                        disparity=rng.random((h, w), dtype=np.float32),
                        confidence=rng.random((h, w), dtype=np.float32),
                        mono_depth=rng.random((H, W), dtype=np.float32))


def update(i: int) -> UpdateEvent:
    rng = np.random.default_rng(2000 + i)
    n = i + 2
    return UpdateEvent(seq=i + 1, reason=UpdateEvent.REASONS[i % 4], kf_ids=list(range(n)),
                       poses=np.stack([_pose(rng) for _ in range(n)]),
                       disparities=rng.random((n, h, w), dtype=np.float32) if i % 2 == 0 else None)


def proxy(i: int) -> ProxyDepth:
    rng = np.random.default_rng(3000 + i)
    return ProxyDepth(kf_id=i, depth=rng.random((H, W), dtype=np.float32) * 5,
                      source=rng.integers(0, 3, (H, W)).astype(np.uint8), pose=_pose(rng),
                      update_seq=i, is_update=i > 0, timestamp=100.0 + i / 30, revision=i % 3)


def image(i: int) -> np.ndarray:
    return np.random.default_rng(4000 + i).integers(0, 256, (H, W, 3), dtype=np.uint8)


def build(topic_kind: str, i: int):
    """The message number ``i`` of one kind."""
    from splat_slam_nodes import convert as C
    if topic_kind == "keyframe":
        return C.keyframe_to_msg(keyframe(i))
    if topic_kind == "pose_graph":
        return C.update_to_msg(update(i), stamp=50.0 + i)
    if topic_kind == "proxy_depth":
        return C.proxy_depth_to_msg(proxy(i))
    if topic_kind == "image":
        return C.image_to_msg(image(i), "rgb8", stamp=100.0 + i / 30, frame_id=f"cam{i}")
    raise KeyError(topic_kind)


def index_of(topic_kind: str, msg) -> int:
    if topic_kind == "keyframe":
        return int(msg.kf_id)
    if topic_kind == "pose_graph":
        return int(msg.seq) - 1
    if topic_kind == "proxy_depth":
        return int(msg.kf_id)
    return int(msg.header.frame_id[3:])


def contents_equal(topic_kind: str, msg, i: int) -> bool:
    """Decode ``msg`` with splat_slam_nodes.convert and compare with the expected payload."""
    from splat_slam_nodes import convert as C
    if topic_kind == "keyframe":
        a, b = C.msg_to_keyframe(msg), keyframe(i)
        return (a.kf_id == b.kf_id and a.frame_index == b.frame_index
                and abs(a.timestamp - b.timestamp) < 1e-6 and np.allclose(a.pose, b.pose, atol=1e-12)
                and np.array_equal(a.image, b.image) and np.array_equal(a.disparity, b.disparity)
                and np.array_equal(a.confidence, b.confidence)
                and np.array_equal(a.mono_depth, b.mono_depth) and a.intrinsics == b.intrinsics)
    if topic_kind == "pose_graph":
        a, b = C.msg_to_update(msg), update(i)
        same_d = (a.disparities is None and b.disparities is None) or (
            a.disparities is not None and b.disparities is not None
            and np.array_equal(a.disparities, b.disparities))
        return (a.seq == b.seq and a.reason == b.reason and list(a.kf_ids) == list(b.kf_ids)
                and np.allclose(a.poses, b.poses, atol=1e-12) and same_d)
    if topic_kind == "proxy_depth":
        a, b = C.msg_to_proxy_depth(msg), proxy(i)
        return (a.kf_id == b.kf_id and np.array_equal(a.depth, b.depth)
                and np.array_equal(a.source, b.source) and np.allclose(a.pose, b.pose, atol=1e-12)
                and (a.update_seq, a.is_update, a.revision) == (b.update_seq, b.is_update,
                                                                b.revision))
    if topic_kind == "image":
        return msg.encoding == "rgb8" and np.array_equal(C.msg_to_image(msg), image(i))
    raise KeyError(topic_kind)


def digest(msg) -> str:
    """SHA-256 over a message's field values (not its CDR bytes: serialising the same
    message twice can differ in the uninitialised alignment padding)."""
    import array
    import hashlib
    h = hashlib.sha256()

    def feed(v):
        if hasattr(v, "get_fields_and_field_types"):
            for name in v.get_fields_and_field_types():
                h.update(name.encode())
                feed(getattr(v, name))
        elif isinstance(v, (array.array, np.ndarray)):
            h.update(str(len(v)).encode())
            h.update(v.tobytes())
        elif isinstance(v, (bytes, bytearray)):
            h.update(bytes(v))
        elif isinstance(v, (list, tuple)):
            h.update(str(len(v)).encode())
            for x in v:
                feed(x)
        else:
            h.update(repr(v).encode())
    feed(msg)
    return h.hexdigest()
