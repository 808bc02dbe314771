"""Geometry in one place: SO3/SE3/Sim3 in torch, quaternions, pinhole projection.

Conventions: poses are camera-to-world 4x4 matrices ``T_wc`` (``omega`` in the
paper); quaternions are ``(qx, qy, qz, qw)`` (TUM order, Hamilton, unit);
se(3) tangent vectors are ``(tx, ty, tz, rx, ry, rz)`` (translation first),
applied on the left: ``T <- exp(xi) @ T``. All functions accept batched inputs
(leading dimensions) and work for any dtype/device.
"""
from __future__ import annotations

import math

import numpy as np
import torch

_EPS = 1e-8


# --------------------------------------------------------------------- SO(3)
def hat(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) skew-symmetric matrix."""
    z = torch.zeros_like(w[..., 0])
    return torch.stack([
        torch.stack([z, -w[..., 2], w[..., 1]], -1),
        torch.stack([w[..., 2], z, -w[..., 0]], -1),
        torch.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: (..., 3) axis-angle -> (..., 3, 3) rotation."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    theta = theta2.clamp_min(_EPS ** 2).sqrt()
    small = theta2 < 1e-10
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(_EPS))
    W = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(W.shape)
    return eye + a * W + b * (W @ W)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation -> (..., 3) axis-angle (stable near 0 and pi)."""
    return quat_to_axis_angle(matrix_to_quat(R))


