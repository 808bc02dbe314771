"""Map deformation (§3.2 "Map Deformation", Eq. 12 of the paper).

When a keyframe's camera-to-world pose changes omega -> omega' and its proxy depth D -> D'
(local BA, loop closure, global BA), every Gaussian anchored by that keyframe is moved:

    (u, v)   = projection of mu_i into omega
    dD       = D'(u, v) - D(u, v)
    z        = (omega^-1 mu_i)_z
    mu_i'    = omega' [ (1 + dD / z) * (omega^-1 mu_i) ]      (shift along the viewing ray)
    R_i'     = R' R^-1 R_i                                      (R, R': rotations of omega, omega')
    s_i'     = (1 + dD / z) s_i          i.e.  log s_i' = log s_i + log(1 + dD / z)

The paper writes mu' = (1 + dD/z) omega' omega^-1 mu; the factor scales the camera-frame
point omega^-1 mu (its depth becomes z + dD, its pixel stays (u, v)) before omega' maps it
back to the world - "shift the mean by D'(u,v) - D(u,v) along the optical axis" in the text.
Gaussians that project outside the image, behind the camera, or onto missing depth (in D
or D') move rigidly only (dD = 0). Depth is looked up at the nearest pixel.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from splat_slam_ros.geometry import matrix_to_quat, project, quat_multiply, se3_inverse, transform_points


@dataclass
class Deformed:
    means: torch.Tensor        # (N, 3)
    quats: torch.Tensor        # (N, 4) x y z w
    log_scales: torch.Tensor   # (N, 3)
    nonrigid: torch.Tensor     # (N,) bool: the depth shift was applied (else rigid only)
    factor: torch.Tensor       # (N,) 1 + dD / z (1 where rigid)


def deform_gaussians(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor,
                     old_pose, new_pose, intrinsics,
                     old_depth: Optional[torch.Tensor] = None,
                     new_depth: Optional[torch.Tensor] = None,
                     old_valid: Optional[torch.Tensor] = None,
                     new_valid: Optional[torch.Tensor] = None,
                     min_factor: float = 0.05) -> Deformed:
    """Apply Eq. 12 to Gaussians anchored by one keyframe (see the module docstring).

    Poses are camera-to-world 4x4; intrinsics (fx, fy, cx, cy) of the depth maps; depth 0 or
    non-finite = missing. Without depth maps the update is rigid. Computed in float64.
    """
    dev, dt = means.device, means.dtype
    f64 = dict(device=dev, dtype=torch.float64)
    mu = means.detach().to(**f64)
    T_old = torch.as_tensor(old_pose).to(**f64)
    T_new = torch.as_tensor(new_pose).to(**f64)
    X = transform_points(se3_inverse(T_old), mu)              # omega^-1 mu (camera frame)
    z = X[:, 2]
    factor = torch.ones_like(z)
    nonrigid = torch.zeros_like(z, dtype=torch.bool)
    if old_depth is not None and new_depth is not None and len(mu):
        D0 = torch.as_tensor(old_depth).to(**f64)
        D1 = torch.as_tensor(new_depth).to(**f64)
        H, W = D0.shape
        intr = torch.as_tensor(intrinsics, **f64)
        uv = project(X, intr)
        u = torch.round(uv[:, 0])
        v = torch.round(uv[:, 1])
        inside = (z > 1e-6) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        ui = u.clamp(0, W - 1).long()
        vi = v.clamp(0, H - 1).long()
        d0 = D0[vi, ui]
        d1 = D1[vi, ui]
        ok = inside & torch.isfinite(d0) & torch.isfinite(d1) & (d0 > 0) & (d1 > 0)
        if old_valid is not None:
            ok &= torch.as_tensor(old_valid, device=dev).bool()[vi, ui]
        if new_valid is not None:
            ok &= torch.as_tensor(new_valid, device=dev).bool()[vi, ui]
        f = 1.0 + (d1 - d0) / z.clamp_min(1e-6)                 # 1 + dD / z
        ok &= f > min_factor                                    # never flip/collapse a Gaussian
        factor = torch.where(ok, f, factor)
        nonrigid = ok
    # Eq. 12: mu' = omega' [(1 + dD/z) omega^-1 mu]
    new_means = transform_points(T_new, X * factor[:, None])
    # Eq. 12: R_i' = R' R^-1 R_i
    q_rel = matrix_to_quat(T_new[:3, :3] @ T_old[:3, :3].T)
    new_quats = quat_multiply(q_rel.expand(len(mu), 4), quats.detach().to(**f64))
    # Eq. 12: s' = (1 + dD/z) s
    new_log_scales = log_scales.detach().to(**f64) + factor.log()[:, None]
    return Deformed(new_means.to(dt), new_quats.to(dt), new_log_scales.to(dt), nonrigid,
                    factor.to(dt))
