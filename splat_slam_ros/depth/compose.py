"""Proxy depth fill (paper §3.2, Eq. 10, with the scale/shift fit of Eq. 3): the multi-view
depth of a keyframe, its holes filled from the mono depth mapped by a least-squares
scale/shift, or (without a mono model) from the tracker's BA depth, and optionally enclosed
small planar holes from their rim. Used by :class:`~splat_slam_ros.depth.proxy_depth.
ProxyDepthEstimator` (step 3 of that module's docstring)."""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.types import ProxyDepth

SOURCE_EMPTY = ProxyDepth.SOURCE_EMPTY
SOURCE_MULTIVIEW = ProxyDepth.SOURCE_MULTIVIEW
SOURCE_MONO = ProxyDepth.SOURCE_MONO
SOURCE_BA = ProxyDepth.SOURCE_BA


# ------------------------------------------------------------------ helpers
def disp_to_depth(disp: torch.Tensor) -> torch.Tensor:
    """1 / disparity where it is finite and positive, else 0 (no depth)."""
    ok = torch.isfinite(disp) & (disp > 0)
    return torch.where(ok, 1.0 / torch.where(ok, disp, torch.ones_like(disp)),
                       torch.zeros_like(disp))


# ---------------------------------------------------------- scale / shift
def fit_scale_shift(x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor,
                    weight: Optional[torch.Tensor] = None) -> Tuple[float, float]:
    """Least squares ``argmin_{theta,gamma} sum w (theta x + gamma - y)^2`` over ``mask``
    (Eq. 3). Returns (theta, gamma); (nan, nan) if fewer than 2 distinct x values."""
    m = mask & torch.isfinite(x) & torch.isfinite(y)
    xs = x[m].to(torch.float64)
    ys = y[m].to(torch.float64)
    ws = torch.ones_like(xs) if weight is None else weight[m].to(torch.float64)
    sw = ws.sum()
    if xs.numel() < 2 or float(sw) <= 0:
        return float("nan"), float("nan")
    mx = (ws * xs).sum() / sw
    my = (ws * ys).sum() / sw
    vx = (ws * (xs - mx) ** 2).sum()
    if float(vx) <= 1e-12 * float(sw) * max(float(mx) ** 2, 1e-12):
        return float("nan"), float("nan")
    theta = (ws * (xs - mx) * (ys - my)).sum() / vx
    gamma = my - theta * mx
    return float(theta), float(gamma)


# ------------------------------------------------------- small hole fill
def fill_small_holes(depth: np.ndarray, valid: np.ndarray, max_px: int,
                     plane_tol: float = 0.02) -> np.ndarray:
    """Fill enclosed holes of <= ``max_px`` pixels whose 1-pixel rim is a plane.

    The plane is fitted in disparity (affine in the pixel coordinates for any 3D plane) to
    the rim by least squares; a hole is filled only if every rim pixel lies within
    ``plane_tol`` (relative disparity) of it, the hole does not touch the image border and
    the plane is in front of the camera on the whole hole. Returns a bool mask of the filled
    pixels; ``depth`` is filled in place.
    """
    from scipy import ndimage
    if max_px <= 0:
        return np.zeros_like(valid, bool)
    H, W = valid.shape
    lab, n = ndimage.label(~valid)                       # 4-connected holes
    if n == 0:
        return np.zeros_like(valid, bool)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    small = sizes <= max_px
    small[0] = False
    small[border] = False
    if not small.any():
        return np.zeros_like(valid, bool)
    slab = np.where(small[lab], lab, 0)
    rim_lab = ndimage.grey_dilation(slab, size=(3, 3))
    rim = valid & (rim_lab > 0)
    rl = rim_lab[rim]
    vv, uu = np.nonzero(rim)
    disp = 1.0 / depth[rim].astype(np.float64)
    u = uu.astype(np.float64)
    v = vv.astype(np.float64)
    L = n + 1
    # per-hole normal equations of disp = a u + b v + c
    cols = [u * u, u * v, u, v * v, v, np.ones_like(u), u * disp, v * disp, disp]
    S = np.stack([np.bincount(rl, c, minlength=L) for c in cols], 1)
    A = np.empty((L, 3, 3))
    A[:, 0] = S[:, [0, 1, 2]]
    A[:, 1] = S[:, [1, 3, 4]]
    A[:, 2] = S[:, [2, 4, 5]]
    b = S[:, 6:9]
    cnt = S[:, 5]
    good = small & (cnt >= 4)
    A[~good] = np.eye(3)
    b[~good] = 0
    det = np.linalg.det(A)
    good &= np.abs(det) > 1e-9
    A[~good] = np.eye(3)
    coef = np.linalg.solve(A, b[..., None])[..., 0]                # (L, 3)
    pred = coef[rl, 0] * u + coef[rl, 1] * v + coef[rl, 2]
    rel = np.abs(pred - disp) / np.maximum(disp, 1e-12)
    worst = np.zeros(L)
    np.maximum.at(worst, rl, rel)
    good &= worst <= plane_tol
    hole = good[lab] & ~valid
    hv, hu = np.nonzero(hole)
    hl = lab[hole]
    dfill = coef[hl, 0] * hu + coef[hl, 1] * hv + coef[hl, 2]
    bad = np.zeros(L, bool)
    np.logical_or.at(bad, hl, ~(dfill > 0))
    keep = ~bad[hl]
    filled = np.zeros_like(valid, bool)
    filled[hv[keep], hu[keep]] = True
    depth[hv[keep], hu[keep]] = (1.0 / dfill[keep]).astype(depth.dtype)
    return filled