# --------------------------------------------------------------- quaternions
def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) (x, y, z, w) -> (..., 3, 3); normalises the input."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(_EPS)
    x, y, z, w = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        torch.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        torch.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)],
        -2)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 4) (x, y, z, w) with w >= 0 (Shepperd's method)."""
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cand = torch.stack([
        torch.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                     m[..., 1, 0] - m[..., 0, 1], 1 + tr], -1),
        torch.stack([1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0],
                     m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] - m[..., 1, 2]], -1),
        torch.stack([m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                     m[..., 1, 2] + m[..., 2, 1], m[..., 0, 2] - m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                     1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2], m[..., 1, 0] - m[..., 0, 1]],
                    -1)], -2)
    diag = torch.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    idx = diag.argmax(-1)
    q = torch.gather(cand, -2, idx[..., None, None].expand(*idx.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(_EPS)
    return torch.where(q[..., 3:4] < 0, -q, q)


def rotation_to_quat_np(R) -> np.ndarray:
    """(3, 3) -> (4,) (x, y, z, w) with w >= 0: :func:`matrix_to_quat` (same candidates,
    same choice) for ONE rotation in plain floats, for poses published at the camera's rate
    (the tensor version's ~40 small ops cost far more than the arithmetic)."""
    m = np.asarray(R, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    cand = ((m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], 1 + tr),
            (1 + m[0, 0] - m[1, 1] - m[2, 2], m[0, 1] + m[1, 0], m[0, 2] + m[2, 0],
             m[2, 1] - m[1, 2]),
            (m[0, 1] + m[1, 0], 1 - m[0, 0] + m[1, 1] - m[2, 2], m[1, 2] + m[2, 1],
             m[0, 2] - m[2, 0]),
            (m[0, 2] + m[2, 0], m[1, 2] + m[2, 1], 1 - m[0, 0] - m[1, 1] + m[2, 2],
             m[1, 0] - m[0, 1]))
    q = np.array(cand[int(np.argmax((tr, m[0, 0], m[1, 1], m[2, 2])))])
    q /= max(float(np.sqrt(q @ q)), _EPS)
    return -q if q[3] < 0 else q


def quat_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    q = torch.where(q[..., 3:4] < 0, -q, q)
    v = q[..., :3]
    s = v.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(s, q[..., 3:4])
    scale = torch.where(s < 1e-8, 2.0 / q[..., 3:4].clamp_min(_EPS), angle / s.clamp_min(1e-12))
    return v * scale


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of (x, y, z, w) quaternions."""
    ax, ay, az, aw = a.unbind(-1)
    bx, by, bz, bw = b.unbind(-1)
    return torch.stack([aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw,
                        aw * bw - ax * bx - ay * by - az * bz], -1)


# --------------------------------------------------------------------- SE(3)
def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """(..., 6) (t, w) -> (..., 4, 4) with the full SE(3) exponential (V matrix)."""
    v, w = xi[..., :3], xi[..., 3:]
    R = so3_exp(w)
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    theta = theta2.clamp_min(_EPS ** 2).sqrt()
    small = theta2 < 1e-10
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(_EPS))
    c = torch.where(small, 1.0 / 6 - theta2 / 120,
                    (theta - torch.sin(theta)) / (theta2 * theta).clamp_min(_EPS))
    W = hat(w)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(W.shape)
    V = eye + b * W + c * (W @ W)
    T = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype, device=xi.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = (V @ v[..., None])[..., 0]
    T[..., 3, 3] = 1
    return T


def se3_exp_one(xi: torch.Tensor) -> torch.Tensor:
    """(6,) (t, w) -> 4x4: the same map as :func:`se3_exp` (Rodrigues + V matrix) for ONE
    twist, evaluated on its six numbers in Python: ~50 us instead of ~40 tensor ops, for
    Gauss-Newton loops that take one step at a time."""
    t0, t1, t2, w0, w1, w2 = (float(v) for v in xi.tolist())
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-10:
        a, b, c = 1.0 - th2 / 6, 0.5 - th2 / 24, 1.0 / 6 - th2 / 120
    else:
        th = math.sqrt(th2)
        a, b, c = math.sin(th) / th, (1 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    W = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    W2 = [[sum(W[i][k] * W[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
    R = [[float(i == j) + a * W[i][j] + b * W2[i][j] for j in range(3)] for i in range(3)]
    V = [[float(i == j) + b * W[i][j] + c * W2[i][j] for j in range(3)] for i in range(3)]
    rows = [R[i] + [V[i][0] * t0 + V[i][1] * t1 + V[i][2] * t2] for i in range(3)]
    return torch.tensor(rows + [[0.0, 0.0, 0.0, 1.0]], dtype=xi.dtype, device=xi.device)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) -> (..., 6) (t, w), inverse of :func:`se3_exp`."""
    w = so3_log(T[..., :3, :3])
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    theta = theta2.clamp_min(_EPS ** 2).sqrt()
    small = theta2 < 1e-10
    # V^-1 = I - W/2 + (1/theta^2)(1 - (theta sin)/(2(1-cos))) W^2
    coef = torch.where(small, 1.0 / 12 + theta2 / 720,
                       (1 - theta * torch.sin(theta) / (2 * (1 - torch.cos(theta))).clamp_min(_EPS))
                       / theta2.clamp_min(_EPS))
    W = hat(w)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand(W.shape)
    Vinv = eye - 0.5 * W + coef * (W @ W)
    v = (Vinv @ T[..., :3, 3:4])[..., 0]
    return torch.cat([v, w], -1)


def se3_inverse(T: torch.Tensor) -> torch.Tensor:
    R = T[..., :3, :3]
    t = T[..., :3, 3:4]
    out = torch.zeros_like(T)
    out[..., :3, :3] = R.transpose(-1, -2)
    out[..., :3, 3:4] = -R.transpose(-1, -2) @ t
    out[..., 3, 3] = 1
    return out


def transform_points(T: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """Apply (..., 4, 4) to points (..., N, 3)."""
    return X @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def pose_from_tq(tq) -> torch.Tensor:
    """(..., 7) (tx ty tz qx qy qz qw) -> (..., 4, 4). Accepts numpy or torch."""
    if not torch.is_tensor(tq):
        tq = torch.as_tensor(np.asarray(tq, dtype=np.float64))
    T = torch.zeros(*tq.shape[:-1], 4, 4, dtype=tq.dtype, device=tq.device)
    T[..., :3, :3] = quat_to_matrix(tq[..., 3:])
    T[..., :3, 3] = tq[..., :3]
    T[..., 3, 3] = 1
    return T


def pose_to_tq(T) -> torch.Tensor:
    """(..., 4, 4) -> (..., 7) (tx ty tz qx qy qz qw)."""
    T = torch.as_tensor(T, dtype=torch.float64) if not torch.is_tensor(T) else T
    return torch.cat([T[..., :3, 3], matrix_to_quat(T[..., :3, :3])], -1)


def orthonormalize(T: torch.Tensor) -> torch.Tensor:
    """Project the rotation part of a pose back onto SO(3) (rounding must not compound)."""
    return pose_from_tq(pose_to_tq(T))


# ---------------------------------------------------------------------- Sim(3)
def sim3_matrix(s, R, t) -> torch.Tensor:
    """Scale, rotation, translation -> 4x4 similarity ``x -> s R x + t``."""
    R = torch.as_tensor(R)
    S = torch.eye(4, dtype=R.dtype, device=R.device)
    S[:3, :3] = s * R
    S[:3, 3] = torch.as_tensor(t, dtype=R.dtype)
    return S


def apply_sim3_to_poses(s: float, R: torch.Tensor, t: torch.Tensor,
                        T: torch.Tensor) -> torch.Tensor:
    """Transform camera-to-world poses by a similarity (scales translations only)."""
    out = T.clone()
    out[..., :3, :3] = R @ T[..., :3, :3]
    out[..., :3, 3] = s * (T[..., :3, 3] @ R.transpose(-1, -2)) + t
    return out


# ---------------------------------------------------------------- projection
def intrinsics_matrix(fx, fy, cx, cy, dtype=torch.float64, device=None) -> torch.Tensor:
    return torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=dtype, device=device)


def intr_tensor(intr, dtype=torch.float32, device=None) -> torch.Tensor:
    """(fx, fy, cx, cy) as a tensor from an Intrinsics, a sequence or a tensor."""
    if hasattr(intr, "fx"):
        intr = (intr.fx, intr.fy, intr.cx, intr.cy)
    return torch.as_tensor(intr, dtype=dtype, device=device)


def pixel_grid(h: int, w: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """(h, w, 2) pixel coordinates (u, v) of pixel centres (integer positions)."""
    v, u = torch.meshgrid(torch.arange(h, dtype=dtype, device=device),
                          torch.arange(w, dtype=dtype, device=device), indexing="ij")
    return torch.stack([u, v], -1)


def project(X: torch.Tensor, intr: torch.Tensor) -> torch.Tensor:
    """Camera-frame points (..., 3) -> pixels (..., 2); intr = (fx, fy, cx, cy)."""
    z = X[..., 2].clamp_min(1e-6)
    return torch.stack([intr[0] * X[..., 0] / z + intr[2],
                        intr[1] * X[..., 1] / z + intr[3]], -1)


def unproject(uv: torch.Tensor, depth: torch.Tensor, intr: torch.Tensor) -> torch.Tensor:
    """Pixels (..., 2) with depth (...) -> camera-frame points (..., 3)."""
    x = (uv[..., 0] - intr[2]) / intr[0]
    y = (uv[..., 1] - intr[3]) / intr[1]
    return torch.stack([x * depth, y * depth, depth], -1)


def depth_to_points(depth: torch.Tensor, intr: torch.Tensor) -> torch.Tensor:
    """(h, w) depth map -> (h, w, 3) camera-frame points."""
    h, w = depth.shape[-2:]
    uv = pixel_grid(h, w, dtype=depth.dtype, device=depth.device)
    return unproject(uv, depth, intr)


# ------------------------------------------------- projection Jacobians (BA)
def project_homogeneous(X: torch.Tensor, intr: torch.Tensor, min_z: float = 1e-6):
    """Project homogeneous camera points ``X = (X, Y, Z)`` (any positive scale,
    e.g. ``R q + t d`` with inverse depth ``d``) -> pixels (..., 2) and the
    (..., 2, 3) Jacobian d(pixel)/dX. ``intr = (fx, fy, cx, cy)``."""
    z = X[..., 2].clamp_min(min_z)
    iz = 1.0 / z
    xz = X[..., 0] * iz
    yz = X[..., 1] * iz
    uv = torch.stack([intr[0] * xz + intr[2], intr[1] * yz + intr[3]], -1)
    zero = torch.zeros_like(z)
    a, b = intr[0] * iz, intr[1] * iz
    J = torch.stack([torch.stack([a, zero, -a * xz], -1),
                     torch.stack([zero, b, -b * yz], -1)], -2)
    return uv, J


def point_jacobian_se3_world(Xw: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """d(Xw_h)/d(xi) for a homogeneous world point ``(Xw, d)`` under the left
    (world-frame) perturbation ``T <- exp(xi) T``, xi = (t, w): (..., 3, 6) =
    ``[d I, -hat(Xw)]``. Chain with ``R_j^T`` for a camera j observing it."""
    eye = torch.eye(3, dtype=Xw.dtype, device=Xw.device).expand(*Xw.shape[:-1], 3, 3)
    return torch.cat([d[..., None, None] * eye, -hat(Xw)], -1)


# ------------------------------------------------------------- interpolation
def quat_slerp(q0: torch.Tensor, q1: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Spherical linear interpolation of (..., 4) (x, y, z, w) quaternions at fractions a (...)."""
    a = torch.as_tensor(a, dtype=q0.dtype, device=q0.device)[..., None]
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    theta = torch.arccos(dot.abs().clamp(max=1.0))
    s = torch.sin(theta)
    small = s < 1e-9
    s_safe = torch.where(small, torch.ones_like(s), s)
    w0 = torch.where(small, 1 - a, torch.sin((1 - a) * theta) / s_safe)
    w1 = torch.where(small, a, torch.sin(a * theta) / s_safe)
    q = w0 * q0 + w1 * q1
    return q / q.norm(dim=-1, keepdim=True)


def interpolate_pose(T0: torch.Tensor, T1: torch.Tensor, a) -> torch.Tensor:
    """Pose between (..., 4, 4) T0 and T1 at fraction a: linear translation, SLERP rotation."""
    a_t = torch.as_tensor(a, dtype=T0.dtype, device=T0.device)
    q = quat_slerp(matrix_to_quat(T0[..., :3, :3]), matrix_to_quat(T1[..., :3, :3]), a_t)
    out = torch.zeros_like(T0)
    out[..., :3, :3] = quat_to_matrix(q)
    out[..., :3, 3] = (1 - a_t[..., None]) * T0[..., :3, 3] + a_t[..., None] * T1[..., :3, 3]
    out[..., 3, 3] = 1
    return out


def disparity_through_flow(d_ref: torch.Tensor, grid: torch.Tensor, flow: torch.Tensor,
                           weight: torch.Tensor, intr: torch.Tensor, T_ref: torch.Tensor,
                           T_new: torch.Tensor) -> torch.Tensor:
    """(h, w) disparity of a new view from the reference view's ``d_ref``: each new pixel
    samples the reference at the end of its flow new -> ref (``grid + flow``), is
    back-projected with that disparity and moved into the new camera (poses camera-to-world).
    Pixels whose flow leaves the image, lands behind the camera or has a mean ``weight``
    <= 0.05 take the median of the others (of ``d_ref`` when none is left)."""
    h, w = d_ref.shape
    coords = grid + flow
    gxy = torch.stack([2 * coords[..., 0] / (w - 1) - 1, 2 * coords[..., 1] / (h - 1) - 1], -1)
    d = torch.nn.functional.grid_sample(d_ref[None, None], gxy[None], mode="bilinear",
                                        padding_mode="border", align_corners=True)[0, 0]
    fx, fy, cx, cy = intr
    q = torch.stack([(coords[..., 0] - cx) / fx, (coords[..., 1] - cy) / fy,
                     torch.ones_like(d)], -1)
    G = (se3_inverse(T_new) @ T_ref).to(torch.float32)
    X = q @ G[:3, :3].T + G[:3, 3] * d[..., None]               # homogeneous (scale d)
    z = X[..., 2] / d.clamp_min(1e-6)                            # metric depth in new
    inside = (coords[..., 0] >= 0) & (coords[..., 0] <= w - 1) & (coords[..., 1] >= 0) & \
        (coords[..., 1] <= h - 1)
    valid = inside & (z > 1e-3) & (weight.mean(-1) > 0.05)
    out = torch.where(valid, 1.0 / z.clamp_min(1e-3), torch.zeros_like(z))
    fill = float(out[valid].median()) if bool(valid.any()) else float(d_ref.median())
    return torch.where(valid, out, torch.full_like(out, fill)).clamp(1e-3, 1e3)
