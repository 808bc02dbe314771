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

:func:`deform_keyframe` applies it to a mapper's keyframe; :func:`merge_keyframe` hands a
keyframe's Gaussians over to an older keyframe, whose deformations they follow from then on.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.geometry import matrix_to_quat, project, quat_multiply, se3_inverse, transform_points
from splat_slam_ros.mapping.keyframe_inputs import MapError, check_keyframe_inputs, check_pose
from splat_slam_ros.mapping.optimise import viewmat


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


@torch.no_grad()
def deform_keyframe(mp, kf_id: int, pose, depth=None, valid=None) -> int:
    """Keyframe ``kf_id`` of the mapper ``mp`` moved: deform its Gaussians (Eq. 12), then
    store the new pose/depth. Returns the number of Gaussians moved (0 for a keyframe that
    was never mapped). Without ``depth`` the keyframe's Gaussians move rigidly."""
    kf = mp.keyframes.get(int(kf_id))
    if kf is None:
        return 0
    pose = check_pose(pose)
    new_depth = new_valid = new_weight = None
    if depth is not None:
        _, new_depth, new_valid, new_weight = check_keyframe_inputs(
            np.zeros((mp.H, mp.W, 3), np.uint8), depth, valid, mp.W, mp.H, mp.device)
    sel = (mp.map.kf_id == kf.kf_id).nonzero()[:, 0]
    if len(sel):
        g = mp.map
        d = deform_gaussians(g.means[sel], g.quats[sel], g.log_scales[sel], kf.pose, pose,
                             mp.intr, kf.depth if new_depth is not None else None,
                             new_depth, kf.valid, new_valid)
        g.set_rows(sel, means=d.means, quats=d.quats, log_scales=d.log_scales)
    kf.pose = pose
    if new_depth is not None:
        kf.depth, kf.valid, kf.weight = new_depth, new_valid, new_weight
    mp.n_deformations += 1
    mp.n_deformed_gaussians += int(len(sel))
    return int(len(sel))


def in_view(mp, means: torch.Tensor, pose) -> torch.Tensor:
    """Which points project inside the mapper's image at camera ``pose`` (in front of it)."""
    X = transform_points(viewmat(pose, mp.device), means)
    uv = project(X, torch.tensor(mp.intr, dtype=X.dtype, device=X.device))
    return (X[:, 2] > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < mp.W) & (uv[:, 1] >= 0) & \
        (uv[:, 1] < mp.H)


@torch.no_grad()
def merge_keyframe(mp, kf_id: int, into: int) -> Tuple[int, int]:
    """A mapped keyframe whose view an older one (``into``) already has leaves the map's
    keyframes (a bounded map in a revisited room), as if it had been recognised as a
    revisit when it arrived: its Gaussians inside the older keyframe's view duplicate
    that view's and are removed; the rest (what only it saw) are anchored to ``into``
    and follow its deformations (Eq. 12). Its view leaves the window and the optimiser.
    Returns (Gaussians removed, Gaussians re-anchored). The first keyframe (exposure
    gauge) stays."""
    kf_id, into = int(kf_id), int(into)
    kf, keep = mp.keyframes.get(kf_id), mp.keyframes.get(into)
    if kf is None or keep is None or kf_id == into:
        raise MapError(f"cannot merge keyframe {kf_id} into {into}: both must be mapped")
    if kf.index == 0:
        raise MapError(f"keyframe {kf_id} fixes the exposure gauge and cannot be merged")
    own = mp.map.kf_id == kf_id
    seen = own & in_view(mp, mp.map.means, keep.pose)
    mp.map.kf_id[own & ~seen] = into
    n_moved = int((own & ~seen).sum())
    n_removed = mp.map.remove(seen)
    # densification statistics gathered while its view sat at a wrong (uncorrected) pose
    # say nothing about missing detail: reset for what that view covers
    stale = in_view(mp, mp.map.means, kf.pose)
    mp.map.grad_accum[stale] = 0
    mp.map.grad_count[stale] = 0
    mp.camera.drop_keyframe(kf)             # its exposure leaves the optimiser
    mp.window.drop(kf_id, into)
    del mp.keyframes[kf_id]
    mp.counts["merged_keyframes"] += 1
    return n_removed, n_moved
