"""REP-105 frame math (map -> odom -> camera -> camera_optical) without a running graph, the
TF / marker messages, and the wire identity of the tf2_msgs package built from msg_defs/."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from splat_slam_ros.geometry import se3_exp
from splat_slam_nodes import tf_frames as F

pytestmark = pytest.mark.ros


def _poses(n, seed=0):
    rng = np.random.default_rng(seed)
    xi = np.cumsum(rng.normal(0, 0.05, (n, 6)), 0)
    return se3_exp(torch.from_numpy(xi)).numpy()


def test_split_is_identity_without_corrections():
    s = F.MapOdomSplit()
    for T in _poses(5):
        np.testing.assert_allclose(s.odom_pose(T), T, atol=1e-12)
    assert s.corrections == 0 and np.allclose(s.map_odom, np.eye(4))
    assert not s.correct(np.eye(4), np.eye(4))


def test_correction_goes_to_map_odom_and_odometry_stays_continuous():
    P = _poses(12, seed=1)
    jump = se3_exp(torch.tensor([0.2, -0.1, 0.05, 0.03, -0.08, 0.1], dtype=torch.float64)).numpy()
    s = F.MapOdomSplit()
    odom = []
    for k, T in enumerate(P):
        if k >= 6:                      # a loop closure moved the map estimate from frame 6 on
            T = jump @ T
        if k == 6:
            before, after = P[5], jump @ P[5]
            odom_before = s.odom_pose(before)
            assert s.correct(before, after)
            # the current pose's odometry does not jump; map -> odom took the whole correction
            np.testing.assert_allclose(s.odom_pose(after), odom_before, atol=1e-9)
            np.testing.assert_allclose(s.map_odom, jump, atol=1e-9)
        o = s.odom_pose(T)
        np.testing.assert_allclose(s.map_odom @ o, T, atol=1e-9)     # map->odom->optical = map pose
        odom.append(o)
    # odometry after the correction equals the uncorrected tracking (continuous, no jump)
    for k in range(12):
        np.testing.assert_allclose(odom[k], P[k], atol=1e-9)
    # two more corrections compose; the rotation stays orthonormal
    s.correct(P[-1], jump @ P[-1])
    s.correct(P[-1], jump @ P[-1])
    R = s.map_odom[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert s.corrections == 3


def test_relocalisation_in_a_loaded_map_goes_to_map_odom():
    P = _poses(10, seed=2)
    s = F.MapOdomSplit()
    s.relocalise(P[0])                  # the first located frame: odom starts at the camera
    np.testing.assert_allclose(s.odom_pose(P[0]), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(s.map_odom @ s.odom_pose(P[3]), P[3], atol=1e-9)
    # lost after frame 4, relocalised at frame 8 (the map pose jumped): the odometry holds
    # frame 4's pose, map -> odom takes the jump, map -> odom -> optical is the map pose
    odom4 = s.odom_pose(P[4])
    s.relocalise(P[8], last_map_pose=P[4])
    np.testing.assert_allclose(s.odom_pose(P[8]), odom4, atol=1e-9)
    np.testing.assert_allclose(s.map_odom @ s.odom_pose(P[9]), P[9], atol=1e-9)
    assert s.corrections == 2


def test_optical_frame_convention():
    # the optical z axis (viewing direction) is the body x axis; optical y (down) is body -z
    R = F.OPTICAL_IN_CAMERA[:3, :3]
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0])
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, -1])
    assert np.isclose(np.linalg.det(R), 1.0)
    T = _poses(1, seed=3)[0]
    np.testing.assert_allclose(F.camera_body_pose(T) @ F.OPTICAL_IN_CAMERA, T, atol=1e-12)


def test_transform_and_marker_messages():
    from splat_slam_nodes.convert import msg_to_pose
    T = _poses(1, seed=4)[0]
    m = F.transform_stamped(F.OPTICAL_IN_CAMERA, 12.5, "camera", "camera_optical")
    q = m.transform.rotation
    # the standard ROS optical-frame quaternion (x, y, z, w) = (-0.5, 0.5, -0.5, 0.5)
    np.testing.assert_allclose(np.sign(q.w) * np.array([q.x, q.y, q.z, q.w]),
                               [-0.5, 0.5, -0.5, 0.5], atol=1e-9)
    assert m.header.stamp.sec == 12 and m.header.stamp.nanosec == 500_000_000
    m = F.transform_stamped(T, 1.0, "map", "odom")
    t, r = m.transform.translation, m.transform.rotation
    from geometry_msgs.msg import Pose
    p = Pose()
    p.position.x, p.position.y, p.position.z = t.x, t.y, t.z
    p.orientation = r
    np.testing.assert_allclose(msg_to_pose(p), T, atol=1e-9)
    P = _poses(4, seed=5)
    arr = F.keyframe_markers(list(P), [0, 1, 2, 5], 3.0, "map")
    from visualization_msgs.msg import Marker
    kinds = [mk.type for mk in arr.markers]
    assert arr.markers[0].action == Marker.DELETEALL
    assert kinds[1:5] == [Marker.ARROW] * 4 and kinds[5] == Marker.LINE_STRIP
    assert [mk.id for mk in arr.markers[1:5]] == [0, 1, 2, 5]
    # an arrow points along its x axis = the camera's viewing direction (optical z)
    Tm = msg_to_pose(arr.markers[2].pose)
    np.testing.assert_allclose(Tm[:3, 0], P[1][:3, 2], atol=1e-9)
    assert len(arr.markers[5].points) == 4 and np.isclose(arr.markers[5].points[3].x, P[3][0, 3])


def test_odometry_twist_is_the_motion_in_the_body_axes():
    """A body turning about its z axis at 0.5 rad/s while moving forward (its x) at 2 units/s:
    the twist in its own axes is (2, 0, 0) / (0, 0, 0.5), whatever its pose in odom."""
    from splat_slam_nodes.convert import msg_to_pose

    def at(t):                       # rotate about z by 0.5 t, move along the rotated x
        xi = torch.tensor([2.0 * t, 0.0, 0.0, 0.0, 0.0, 0.5 * t], dtype=torch.float64)
        return se3_exp(xi).numpy()
    start = _poses(1, seed=6)[0]
    lin, ang = F.body_twist(start @ at(1.0), start @ at(1.1), 0.1)
    np.testing.assert_allclose(lin, [2.0, 0, 0], atol=0.06)     # chord of the arc
    np.testing.assert_allclose(ang, [0, 0, 0.5], atol=1e-9)
    lin, ang = F.body_twist(start @ at(1.0), start @ at(1.001), 0.001)
    np.testing.assert_allclose(lin, [2.0, 0, 0], atol=1e-3)
    m = F.odometry_msg(start, lin, ang, 7.25, "odom", "camera")
    assert (m.header.frame_id, m.child_frame_id) == ("odom", "camera")
    assert m.header.stamp.sec == 7 and m.header.stamp.nanosec == 250_000_000
    np.testing.assert_allclose(msg_to_pose(m.pose.pose), start, atol=1e-9)
    assert np.isclose(m.twist.twist.linear.x, lin[0]) and np.isclose(m.twist.twist.angular.z,
                                                                     ang[2])
    assert not any(m.pose.covariance) and not any(m.twist.covariance)     # not estimated


# RIHS01 type hashes of the published ROS 2 Jazzy tf2_msgs (what `ros2 topic info -v /tf`
# shows on a stock installation): equal hashes = same names, fields and types on the wire.
JAZZY_HASHES = {
    "msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "msg/TF2Error": "RIHS01_db2485e7d6a0ec75bf087e058ee45df682acc3a621ca7780503d10aac141809a",
}


def test_tf2_msgs_is_the_standard_package():
    import sys
    from tf2_msgs.action import LookupTransform
    from tf2_msgs.msg import TF2Error, TFMessage
    from tf2_msgs.srv import FrameGraph
    share = Path(sys.prefix) / "share" / "tf2_msgs"           # msg_defs/build.sh installs here
    for name, want in JAZZY_HASHES.items():
        d = json.loads((share / f"{name}.json").read_text())
        hashes = {h["type_name"]: h["hash_string"] for h in d["type_hashes"]}
        assert hashes[f"tf2_msgs/{name}"] == want, name
    assert TFMessage.__module__.startswith("tf2_msgs.msg")
    assert TF2Error.TRANSFORM_ERROR == 6 and hasattr(FrameGraph.Response(), "frame_yaml")
    g = LookupTransform.Goal()
    assert {"target_frame", "source_frame", "fixed_frame", "advanced"} <= set(
        g.get_fields_and_field_types())
