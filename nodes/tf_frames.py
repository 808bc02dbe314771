"""REP-105 TF frames of the tracker: ``map -> odom -> camera`` on /tf, ``camera ->
camera_optical`` on /tf_static, the same ``odom -> camera`` with its velocity as
``nav_msgs/Odometry``, and the keyframe poses as a ``visualization_msgs/MarkerArray``.

Frames (names from ``ros.map_frame``, ``ros.odom_frame``, ``ros.camera_frame``,
``ros.optical_frame``):

- ``map``: the SLAM world frame (the first camera's optical frame, as every pose, path and
  point cloud of the graph).
- ``map -> odom``: the correction that loop closure and global BA applied to the current
  camera pose (identity until the first correction), and in a loaded map (``--load-map``)
  each relocalisation: the first places odom at the camera where it was located, a later
  one (after a loss) moves the map under the odometry. It jumps; odometry does not.
- ``odom -> camera``: the tracking pose (frame-to-keyframe tracking + local BA), continuous.
  ``camera`` is the ROS body frame of the camera (x forward, y left, z up, REP-103).
- ``camera -> camera_optical`` (static): OpenCV axes (z forward, x right, y down), the frame
  images, CameraInfo and the tracker's 4x4 poses refer to.

The split itself (:class:`MapOdomSplit`) is pure math, tested without ROS.
"""
from __future__ import annotations

import threading
from typing import List, Optional, Sequence

import numpy as np
import torch

from splat_slam_ros.geometry import rotation_to_quat_np, se3_inverse, so3_log

# T_camera_optical: the optical frame's axes in the camera body frame (REP-103):
# optical x (right) = -y body, optical y (down) = -z body, optical z (forward) = +x body.
OPTICAL_IN_CAMERA = np.array([[0.0, 0.0, 1.0, 0.0],
                              [-1.0, 0.0, 0.0, 0.0],
                              [0.0, -1.0, 0.0, 0.0],
                              [0.0, 0.0, 0.0, 1.0]])
CAMERA_IN_OPTICAL = OPTICAL_IN_CAMERA.T.copy()     # a pure rotation: inverse = transpose


def inverse(T) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (numpy in, numpy out)."""
    return se3_inverse(torch.as_tensor(np.asarray(T, np.float64))).numpy()


def _rigid(T: np.ndarray) -> np.ndarray:
    """Project the rotation block back onto SO(3) (products of many corrections drift)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    out = np.array(T, np.float64, copy=True)
    out[:3, :3] = R
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


class MapOdomSplit:
    """Splits the tracker's map pose of the camera into ``map -> odom`` x ``odom -> optical``.

    ``T_map_optical = T_map_odom @ T_odom_optical`` always holds. Loop closure / global BA
    updates move the current map pose from ``before`` to ``after``; :meth:`correct` absorbs
    that jump into ``T_map_odom`` so that ``T_odom_optical`` stays continuous.
    """

    def __init__(self):
        self.map_odom = np.eye(4)
        self.corrections = 0

    def odom_pose(self, T_map_optical) -> np.ndarray:
        """T_odom_optical of a map pose under the current correction."""
        return inverse(self.map_odom) @ np.asarray(T_map_optical, np.float64)

    def correct(self, before, after) -> bool:
        """The current map pose moved ``before -> after`` (a correction, not odometry).
        Returns whether ``map -> odom`` changed."""
        before = np.asarray(before, np.float64)
        after = np.asarray(after, np.float64)
        if np.allclose(before, after, atol=1e-12):
            return False
        # T_odom_optical = T_map_odom^-1 @ before must equal T_map_odom'^-1 @ after
        self.map_odom = _rigid(after @ inverse(before) @ self.map_odom)
        self.corrections += 1
        return True

    def relocalise(self, T_map_optical, last_map_pose=None) -> None:
        """Located in a loaded map (relocalisation) at ``T_map_optical``: ``odom`` stays
        continuous, the jump goes into ``map -> odom``. The first time (nothing published
        yet) odom starts at the camera; after a loss the odometry holds its last pose."""
        if last_map_pose is None:
            self.map_odom = _rigid(np.asarray(T_map_optical, np.float64))
            self.corrections += 1
        else:
            self.correct(last_map_pose, T_map_optical)


def camera_body_pose(T_x_optical) -> np.ndarray:
    """Pose of the camera body frame from a pose of its optical frame (same parent)."""
    return np.asarray(T_x_optical, np.float64) @ CAMERA_IN_OPTICAL


