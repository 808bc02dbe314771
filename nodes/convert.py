"""Fast conversions between numpy / project types and ROS 2 messages.

Speed: numpy arrays are never assigned to message sequence fields directly (that checks every
element: 37-92 ms for one 640x480 array); they go in as ``array.array`` filled from the raw
buffer (~0.2 ms) and come out with ``np.frombuffer``. The ``msg_to_*`` functions copy by
default; ``copy=False`` returns (writable) views into the message's buffers.

Conventions (splat_slam_ros.types): images H x W x C uint8 (RGB for colour), depth metres
float32, poses camera-to-world 4x4 float64, quaternions (x, y, z, w), stamps float seconds.
"""
from __future__ import annotations

import array
from typing import Optional, Sequence, Tuple

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, Quaternion
from sensor_msgs.msg import CameraInfo, Image

from splat_slam_ros.io.sensor_codec import ConversionError, decode_image, decode_rgb, encode_image
# public names of this module that live in the core codec (nodes import them from here)
from splat_slam_ros.io.sensor_codec import UnsupportedEncoding, camera_info_to_intrinsics  # noqa: F401
from splat_slam_ros.types import Intrinsics, KeyframeData, ProxyDepth, UpdateEvent


# ------------------------------------------------------------------ raw helpers
def _u8(a: np.ndarray) -> array.array:
    """Raw bytes of ``a`` (C order) as array.array('B') for a uint8[] field."""
    out = array.array("B")
    out.frombytes(memoryview(np.ascontiguousarray(a)).cast("B"))
    return out


def _f32(a: Optional[np.ndarray]) -> array.array:
    out = array.array("f")
    if a is not None and a.size:
        out.frombytes(memoryview(np.ascontiguousarray(a, dtype=np.float32)).cast("B"))
    return out


def _from(field, dtype, shape: Tuple[int, ...], what: str, copy: bool) -> np.ndarray:
    """np.frombuffer of a sequence field, checked against ``shape``."""
    a = np.frombuffer(field, dtype=dtype) if len(field) else np.zeros(0, dtype)
    n = int(np.prod(shape)) if shape else 0
    if a.size != n:
        raise ConversionError(f"{what}: {a.size} values, expected {n} for shape {tuple(shape)}")
    a = a.reshape(shape)
    return a.copy() if copy else a


# ------------------------------------------------------------------ time
def to_stamp(t: float) -> Time:
    """Float seconds -> builtin_interfaces/Time (rounded to the nanosecond)."""
    ns = int(round(float(t) * 1e9))
    if ns < 0:
        raise ConversionError(f"negative timestamp {t} cannot be a ROS stamp")
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def from_stamp(stamp: Time) -> float:
    """builtin_interfaces/Time -> float seconds."""
    return stamp.sec + stamp.nanosec * 1e-9


# ------------------------------------------------------------------ images
def image_to_msg(img: np.ndarray, encoding: Optional[str] = None, stamp: float = 0.0,
                 frame_id: str = "") -> Image:
    """numpy image -> sensor_msgs/Image (fields from ``sensor_codec.encode_image``: encoding
    defaults by shape/dtype; the array must already be in the channel order it names)."""
    f = encode_image(img, encoding)
    m = Image()
    m.header.stamp = to_stamp(stamp)
    m.header.frame_id = frame_id
    m.height, m.width, m.encoding, m.step = f.height, f.width, f.encoding, f.step
    m.is_bigendian = 0
    m.data = _u8(f.data)
    return m


def msg_to_image(msg: Image, copy: bool = True) -> np.ndarray:
    """sensor_msgs/Image -> numpy in the message's own channel order and dtype
    (``sensor_codec.decode_image``: row padding and big-endian data handled)."""
    return decode_image(msg, copy)


def msg_to_rgb(msg) -> np.ndarray:
    """sensor_msgs/Image of a colour/mono camera encoding, or a CompressedImage -> H x W x 3
    uint8 RGB (a copy)."""
    return decode_rgb(msg)


