import numpy as np
import pytest
import torch

from splat_slam_ros import geometry as g


def rand_quat(n, gen):
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[:, 3:] < 0, -q, q)


def test_se3_exp_log_roundtrip_and_inverse():
    gen = torch.Generator().manual_seed(0)
    xi = torch.randn(50, 6, generator=gen, dtype=torch.float64)
    xi[:, 3:] *= 0.9  # rotation angles below pi
    T = g.se3_exp(xi)
    assert torch.allclose(g.se3_log(T), xi, atol=1e-10)
    eye = torch.eye(4, dtype=torch.float64)
    assert torch.allclose(g.se3_inverse(T) @ T, eye.expand_as(T), atol=1e-12)
    # rotation block orthonormal with det 1
    R = T[:, :3, :3]
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(50, dtype=torch.float64))


def test_small_angle_and_near_pi():
    tiny = torch.tensor([[0.1, -0.2, 0.3, 1e-9, -2e-9, 3e-9]], dtype=torch.float64)
    assert torch.allclose(g.se3_log(g.se3_exp(tiny)), tiny, atol=1e-12)
    w = torch.tensor([[0.0, 0.0, np.pi - 1e-6]], dtype=torch.float64)
    R = g.so3_exp(w)
    assert torch.allclose(g.so3_exp(g.so3_log(R)), R, atol=1e-6)


def test_exp_matches_matrix_exponential():
    gen = torch.Generator().manual_seed(1)
    xi = torch.randn(6, generator=gen, dtype=torch.float64)
    A = torch.zeros(4, 4, dtype=torch.float64)
    A[:3, :3] = g.hat(xi[3:])
    A[:3, 3] = xi[:3]
    assert torch.allclose(g.se3_exp(xi), torch.linalg.matrix_exp(A), atol=1e-12)


def test_quaternion_roundtrip_and_product():
    gen = torch.Generator().manual_seed(2)
    q = rand_quat(100, gen)
    assert torch.allclose(g.matrix_to_quat(g.quat_to_matrix(q)), q, atol=1e-12)
    a, b = rand_quat(10, gen), rand_quat(10, gen)
    Rab = g.quat_to_matrix(g.quat_multiply(a, b))
    assert torch.allclose(Rab, g.quat_to_matrix(a) @ g.quat_to_matrix(b), atol=1e-12)
    # scipy agrees on the (x, y, z, w) convention
    from scipy.spatial.transform import Rotation
    assert np.allclose(Rotation.from_quat(q.numpy()).as_matrix(), g.quat_to_matrix(q).numpy())


def test_pose_tq_roundtrip():
    gen = torch.Generator().manual_seed(3)
    tq = torch.cat([torch.randn(7, 3, generator=gen, dtype=torch.float64), rand_quat(7, gen)], 1)
    assert torch.allclose(g.pose_to_tq(g.pose_from_tq(tq)), tq, atol=1e-12)
    assert torch.allclose(g.pose_from_tq(tq.numpy()), g.pose_from_tq(tq))


def test_project_unproject():
    intr = torch.tensor([500.0, 480.0, 320.0, 240.0], dtype=torch.float64)
    depth = torch.rand(6, 8, dtype=torch.float64) + 0.5
    X = g.depth_to_points(depth, intr)
    uv = g.project(X, intr)
    assert torch.allclose(uv, g.pixel_grid(6, 8, dtype=torch.float64), atol=1e-10)
    assert torch.allclose(X[..., 2], depth)


def test_transform_points_and_sim3():
    gen = torch.Generator().manual_seed(4)
    T = g.se3_exp(torch.randn(6, generator=gen, dtype=torch.float64))
    X = torch.randn(5, 3, generator=gen, dtype=torch.float64)
    Xh = torch.cat([X, torch.ones(5, 1, dtype=torch.float64)], 1)
    assert torch.allclose(g.transform_points(T, X), (Xh @ T.T)[:, :3])
    R = g.so3_exp(torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
    t = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    P = g.apply_sim3_to_poses(2.0, R, t, T[None])[0]
    assert torch.allclose(P[:3, 3], 2.0 * R @ T[:3, 3] + t)
    assert torch.allclose(P[:3, :3], R @ T[:3, :3])
    S = g.sim3_matrix(2.0, R, t)
    assert torch.allclose(S[:3, :3], 2.0 * R)


def test_slerp_and_pose_interpolation():
    gen = torch.Generator().manual_seed(5)
    T0 = g.se3_exp(torch.randn(6, generator=gen, dtype=torch.float64) * 0.3)
    xi = torch.randn(6, generator=gen, dtype=torch.float64) * 0.3
    T1 = g.se3_exp(xi) @ T0
    for a in (0.0, 0.25, 1.0):
        Ta = g.interpolate_pose(T0, T1, a)
        # rotation: geodesic fraction a of the relative rotation (right-composed)
        Rexp = T0[:3, :3] @ g.so3_exp(a * g.so3_log(T0[:3, :3].T @ T1[:3, :3]))
        assert torch.allclose(Ta[:3, :3], Rexp, atol=1e-10)
        assert torch.allclose(Ta[:3, 3], (1 - a) * T0[:3, 3] + a * T1[:3, 3], atol=1e-12)
    q0 = g.matrix_to_quat(T0[:3, :3])
    assert torch.allclose(g.quat_slerp(q0, -q0, torch.tensor(0.5, dtype=torch.float64)).abs(), q0.abs())


def test_one_rotation_to_quaternion_in_plain_floats_matches_the_tensor_version():
    """rotation_to_quat_np (poses published per frame) = matrix_to_quat, including the
    branches near 180 degrees about each axis and the w >= 0 convention."""
    from splat_slam_ros.geometry import matrix_to_quat, rotation_to_quat_np, so3_exp
    rng = np.random.default_rng(3)
    ws = [rng.normal(size=3) * s for s in (1e-9, 0.1, 1.0, 3.0) for _ in range(25)]
    ws += [np.array(a) * (np.pi - 1e-4) for a in ((1, 0, 0), (0, 1, 0), (0, 0, 1))]
    for w in ws:
        R = so3_exp(torch.as_tensor(w, dtype=torch.float64))
        ref = matrix_to_quat(R).numpy()
        got = rotation_to_quat_np(R.numpy())
        assert np.allclose(got, ref, atol=1e-12, rtol=0), (w, got, ref)
        assert got[3] >= 0 and abs(np.linalg.norm(got) - 1) < 1e-12
