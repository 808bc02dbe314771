"""Map initialisation per keyframe (§3.2 "Map Initialization", supplementary "Map Initialization").

New Gaussians come from the keyframe's proxy depth, as MonoGS does in RGB-D mode: every
pixel with valid depth is unprojected to 3D, the point cloud is randomly downsampled by
the factor theta (keep 1/theta of the points; theta = 32, 16 for the first keyframe), and
each kept point becomes a Gaussian with identity rotation, opacity 0.5, the pixel's colour
and an isotropic scale from the distances to its nearest neighbours in that point cloud.
"""
from __future__ import annotations

from typing import Dict, Optional

import numpy as np
import torch
from scipy.spatial import cKDTree

from splat_slam_ros.geometry import transform_points, unproject

# Neighbours used for the initial scale (MonoGS/3DGS use the 3 nearest).
N_NEIGHBOURS = 3


def nn_scale(points: np.ndarray, k: int = N_NEIGHBOURS) -> np.ndarray:
    """Per point: sqrt(mean squared distance to its k nearest neighbours) (cKDTree)."""
    n = len(points)
    if n < 2:
        return np.zeros(n)
    k = min(k, n - 1)
    d, _ = cKDTree(points).query(points, k=k + 1)   # column 0 is the point itself
    d = np.asarray(d).reshape(n, k + 1)[:, 1:]
    return np.sqrt((d * d).mean(1))


def init_gaussians(image, depth, valid, pose_c2w, intrinsics, downsample: int,
                   opacity: float = 0.5, generator: Optional[torch.Generator] = None,
                   device="cpu", dtype=torch.float32, scale: float = 1.0
                   ) -> Dict[str, torch.Tensor]:
    """New Gaussians for one keyframe from its proxy depth (``scale``: the initial scale
    over the nearest-neighbour distance; ``mapping.init_scale``).

    image (H,W,3) uint8 or float in [0,1]; depth (H,W) metres, 0 = missing; valid (H,W) bool
    or None; pose_c2w 4x4; intrinsics (fx, fy, cx, cy); pixel centres at integer (u, v).
    Returns means (M,3) world, colors (M,3), log_scales (M,3), quats (M,4) identity,
    opacity_logits (M,), with M = n_valid // downsample (at least 1 if any depth is valid).
    """
    depth = torch.as_tensor(depth).to(device=device, dtype=torch.float64)
    ok = torch.isfinite(depth) & (depth > 0)
    if valid is not None:
        ok &= torch.as_tensor(valid, device=device).bool()
    idx = ok.flatten().nonzero()[:, 0]
    n_valid = int(idx.numel())
    keep = 0 if n_valid == 0 else max(1, n_valid // max(1, int(downsample)))
    if keep < n_valid:
        perm = torch.randperm(n_valid, generator=generator)[:keep].to(idx.device)
        idx = idx[perm.sort().values]
    H, W = depth.shape
    v = (idx // W).to(torch.float64)
    u = (idx % W).to(torch.float64)
    z = depth.flatten()[idx]
    intr = torch.as_tensor(np.asarray(intrinsics, dtype=np.float64), device=device)
    pts_cam = unproject(torch.stack([u, v], -1), z, intr)
    T = torch.as_tensor(np.asarray(pose_c2w, dtype=np.float64), device=device)
    pts = transform_points(T, pts_cam)

    img = torch.as_tensor(np.asarray(image)).to(device)
    img = img.to(torch.float64) / 255.0 if img.dtype == torch.uint8 else img.to(torch.float64)
    colors = img.reshape(-1, img.shape[-1])[idx][:, :3]

    if not scale > 0:
        raise ValueError(f"mapping.init_scale must be > 0, got {scale}")
    nn = torch.as_tensor(nn_scale(pts.cpu().numpy()), device=device)
    # Fallback for a lone point / duplicates: the footprint of theta pixels at that depth.
    footprint = z * np.sqrt(max(1, int(downsample))) / abs(float(intr[0]))
    scale = float(scale) * torch.where(nn > 1e-7, nn, footprint)
    M = int(idx.numel())
    f = dict(device=device, dtype=dtype)
    quats = torch.zeros(M, 4, **f)
    quats[:, 3] = 1.0
    op = float(np.clip(opacity, 1e-4, 1 - 1e-4))
    return {
        "means": pts.to(**f),
        "colors": colors.to(**f),
        "log_scales": scale.log()[:, None].expand(M, 3).to(**f).contiguous(),
        "quats": quats,
        "opacity_logits": torch.full((M,), float(np.log(op / (1 - op))), **f),
    }


def uncovered(alpha: torch.Tensor, rendered_depth: torch.Tensor, depth: torch.Tensor,
              tol: float) -> torch.Tensor:
    """Pixels a map does not explain yet (``mapping.seed_uncovered``): rendered with
    accumulated opacity below 0.5, or a rendered depth off the keyframe's depth by more than
    ``tol`` x depth (something new in front of or behind the map). New Gaussians are seeded
    only there when a loaded map is extended, so a revisited view adds none."""
    far = (rendered_depth / alpha.clamp_min(1e-6) - depth).abs() > tol * depth   # blended z
    return (alpha < 0.5) | far