# ------------------------------------------------------------------ camera info
def intrinsics_to_camera_info(intr: Intrinsics, stamp: float = 0.0,
                              frame_id: str = "") -> CameraInfo:
    """Intrinsics -> sensor_msgs/CameraInfo (K, P with zero baseline, R = identity, D)."""
    m = CameraInfo()
    m.header.stamp = to_stamp(stamp)
    m.header.frame_id = frame_id
    m.width, m.height = int(intr.width), int(intr.height)
    m.distortion_model = intr.distortion_model or ""
    m.d = [float(x) for x in intr.distortion]
    m.k = [float(intr.fx), 0.0, float(intr.cx), 0.0, float(intr.fy), float(intr.cy), 0.0, 0.0, 1.0]
    m.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    m.p = [float(intr.fx), 0.0, float(intr.cx), 0.0,
           0.0, float(intr.fy), float(intr.cy), 0.0, 0.0, 0.0, 1.0, 0.0]
    return m


# ------------------------------------------------------------------ poses
def _poses_to_tq(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim == 2:                 # one pose (a frame's, at the camera's rate): plain floats
        from splat_slam_ros.geometry import rotation_to_quat_np
        return np.concatenate([T[:3, 3], rotation_to_quat_np(T[:3, :3])])
    from splat_slam_ros.geometry import pose_to_tq   # lazy: torch only when poses are used
    return pose_to_tq(T).numpy()


def _tq_to_poses(tq: np.ndarray) -> np.ndarray:
    from splat_slam_ros.geometry import pose_from_tq
    return pose_from_tq(np.asarray(tq, dtype=np.float64)).numpy()


def _tq_msg(tq) -> Pose:
    return Pose(position=Point(x=float(tq[0]), y=float(tq[1]), z=float(tq[2])),
                orientation=Quaternion(x=float(tq[3]), y=float(tq[4]), z=float(tq[5]),
                                       w=float(tq[6])))


def _msg_tq(p: Pose) -> Tuple[float, ...]:
    o, q = p.position, p.orientation
    return (o.x, o.y, o.z, q.x, q.y, q.z, q.w)


def _check_pose(T: np.ndarray, what: str = "pose") -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ConversionError(f"{what} must be 4x4 (camera-to-world), got shape {T.shape}")
    if not np.isfinite(T).all():
        raise ConversionError(f"{what} has non-finite values")
    return T


def pose_to_msg(T: np.ndarray) -> Pose:
    """4x4 camera-to-world matrix -> geometry_msgs/Pose (quaternion with w >= 0)."""
    return _tq_msg(_poses_to_tq(_check_pose(T)))


def msg_to_pose(msg: Pose) -> np.ndarray:
    """geometry_msgs/Pose -> 4x4 float64 (quaternion normalised)."""
    return _tq_to_poses(np.array(_msg_tq(msg)))


def poses_to_msgs(Ts: np.ndarray) -> list:
    """N x 4 x 4 -> list of geometry_msgs/Pose (one batched conversion)."""
    Ts = _check_pose(Ts, "poses")
    if Ts.ndim != 3:
        raise ConversionError(f"poses must be N x 4 x 4, got shape {Ts.shape}")
    if len(Ts) == 0:
        return []
    return [_tq_msg(tq) for tq in _poses_to_tq(Ts)]


def msgs_to_poses(msgs: Sequence[Pose]) -> np.ndarray:
    """list of geometry_msgs/Pose -> N x 4 x 4 float64."""
    if len(msgs) == 0:
        return np.zeros((0, 4, 4))
    return _tq_to_poses(np.array([_msg_tq(p) for p in msgs]))


# ------------------------------------------------------------------ keyframes
def keyframe_to_msg(kf: KeyframeData, frame_id: str = "map"):
    """KeyframeData -> splat_slam_msgs/Keyframe (image published as rgb8)."""
    from splat_slam_msgs.msg import Keyframe
    img = np.asarray(kf.image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ConversionError(f"keyframe image must be H x W x 3 uint8 RGB, got {img.shape} {img.dtype}")
    disp = np.asarray(kf.disparity, dtype=np.float32)
    conf = np.asarray(kf.confidence, dtype=np.float32)
    if disp.ndim != 2:
        raise ConversionError(f"keyframe disparity must be h x w, got shape {disp.shape}")
    if conf.shape != disp.shape:
        raise ConversionError(f"keyframe confidence shape {conf.shape} != disparity shape {disp.shape}")
    intr = kf.intrinsics
    if (int(intr.width), int(intr.height)) != (img.shape[1], img.shape[0]):
        raise ConversionError(f"intrinsics are for {intr.width}x{intr.height} but the image is "
                              f"{img.shape[1]}x{img.shape[0]}")
    m = Keyframe()
    m.header.stamp = to_stamp(kf.timestamp)
    m.header.frame_id = frame_id
    m.kf_id = int(kf.kf_id)
    m.frame_index = int(kf.frame_index)
    m.pose = pose_to_msg(kf.pose)
    m.intrinsics = np.array([intr.fx, intr.fy, intr.cx, intr.cy], dtype=np.float64)
    m.width, m.height = int(intr.width), int(intr.height)
    m.distortion_model = intr.distortion_model if intr.has_distortion else ""
    m.distortion = [float(x) for x in intr.distortion] if intr.has_distortion else []
    m.image = image_to_msg(img, "rgb8", kf.timestamp, frame_id)
    m.disparity = _f32(disp)
    m.confidence = _f32(conf)
    m.disp_height, m.disp_width = int(disp.shape[0]), int(disp.shape[1])
    m.batch_id = int(kf.kf_id if kf.batch_id < 0 else kf.batch_id)
    m.batch_size = max(1, int(kf.batch_size))
    if kf.mono_depth is not None:
        md = np.asarray(kf.mono_depth, dtype=np.float32)
        if md.ndim != 2:
            raise ConversionError(f"keyframe mono_depth must be H x W, got shape {md.shape}")
        m.has_mono_depth = True
        m.mono_depth = _f32(md)
        m.mono_height, m.mono_width = int(md.shape[0]), int(md.shape[1])
    return m


def msg_to_keyframe(msg, copy: bool = True) -> KeyframeData:
    """splat_slam_msgs/Keyframe -> KeyframeData (image as H x W x 3 RGB)."""
    fx, fy, cx, cy = (float(x) for x in msg.intrinsics)
    dist = [float(x) for x in msg.distortion]
    intr = Intrinsics(fx, fy, cx, cy, int(msg.width), int(msg.height),
                      msg.distortion_model or "plumb_bob", dist)
    img = msg_to_rgb(msg.image) if msg.image.encoding != "rgb8" else msg_to_image(msg.image, copy)
    if (img.shape[1], img.shape[0]) != (intr.width, intr.height):
        raise ConversionError(f"keyframe {msg.kf_id}: image is {img.shape[1]}x{img.shape[0]} "
                              f"but width/height say {intr.width}x{intr.height}")
    shp = (int(msg.disp_height), int(msg.disp_width))
    disp = _from(msg.disparity, np.float32, shp, f"keyframe {msg.kf_id} disparity", copy)
    conf = _from(msg.confidence, np.float32, shp, f"keyframe {msg.kf_id} confidence", copy)
    mono = None
    if msg.has_mono_depth:
        mono = _from(msg.mono_depth, np.float32, (int(msg.mono_height), int(msg.mono_width)),
                     f"keyframe {msg.kf_id} mono_depth", copy)
    return KeyframeData(kf_id=int(msg.kf_id), frame_index=int(msg.frame_index),
                        timestamp=from_stamp(msg.header.stamp), pose=msg_to_pose(msg.pose),
                        image=img, intrinsics=intr, disparity=disp, confidence=conf,
                        mono_depth=mono, batch_id=int(msg.batch_id),
                        batch_size=max(1, int(msg.batch_size)))


# ------------------------------------------------------------------ pose-graph updates
def update_to_msg(ev: UpdateEvent, stamp: float = 0.0, frame_id: str = "map"):
    """UpdateEvent -> splat_slam_msgs/PoseGraphUpdate (poses_only when disparities is None)."""
    from splat_slam_msgs.msg import PoseGraphUpdate
    if ev.reason not in UpdateEvent.REASONS:
        raise ConversionError(f"unknown update reason {ev.reason!r}; expected one of "
                              f"{', '.join(UpdateEvent.REASONS)}")
    ids = [int(i) for i in ev.kf_ids]
    poses = _check_pose(ev.poses, "update poses").reshape(-1, 4, 4)
    if len(poses) != len(ids):
        raise ConversionError(f"update has {len(ids)} kf_ids but {len(poses)} poses")
    m = PoseGraphUpdate()
    m.header.stamp = to_stamp(stamp)
    m.header.frame_id = frame_id
    m.seq = int(ev.seq)
    m.reason = UpdateEvent.REASONS.index(ev.reason)
    m.kf_ids = array.array("I", ids)
    m.poses = poses_to_msgs(poses)
    if ev.disparities is None:
        m.poses_only = True
    else:
        d = np.asarray(ev.disparities, dtype=np.float32)
        if d.ndim != 3 or d.shape[0] != len(ids):
            raise ConversionError(f"update disparities must be N x h x w with N={len(ids)}, "
                                  f"got shape {d.shape}")
        m.poses_only = False
        m.disparities = _f32(d)
        m.disp_height, m.disp_width = int(d.shape[1]), int(d.shape[2])
    return m


def msg_to_update(msg, copy: bool = True) -> UpdateEvent:
    """splat_slam_msgs/PoseGraphUpdate -> UpdateEvent."""
    if msg.reason >= len(UpdateEvent.REASONS):
        raise ConversionError(f"PoseGraphUpdate {msg.seq}: unknown reason code {msg.reason}")
    ids = [int(i) for i in msg.kf_ids]
    if len(msg.poses) != len(ids):
        raise ConversionError(f"PoseGraphUpdate {msg.seq}: {len(ids)} kf_ids but {len(msg.poses)} poses")
    disp = None
    if not msg.poses_only:
        disp = _from(msg.disparities, np.float32,
                     (len(ids), int(msg.disp_height), int(msg.disp_width)),
                     f"PoseGraphUpdate {msg.seq} disparities", copy)
    return UpdateEvent(seq=int(msg.seq), reason=UpdateEvent.REASONS[msg.reason], kf_ids=ids,
                       poses=msgs_to_poses(msg.poses), disparities=disp)


# ------------------------------------------------------------------ lockstep ack
def frame_ack_msg(frame_index: int, consumer: str, stamp: float = 0.0,
                  kf_id: Optional[int] = None):
    """splat_slam_msgs/FrameAck for one consumed frame (``kf_id`` given = it became a keyframe)."""
    from splat_slam_msgs.msg import FrameAck
    m = FrameAck()
    m.header.stamp = to_stamp(stamp)
    m.frame_index = int(frame_index)
    m.consumer = str(consumer)
    m.is_keyframe = kf_id is not None
    m.kf_id = int(kf_id) if kf_id is not None else 0
    return m


# ------------------------------------------------------------------ proxy depth
def proxy_depth_to_msg(pd: ProxyDepth, frame_id: str = "map"):
    """ProxyDepth -> splat_slam_msgs/ProxyDepth (``source`` is cast to uint8)."""
    from splat_slam_msgs.msg import ProxyDepth as ProxyDepthMsg
    d = np.asarray(pd.depth, dtype=np.float32)
    s = np.asarray(pd.source)
    if d.ndim != 2:
        raise ConversionError(f"proxy depth must be H x W, got shape {d.shape}")
    if s.shape != d.shape:
        raise ConversionError(f"proxy depth source mask shape {s.shape} != depth shape {d.shape}")
    if s.size and (s.min() < 0 or s.max() > ProxyDepth.SOURCE_BA):
        raise ConversionError("proxy depth source mask values must be 0 (empty), 1 (multi-view), "
                              "2 (mono) or 3 (BA depth in a hole)")
    m = ProxyDepthMsg()
    m.header.stamp = to_stamp(pd.timestamp)
    m.header.frame_id = frame_id
    m.kf_id = int(pd.kf_id)
    m.depth = _f32(d)
    m.height, m.width = int(d.shape[0]), int(d.shape[1])
    m.source = _u8(s.astype(np.uint8, copy=False))
    m.pose = pose_to_msg(pd.pose)
    m.update_seq = int(pd.update_seq)
    m.is_update = bool(pd.is_update)
    m.revision = int(pd.revision)
    return m


def msg_to_proxy_depth(msg, copy: bool = True) -> ProxyDepth:
    """splat_slam_msgs/ProxyDepth -> ProxyDepth."""
    shp = (int(msg.height), int(msg.width))
    return ProxyDepth(
        kf_id=int(msg.kf_id),
        depth=_from(msg.depth, np.float32, shp, f"proxy depth {msg.kf_id}", copy),
        source=_from(msg.source, np.uint8, shp, f"proxy depth {msg.kf_id} source", copy),
        pose=msg_to_pose(msg.pose), update_seq=int(msg.update_seq),
        is_update=bool(msg.is_update), timestamp=from_stamp(msg.header.stamp),
        revision=int(msg.revision))
