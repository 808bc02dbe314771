"""The multi-view consistency filter (paper Eq. 4-6) and sampling of full-resolution maps on
the BA grid: shared by DSPO (its high/low-error split of the window's disparities) and the
proxy depth stage (which pixels of a keyframe's depth to trust).

Eq. 4-6 (:func:`multiview_filter`): every pixel of keyframe i is warped with its depth into
the other keyframes k, the depth of k is read there and back-projected (Eq. 4-5); the pixel
is consistent with k when the two 3D points are closer than ``eta * mean depth of i``. It is
valid when consistent in ``>= n_c`` views (Eq. 6) and its depth is ``<= 3x`` the median valid
depth. Only views with parallax count (:func:`parallax_pairs`).
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.geometry import intr_tensor, pixel_grid, se3_inverse

_PAIR_CHUNK_POINTS = 1 << 21      # (pairs x pixels) processed at once in the filter


# ------------------------------------------------------- Eq. 4-6 filter
def all_pairs(n: int, device=None) -> torch.Tensor:
    """(P, 2) (target, view) pairs over all ordered pairs i != k."""
    t, k = torch.meshgrid(torch.arange(n, device=device), torch.arange(n, device=device),
                          indexing="ij")
    m = t != k
    return torch.stack([t[m], k[m]], -1)


def _sample_depth(depth_flat: torch.Tensor, k: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
                  h: int, w: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """Depth of views ``k`` (P,) at continuous pixels (P, Q) (``depth_flat``: all views
    flattened, 0 = missing): bilinear where all four neighbours have depth, nearest
    otherwise; returns (depth, ok)."""
    P, Q = u.shape
    inb = (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    uc = u.clamp(0, w - 1)
    vc = v.clamp(0, h - 1)
    x0 = uc.floor().clamp_(max=max(w - 2, 0))
    y0 = vc.floor().clamp_(max=max(h - 2, 0))
    ax = uc - x0
    ay = vc - y0
    dx = 1 if w > 1 else 0
    dy = w if h > 1 else 0
    i00 = (y0 * w + x0).long() + (k * (h * w))[:, None]
    i00 = i00.reshape(-1)

    def gather(idx):
        return depth_flat.index_select(0, idx).view(P, Q)

    d00, d01, d10, d11 = gather(i00), gather(i00 + dx), gather(i00 + dy), gather(i00 + dx + dy)
    all4 = (d00 > 0) & (d01 > 0) & (d10 > 0) & (d11 > 0)
    bil = torch.lerp(torch.lerp(d00, d01, ax), torch.lerp(d10, d11, ax), ay)
    left, top = ax < 0.5, ay < 0.5
    near = torch.where(top, torch.where(left, d00, d01), torch.where(left, d10, d11))
    out = torch.where(all4, bil, near)
    return out, inb & (out > 0)


@torch.no_grad()
def consistency_count(depths: torch.Tensor, poses: torch.Tensor, intr, eta: float,
                      pairs: Optional[torch.Tensor] = None,
                      valid: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Two-view consistency count n_i(u, v) of Eq. 6 for every keyframe that is a target.

    depths (N, h, w) metres (<= 0 or non-finite = missing); poses (N, 4, 4) camera-to-world;
    intr (fx, fy, cx, cy) of the (h, w) grid; pairs (P, 2) long (target, view), default all
    ordered pairs. Returns (N, h, w) int32 (0 for keyframes that are no target).

    Eq. 4-5: p_i = T_i D_i(u,v) K^-1[u,v,1]; (u^,v^) = pi(T_k^-1 p_i); p_k = T_k D_k(u^,v^)
    K^-1[u^,v^,1] with D_k read at the continuous (u^,v^) (bilinear where its 4 neighbours
    are valid, else nearest). p_i and p_k lie on the same ray of camera k, so
    ||p_i - p_k|| = |z_ik - D_k(u^,v^)| * ||X_ik|| / z_ik, which is what is evaluated.
    """
    N, h, w = depths.shape
    device = depths.device
    D = depths.to(torch.float32)
    ok = torch.isfinite(D) & (D > 0)
    if valid is not None:
        ok &= valid.to(device)
    D = torch.where(ok, D, torch.zeros_like(D))
    if pairs is None:
        pairs = all_pairs(N, device)
    pairs = pairs.to(device=device, dtype=torch.long).reshape(-1, 2)
    count = torch.zeros(N, h * w, dtype=torch.int32, device=device)
    if len(pairs) == 0:
        return count.reshape(N, h, w)
    intr = intr_tensor(intr, torch.float32, device)
    # threshold per target: eta * average depth (Eq. 6)
    nvalid = ok.flatten(1).sum(1)
    mean_d = D.flatten(1).sum(1) / nvalid.clamp_min(1)
    thresh = eta * mean_d
    # target camera points (N, Q, 3)
    uv = pixel_grid(h, w, dtype=torch.float32, device=device).reshape(-1, 2)
    rays = torch.stack([(uv[:, 0] - intr[2]) / intr[0], (uv[:, 1] - intr[3]) / intr[1],
                        torch.ones_like(uv[:, 0])], -1)                       # (Q, 3)
    Dflat = D.reshape(-1)
    T = poses.to(device=device, dtype=torch.float64)
    Tinv = se3_inverse(T)
    Q = h * w
    raysT = rays.T.contiguous()                                               # (3, Q)
    okf = ok.reshape(N, Q)
    chunk = max(1, _PAIR_CHUNK_POINTS // Q)
    for s in range(0, len(pairs), chunk):
        pt, pk = pairs[s:s + chunk, 0], pairs[s:s + chunk, 1]
        rel = (Tinv[pk] @ T[pt]).to(torch.float32)                           # cam t -> cam k
        dt = D[pt].reshape(len(pt), 1, Q)
        X = torch.matmul(rel[:, :3, :3], raysT) * dt + rel[:, :3, 3:4]       # (P, 3, Q)
        x, y, z = X.unbind(1)
        front = z > 1e-6
        iz = 1.0 / torch.where(front, z, torch.ones_like(z))
        xn, yn = x * iz, y * iz
        dk, okk = _sample_depth(Dflat, pk, intr[0] * xn + intr[2], intr[1] * yn + intr[3],
                                h, w)
        # ||p_i - p_k||: both on the ray (xn, yn, 1) of camera k
        dist = (z - dk).abs() * torch.sqrt(1.0 + xn * xn + yn * yn)
        cons = front & okk & okf[pt] & (dist < thresh[pt][:, None])
        count.index_add_(0, pt, cons.to(torch.int32))
    return count.reshape(N, h, w)


@torch.no_grad()
def parallax_pairs(depths: torch.Tensor, poses: torch.Tensor, pairs: torch.Tensor,
                   min_deg: float) -> torch.Tensor:
    """The (target, view) pairs whose baseline is at least tan(``min_deg``) x the target's
    median depth. Eq. 4-6 cannot test a depth without parallax: under a pure rotation every
    depth reprojects consistently, so such views would "confirm" any depth, including the
    near-zero disparities that BA leaves on keyframes it cannot triangulate."""
    if min_deg <= 0 or len(pairs) == 0:
        return pairs
    D = depths.to(torch.float32)
    ok = torch.isfinite(D) & (D > 0)
    med = torch.nanmedian(torch.where(ok, D, torch.full_like(D, float("nan"))).flatten(1),
                          dim=1).values                                   # nan if none
    c = poses.to(torch.float64)[:, :3, 3]
    base = (c[pairs[:, 0]] - c[pairs[:, 1]]).norm(dim=1)
    need = float(np.tan(np.radians(min_deg))) * med[pairs[:, 0]].to(torch.float64)
    return pairs[base >= need]


def multiview_filter(depths: torch.Tensor, poses: torch.Tensor, intr, eta: float = 0.01,
                     min_views: int = 2, max_depth_ratio: float = 3.0,
                     pairs: Optional[torch.Tensor] = None,
                     valid: Optional[torch.Tensor] = None,
                     min_parallax_deg: float = 0.0) -> Tuple[torch.Tensor, torch.Tensor]:
    """Eq. 6 validity: consistent in >= ``min_views`` other keyframes and depth <=
    ``max_depth_ratio`` x the median of the consistent depths; only views with a baseline
    of at least ``min_parallax_deg`` at the target's median depth count
    (:func:`parallax_pairs`). Returns (valid (N,h,w) bool, count (N,h,w) int32)."""
    if pairs is None:
        pairs = all_pairs(depths.shape[0], depths.device)
    pairs = parallax_pairs(depths, poses, pairs.to(depths.device).reshape(-1, 2),
                           min_parallax_deg)
    count = consistency_count(depths, poses, intr, eta, pairs, valid)
    ok = count >= int(min_views)
    if max_depth_ratio and max_depth_ratio > 0:
        d = torch.where(ok, depths.to(torch.float32), torch.full_like(depths, float("nan"),
                                                                      dtype=torch.float32))
        med = torch.nanmedian(d.flatten(1), dim=1).values                     # nan if none
        ok &= ~(depths > max_depth_ratio * med[:, None, None])
    return ok, count


# ------------------------------------------------ sampling on the BA grid
def sample_at_grid(img: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Values of a full-resolution map (H, W) at the pixel centres of an (h, w) grid
    (bilinear, pixel-centre aligned); 0 where any contributing pixel is 0."""
    H, W = img.shape
    x = img[None, None].to(torch.float32)
    ys = (torch.arange(h, device=img.device, dtype=torch.float32) + 0.5) * (H / h) - 0.5
    xs = (torch.arange(w, device=img.device, dtype=torch.float32) + 0.5) * (W / w) - 0.5
    gy = ys / max(H - 1, 1) * 2 - 1
    gx = xs / max(W - 1, 1) * 2 - 1
    grid = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], -1)[None]
    val = torch.nn.functional.grid_sample(x, grid, mode="bilinear", align_corners=True)
    ok = torch.nn.functional.grid_sample((x > 0).float(), grid, mode="bilinear",
                                         align_corners=True)
    return torch.where(ok > 0.999, val, torch.zeros_like(val))[0, 0]