def body_twist(T_prev, T_cur, dt: float):
    """(linear, angular) velocity, each (3,), of a body that moved from pose ``T_prev`` to
    ``T_cur`` (4x4, one parent frame) in ``dt`` seconds, in ``T_cur``'s axes (the twist of a
    nav_msgs/Odometry, given in its child frame)."""
    T_prev, T_cur = np.asarray(T_prev, np.float64), np.asarray(T_cur, np.float64)
    R = T_cur[:3, :3]
    linear = R.T @ (T_cur[:3, 3] - T_prev[:3, 3]) / dt
    dR = T_prev[:3, :3].T @ R                   # its axis is the same in both bodies' axes
    angular = so3_log(torch.as_tensor(dR)).numpy() / dt
    return linear, angular


# --------------------------------------------------------------------------- ROS messages
def transform_stamped(T, stamp: float, parent: str, child: str):
    """geometry_msgs/TransformStamped of ``child`` in ``parent`` (4x4 parent_T_child)."""
    from geometry_msgs.msg import TransformStamped

    from .convert import to_stamp
    T = np.asarray(T, np.float64)
    q = rotation_to_quat_np(T[:3, :3])                               # x, y, z, w
    m = TransformStamped()
    m.header.stamp = to_stamp(stamp)
    m.header.frame_id = parent
    m.child_frame_id = child
    tr, ro = m.transform.translation, m.transform.rotation
    tr.x, tr.y, tr.z = (float(v) for v in T[:3, 3])
    ro.x, ro.y, ro.z, ro.w = (float(v) for v in q)
    return m


def tf_qos():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def odometry_msg(T_odom_child, linear, angular, stamp: float, odom: str, child: str):
    """nav_msgs/Odometry: the pose of ``child`` in ``odom`` and its velocity in ``child``'s
    axes; the covariances are not estimated (zeros)."""
    from nav_msgs.msg import Odometry

    from .convert import pose_to_msg, to_stamp
    m = Odometry()
    m.header.stamp = to_stamp(stamp)
    m.header.frame_id = odom
    m.child_frame_id = child
    m.pose.pose = pose_to_msg(T_odom_child)
    tw = m.twist.twist
    tw.linear.x, tw.linear.y, tw.linear.z = (float(v) for v in linear)
    tw.angular.x, tw.angular.y, tw.angular.z = (float(v) for v in angular)
    return m


