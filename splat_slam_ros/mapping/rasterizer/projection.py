"""EWA splatting of 3D Gaussians onto the image plane (paper §3.2, "Rendering"), in torch.

Device-agnostic and differentiable by autograd; shared by the C++ and the pure-torch
rasterizers so both see the same 2D Gaussians. Culled (radius 0, no footprint): centre not
beyond ``near``, or footprint outside the image (the frustum test, with the footprint as
margin).

Pixel convention (the project's, see ``geometry.pixel_grid``): pixel ``(row v, col u)`` has
its centre at the continuous image point ``(u, v)``, i.e. ``u = fx * x / z + cx``.

A Gaussian's *footprint* is the axis-aligned bounding box of its 3-sigma ellipse,
``|u - mu_x| <= 3 sqrt(S'_xx)`` and ``|v - mu_y| <= 3 sqrt(S'_yy)``, as inclusive integer pixel
ranges clipped to the image. A Gaussian only ever contributes to pixels inside its footprint;
this rule is tile-independent, so the tiled C++ kernel and the reference agree for any tile size.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from splat_slam_ros.geometry import quat_to_matrix

LOW_PASS = 0.3          # added to the 2D covariance diagonal (anti-aliasing low-pass, in px^2)
SIGMA_EXTENT = 3.0      # footprint / radius in standard deviations
FOV_CLAMP = 0.3         # J is evaluated with x/z clamped to the frustum widened by 30 % of tan(fov/2)


@dataclass
class Projected:
    means2d: torch.Tensor   # (N, 2) pixel position of the centre
    conics: torch.Tensor    # (N, 3) inverse 2D covariance (a, b, c) of [[a, b], [b, c]]
    depths: torch.Tensor    # (N,) camera z of the centre
    ranges: torch.Tensor    # (N, 4) int32 inclusive footprint (x_lo, x_hi, y_lo, y_hi); empty if culled
    radii: torch.Tensor     # (N,) int32 3-sigma radius of the major axis in px, 0 if culled
    valid: torch.Tensor     # (N,) bool, not culled


def project_gaussians(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                      viewmat: torch.Tensor, fx: float, fy: float, cx: float, cy: float,
                      width: int, height: int, near: float,
                      low_pass: float = LOW_PASS) -> Projected:
    """Project N Gaussians with world-to-camera ``viewmat``; quats are (x, y, z, w);
    ``low_pass`` px^2 added to the 2D covariance diagonal."""
    dtype = means.dtype
    R = viewmat[:3, :3].to(dtype)
    t = viewmat[:3, 3].to(dtype)
    p = means @ R.T + t                                          # mu_cam = omega^-1 mu
    x, y, z = p.unbind(-1)
    in_front = z > near
    zs = torch.where(in_front, z, torch.ones_like(z))            # safe z for culled Gaussians

    # Sigma' = J W Sigma W^T J^T + low_pass I with Sigma = (R_q S)(R_q S)^T  (paper §3.2, EWA).
    # Written with few, large ops: autograd overhead per op dominates on CPU.
    Rq = quat_to_matrix(quats)                                   # (N, 3, 3)
    n = Rq.shape[0]
    WR = (R @ Rq.transpose(0, 1).reshape(3, 3 * n)).reshape(3, n, 3)   # rows of W R_q
    M = WR * scales[None]                                        # rows of W R_q S, (3, N, 3)
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    inv_z = 1.0 / zs
    tx = (x * inv_z).clamp(-(cx / fx + FOV_CLAMP * tan_x), (width - cx) / fx + FOV_CLAMP * tan_x)
    ty = (y * inv_z).clamp(-(cy / fy + FOV_CLAMP * tan_y), (height - cy) / fy + FOV_CLAMP * tan_y)
    # J = [[fx/z, 0, -fx tx/z], [0, fy/z, -fy ty/z]] (tx, ty: clamped x/z, y/z)
    A0 = (fx * inv_z)[:, None] * (M[0] - tx[:, None] * M[2])     # rows of J W R_q S
    A1 = (fy * inv_z)[:, None] * (M[1] - ty[:, None] * M[2])
    a = (A0 * A0).sum(-1) + low_pass
    b = (A0 * A1).sum(-1)
    c = (A1 * A1).sum(-1) + low_pass
    det = a * c - b * b
    conics = torch.stack([c, -b, a], -1) / det[:, None]
    means2d = torch.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], -1)

    with torch.no_grad():
        mx, my = means2d[:, 0].detach(), means2d[:, 1].detach()
        ex = SIGMA_EXTENT * a.detach().sqrt()
        ey = SIGMA_EXTENT * c.detach().sqrt()
        # clamp before the integer cast: off-screen centres can be huge
        x_lo = torch.ceil(mx - ex).clamp(-1, width)
        x_hi = torch.floor(mx + ex).clamp(-1, width)
        y_lo = torch.ceil(my - ey).clamp(-1, height)
        y_hi = torch.floor(my + ey).clamp(-1, height)
        valid = (in_front & (det.detach() > 0) & (x_lo <= x_hi) & (y_lo <= y_hi)
                 & (x_hi >= 0) & (x_lo <= width - 1) & (y_hi >= 0) & (y_lo <= height - 1))
        ranges = torch.stack([x_lo.clamp(0, width - 1), x_hi.clamp(0, width - 1),
                              y_lo.clamp(0, height - 1), y_hi.clamp(0, height - 1)], -1)
        ranges = torch.where(valid[:, None], ranges,
                             torch.tensor([1.0, 0.0, 1.0, 0.0], dtype=dtype, device=means.device))
        ranges = ranges.to(torch.int32)
        mid = 0.5 * (a.detach() + c.detach())
        lam = mid + (mid * mid - det.detach()).clamp_min(0.1).sqrt()
        radii = torch.where(valid, torch.ceil(SIGMA_EXTENT * lam.sqrt()), torch.zeros_like(lam))
        radii = radii.clamp(max=2 ** 30).to(torch.int32)
    return Projected(means2d=means2d, conics=conics, depths=z, ranges=ranges, radii=radii,
                     valid=valid)