# ---------------------------------------------------------------- compose
def _mono_to_fit_space(mono: torch.Tensor, fit_space: str) -> torch.Tensor:
    if fit_space == "disparity":
        return disp_to_depth(mono)                   # 1 / x where positive (an inversion)
    return torch.where(torch.isfinite(mono) & (mono > 0), mono, torch.zeros_like(mono))


def fit_mono(mono: torch.Tensor, depth: torch.Tensor, valid: torch.Tensor,
             fit_space: str = "depth") -> Tuple[float, float]:
    """Eq. 3 (§3.2 in depth, or in disparity): theta, gamma mapping the mono prediction onto
    the valid multi-view ``depth`` (same grid as ``mono``)."""
    x = _mono_to_fit_space(mono.to(torch.float32), fit_space)
    y = disp_to_depth(depth) if fit_space == "disparity" else depth
    return fit_scale_shift(x, y, valid & (x > 0) & (depth > 0))


def compose_proxy_depth(mv_depth: torch.Tensor, mv_valid: torch.Tensor,
                        mono_depth: Optional[torch.Tensor] = None, fit_space: str = "depth",
                        fill_small: int = 0, plane_tol: float = 0.02,
                        max_depth_ratio: float = 3.0,
                        scale_shift: Optional[Tuple[float, float]] = None,
                        ba_depth: Optional[torch.Tensor] = None):
    """§3.2, Eq. 10: D = multi-view depth where valid, else theta * D_mono + gamma (Eq. 3 in depth;
    or in disparity for disparity models); without mono, the holes take ``ba_depth`` (the
    BA-grid depth upsampled over every cell, source 3) when given and some pixel is
    multi-view consistent (a keyframe without any waits for its views), then the optional
    small-hole fill.

    ``scale_shift``: (theta, gamma) fitted elsewhere (the estimator fits at BA resolution,
    where the multi-view depth is not interpolated); default: fitted here on ``mv_valid``.
    Returns (depth (H,W) float32 numpy, source (H,W) uint8 numpy, theta, gamma).
    """
    depth = torch.where(mv_valid, mv_depth, torch.zeros_like(mv_depth)).to(torch.float32)
    source = torch.where(mv_valid, SOURCE_MULTIVIEW, SOURCE_EMPTY).to(torch.uint8)
    theta = gamma = float("nan")
    if mono_depth is not None:
        mono = mono_depth.to(depth.device, torch.float32)
        x = _mono_to_fit_space(mono, fit_space)
        mok = x > 0
        if scale_shift is None:
            theta, gamma = fit_mono(mono, depth, mv_valid, fit_space)
        else:
            theta, gamma = scale_shift
        if np.isfinite(theta) and theta > 0:
            fitted = theta * x + gamma
            if fit_space == "disparity":
                fitted = disp_to_depth(fitted)
            hole = ~mv_valid & mok & torch.isfinite(fitted) & (fitted > 0)
            if max_depth_ratio and max_depth_ratio > 0 and bool(mv_valid.any()):
                med = depth[mv_valid].median()
                hole &= fitted <= max_depth_ratio * med
            depth = torch.where(hole, fitted, depth)
            source = torch.where(hole, torch.full_like(source, SOURCE_MONO), source)
        else:
            theta = gamma = float("nan")
    elif ba_depth is not None and bool(mv_valid.any()):   # nothing consistent yet: wait
        hole = ~mv_valid & (ba_depth > 0)
        if max_depth_ratio and max_depth_ratio > 0:
            hole &= ba_depth <= max_depth_ratio * depth[mv_valid].median()
        depth = torch.where(hole, ba_depth.to(depth.dtype), depth)
        source = torch.where(hole, torch.full_like(source, SOURCE_BA), source)
    depth_np = depth.cpu().numpy().astype(np.float32, copy=False)
    source_np = source.cpu().numpy()
    if mono_depth is None and fill_small > 0:
        filled = fill_small_holes(depth_np, source_np > 0, fill_small, plane_tol)
        source_np[filled] = SOURCE_MULTIVIEW
    return depth_np, source_np, theta, gamma