def tf_static_qos():
    """What tf2_ros's static broadcaster / listener use: latched, RELIABLE."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def keyframe_markers(poses: Sequence[np.ndarray], ids: Sequence[int], stamp: float,
                     frame_id: str, scale: float = 0.05):
    """visualization_msgs/MarkerArray: one arrow per keyframe (along the viewing direction)
    plus a line strip through the keyframe positions; starts with DELETEALL so keyframes
    dropped or renumbered since the last array disappear."""
    from geometry_msgs.msg import Point
    from visualization_msgs.msg import Marker, MarkerArray

    from .convert import pose_to_msg, to_stamp
    st = to_stamp(stamp)
    out: List = [Marker(action=Marker.DELETEALL)]
    out[0].header.frame_id = frame_id
    for kid, T in zip(ids, poses):
        m = Marker(ns="keyframes", id=int(kid), type=Marker.ARROW, action=Marker.ADD)
        m.header.stamp, m.header.frame_id = st, frame_id
        m.pose = pose_to_msg(camera_body_pose(T))      # an arrow points along its x axis
        m.scale.x, m.scale.y, m.scale.z = 2 * scale, 0.2 * scale, 0.2 * scale
        m.color.r, m.color.g, m.color.b, m.color.a = 0.1, 0.6, 1.0, 1.0
        out.append(m)
    if len(poses) >= 2:
        ln = Marker(ns="keyframe_path", id=0, type=Marker.LINE_STRIP, action=Marker.ADD)
        ln.header.stamp, ln.header.frame_id = st, frame_id
        ln.pose.orientation.w = 1.0
        ln.scale.x = 0.2 * scale
        ln.color.r, ln.color.g, ln.color.b, ln.color.a = 1.0, 0.5, 0.0, 1.0
        ln.points = [Point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])) for T in poses]
        out.append(ln)
    return MarkerArray(markers=out)


class TrackerFrames:
    """The tracker node's TF + marker publishers (hooked into nodes/tracker_node.py).

    ``on_pose`` after each tracked frame, ``around_update`` for pose-graph updates applied to
    the tracker, ``on_keyframes`` when the keyframe set or its poses changed.
    """

    def __init__(self, owner, tracker_reasons: Sequence[str]):
        from nav_msgs.msg import Odometry
        from tf2_msgs.msg import TFMessage
        from visualization_msgs.msg import MarkerArray

        from .node_common import TOPICS
        from .qos import pose_qos, status_qos
        n = owner.node
        r = owner.cfg.ros
        self.map, self.odom, self.camera, self.optical = (
            r.map_frame, r.odom_frame, r.camera_frame, r.optical_frame)
        self.TFMessage = TFMessage
        self.tracker_reasons = tuple(tracker_reasons)
        self.pub = n.create_publisher(TFMessage, "/tf", tf_qos())
        self.pub_static = n.create_publisher(TFMessage, "/tf_static", tf_static_qos())
        self.pub_markers = n.create_publisher(MarkerArray, TOPICS["keyframe_markers"],
                                              status_qos())
        self.pub_odom = n.create_publisher(Odometry, TOPICS["odometry"], pose_qos())
        self.last_odom = None                # (stamp, odom -> camera) of the newest Odometry
        # poses come from the worker (tracked frames) and the executor (skipped ones, at once)
        self._odom_lock = threading.Lock()
        self.split = MapOdomSplit()
        self.last_stamp: Optional[float] = None
        self.last_map_pose: Optional[np.ndarray] = None     # of the newest on_pose
        self.pub_static.publish(TFMessage(transforms=[transform_stamped(
            OPTICAL_IN_CAMERA, owner.now(), self.camera, self.optical)]))

    def on_pose(self, T_map_optical, stamp: float) -> None:
        """map -> odom and odom -> camera at a tracked frame's stamp; the odometry when the
        stamp is newer than the last one's (its velocity from that one's pose)."""
        T_odom_cam = camera_body_pose(self.split.odom_pose(T_map_optical))
        self.pub.publish(self.TFMessage(transforms=[
            transform_stamped(self.split.map_odom, stamp, self.map, self.odom),
            transform_stamped(T_odom_cam, stamp, self.odom, self.camera)]))
        with self._odom_lock:
            last = self.last_odom
            if last is None or stamp > last[0]:
                lin, ang = body_twist(last[1], T_odom_cam, stamp - last[0]) \
                    if last is not None else (np.zeros(3), np.zeros(3))
                self.pub_odom.publish(odometry_msg(T_odom_cam, lin, ang, stamp, self.odom,
                                                   self.camera))
                self.last_odom = (stamp, T_odom_cam)
        self.last_stamp = stamp
        self.last_map_pose = np.asarray(T_map_optical, np.float64).copy()

    def relocalised(self, T_map_optical) -> None:
        """Located in a loaded map: see :meth:`MapOdomSplit.relocalise` (published with the
        frame's pose by :meth:`on_pose`)."""
        self.split.relocalise(T_map_optical, self.last_map_pose)

    def around_update(self, tracker, ev, apply) -> None:
        """Run ``apply(ev)``; a loop closure / global BA / final update that moved the
        current camera pose becomes a new ``map -> odom`` (published at once, 1 us after the
        last frame's stamp, so that tf buffers keep both values)."""
        if tracker is None or ev.reason in self.tracker_reasons or not tracker.initialized:
            apply(ev)
            return
        before = tracker.last_pose.detach().cpu().numpy().copy()
        apply(ev)
        after = tracker.last_pose.detach().cpu().numpy()
        if self.split.correct(before, after) and self.last_stamp is not None:
            self.last_stamp += 1e-6
            self.pub.publish(self.TFMessage(transforms=[
                transform_stamped(self.split.map_odom, self.last_stamp, self.map, self.odom)]))

    def on_keyframes(self, tracker, stamp: float) -> None:
        if tracker is None:
            return
        ts, P = tracker.trajectory_keyframes()
        self.pub_markers.publish(keyframe_markers(list(P), tracker.keyframe_ids(), stamp,
                                                  self.map))


def render_camera_info(mapper, width: int, height: int, intrinsics, stamp: float,
                       frame_id: str):
    """sensor_msgs/CameraInfo of a map render of ``width`` x ``height`` (the intrinsics
    Mapper.render used: the given (fx, fy, cx, cy) or the mapper's, rescaled; no distortion,
    renders are ideal pinhole images)."""
    from splat_slam_ros.types import Intrinsics

    from .convert import intrinsics_to_camera_info
    if intrinsics is not None and any(abs(float(x)) > 0 for x in intrinsics):
        fx, fy, cx, cy = (float(x) for x in intrinsics)
        K = Intrinsics(fx, fy, cx, cy, int(width), int(height), "plumb_bob", [])
    else:
        K = mapper.K.scaled(width / mapper.W, height / mapper.H)
        K = Intrinsics(K.fx, K.fy, K.cx, K.cy, int(width), int(height), "plumb_bob", [])
    return intrinsics_to_camera_info(K, stamp, frame_id)
