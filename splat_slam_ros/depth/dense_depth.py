"""Dense multi-view proxy depth at processing resolution (§3.2, Eq. 4-6 per pixel).

The tracker's BA disparity lives on a 1/8 grid (40x30 at 320x240) and is often several
centimetres off; the keyframe poses are much better (ATE well under 1 cm). This module
triangulates a depth for every pixel of a keyframe from dense optical flow (OpenCV DIS)
towards a few neighbouring keyframes, using the BA poses, and keeps a pixel only where at
least ``min_views`` views agree on its depth - the multi-view consistency filter of Eq. 6,
evaluated at the processing resolution instead of the BA grid.

* :func:`dense_flow`: DIS flow between two grey images (OpenCV, CPU).
* :func:`triangulate_flow`: depth along the rays of view i from a flow i -> k and the
  relative pose (linear two-view triangulation), with the parallax angle of every pixel.
* :func:`fuse_views`: per-pixel agreement of the per-view depths (Eq. 6: count of views
  within ``eta`` x depth of the parallax-weighted median) and their weighted mean.
* :func:`select_views`: which neighbours to use (largest baseline / depth ratio, capped).
* :class:`FlowCache`: flows do not depend on the poses, so BA updates reuse them.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Optional, Sequence, Tuple

import cv2
import numpy as np
import torch

from splat_slam_ros.geometry import intr_tensor, se3_inverse


_DIS = {}


def dense_flow(grey_a: np.ndarray, grey_b: np.ndarray) -> np.ndarray:
    """DIS optical flow a -> b (medium preset): (H, W, 2) float32, pixel a + flow = pixel b."""
    dis = _DIS.get("medium")
    if dis is None:
        dis = _DIS["medium"] = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(grey_a, grey_b, None)


@torch.no_grad()
def triangulate_flow(flow: torch.Tensor, pose_i: torch.Tensor, pose_k: torch.Tensor, intr
                     ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Depth (z in camera i) of every pixel of view i from its flow to view k.

    flow (H, W, 2) (u + flow = matched pixel in k); poses 4x4 camera-to-world; intr
    (fx, fy, cx, cy) of the (H, W) image. With r the ray of i, m the matched ray of k and
    (R, t) camera i -> camera k, the point R d r + t must lie on m: d (m x Rr) = -(m x t),
    solved in least squares, d = -(m x Rr).(m x t) / |m x Rr|^2. Returns (depth (H, W), 0
    where the point is behind either camera or the match leaves image k; parallax (H, W)
    angle in radians between the two rays, 0 where invalid).
    """
    H, W = flow.shape[:2]
    dev = flow.device
    K = [float(v) for v in intr_tensor(intr, torch.float64)]
    rel = (se3_inverse(pose_k.to(dev, torch.float64)) @ pose_i.to(dev, torch.float64))
    R, t = rel[:3, :3].tolist(), rel[:3, 3].tolist()
    x = ((torch.arange(W, device=dev, dtype=torch.float32) - K[2]) / K[0])[None, :]
    y = ((torch.arange(H, device=dev, dtype=torch.float32) - K[3]) / K[1])[:, None]
    a1, a2, a3 = (R[j][0] * x + R[j][1] * y + R[j][2] for j in range(3))   # R r
    fl = flow.float()
    mx = x + fl[..., 0] / K[0]                                              # matched ray m
    my = y + fl[..., 1] / K[1]
    c1, c2, c3 = my * a3 - a2, a1 - mx * a3, mx * a2 - my * a1               # m x Rr
    e1, e2, e3 = my * t[2] - t[1], t[0] - mx * t[2], mx * t[1] - my * t[0]   # m x t
    den = c1 * c1 + c2 * c2 + c3 * c3
    d = -(c1 * e1 + c2 * e2 + c3 * e3) / den.clamp_min(1e-12)
    zk = d * a3 + t[2]
    uk = mx * K[0] + K[2]
    vk = my * K[1] + K[3]
    inside = (uk >= 0) & (uk <= W - 1) & (vk >= 0) & (vk <= H - 1)
    ok = torch.isfinite(d) & (d > 0) & (zk > 0) & inside & (den > 1e-12)
    sin_par = torch.sqrt(den / ((mx * mx + my * my + 1) * (a1 * a1 + a2 * a2 + a3 * a3)))
    par = torch.asin(sin_par.clamp(0, 1))
    return torch.where(ok, d, torch.zeros_like(d)), torch.where(ok, par, torch.zeros_like(par))


@torch.no_grad()
def fuse_views(depths: torch.Tensor, parallax: torch.Tensor, eta: float, min_views: int,
               min_parallax: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """Multi-view agreement of per-view depths (Eq. 6 per pixel).

    depths, parallax (V, H, W) from :func:`triangulate_flow`; views with parallax below
    ``min_parallax`` (radians) are not used at that pixel. Every usable view is a candidate
    reference; a view agrees with it when within ``eta`` x its depth. The reference is the
    candidate with the largest parallax^2-weighted agreement (depth error ~ 1 / parallax);
    a pixel is valid with ``>= min_views`` views agreeing with it and takes their
    parallax^2-weighted mean. Returns (depth (H, W), 0 = invalid; count (H, W) int32).
    """
    use = (depths > 0) & (parallax >= min_parallax)
    w = torch.where(use, parallax * parallax, torch.zeros_like(parallax))
    d = torch.where(use, depths, torch.zeros_like(depths))
    best = torch.full_like(d[0], -1.0)
    sel = torch.zeros_like(use)
    for a in range(d.shape[0]):             # Eq. 6 per pixel: views agreeing with candidate a
        agree_a = use & ((d - d[a]).abs() <= eta * d[a])
        score = torch.where(use[a], (w * agree_a).sum(0), torch.full_like(best, -1.0))
        better = score > best
        best = torch.where(better, score, best)
        sel = torch.where(better, agree_a, sel)
    count = sel.sum(0).to(torch.int32)
    ws = w * sel
    fused = (ws * d).sum(0) / ws.sum(0).clamp_min(1e-12)
    ok = count >= int(min_views)
    return torch.where(ok, fused, torch.zeros_like(fused)), count


def select_views(pose: np.ndarray, candidates: Sequence[Tuple[int, np.ndarray]],
                 depth: float, n: int, max_ratio: float = 0.5) -> list:
    """Up to ``n`` candidate ids with the largest baseline / ``depth`` ratio (more parallax,
    smaller depth error), skipping those beyond ``max_ratio`` (little overlap, large flow).
    candidates: (kf_id, 4x4 camera-to-world)."""
    c = np.asarray(pose, np.float64)[:3, 3]
    scored = []
    for k, P in candidates:
        ratio = float(np.linalg.norm(np.asarray(P, np.float64)[:3, 3] - c)) / max(depth, 1e-6)
        if ratio <= max_ratio:
            scored.append((ratio, k))
    scored.sort(reverse=True)
    return [k for _, k in scored[: max(0, int(n))]]


_REUSE = 1e-3     # pose change (rad; fraction of the depth) below which a result is reused


class FlowCache:
    """LRU of flows (i, k) -> (H, W, 2) float16; a flow depends on the two images only."""

    def __init__(self, capacity: int = 128):
        self.capacity = int(capacity)
        self._d: "OrderedDict[Tuple[int, int], np.ndarray]" = OrderedDict()

    def get(self, i: int, k: int, grey_i: np.ndarray, grey_k: np.ndarray) -> np.ndarray:
        key = (int(i), int(k))
        f = self._d.get(key)
        if f is None:
            f = dense_flow(grey_i, grey_k).astype(np.float16)
            self._d[key] = f
            while len(self._d) > self.capacity:
                self._d.popitem(last=False)
        else:
            self._d.move_to_end(key)
        return f

    def drop(self, kf_id: int) -> None:
        for key in [key for key in self._d if int(kf_id) in key]:
            del self._d[key]

    def __len__(self) -> int:
        return len(self._d)


@torch.no_grad()
def dense_depth(grey: np.ndarray, pose: np.ndarray, views: Sequence[Tuple[int, np.ndarray,
                np.ndarray]], intr, eta: float, min_views: int, min_parallax: float,
                cache: Optional[FlowCache] = None, kf_id: int = -1,
                device=None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Dense depth of one keyframe (grey (H, W) uint8, pose 4x4 c2w) from ``views``
    (kf_id, grey, pose): flow to each view, triangulation, :func:`fuse_views`. Returns
    (depth (H, W) float32, 0 = none; count (H, W) int32)."""
    H, W = grey.shape
    dev = torch.device("cpu") if device is None else torch.device(device)
    if len(views) == 0:
        return torch.zeros(H, W, device=dev), torch.zeros(H, W, dtype=torch.int32, device=dev)
    Ti = torch.as_tensor(np.asarray(pose, np.float64), device=dev)
    ds, ps = [], []
    for k, g, P in views:
        f = cache.get(kf_id, k, grey, g) if cache is not None else dense_flow(grey, g)
        d, p = triangulate_flow(torch.from_numpy(np.asarray(f, np.float32)).to(dev), Ti,
                                torch.as_tensor(np.asarray(P, np.float64), device=dev), intr)
        ds.append(d)
        ps.append(p)
    return fuse_views(torch.stack(ds), torch.stack(ps), eta, min_views, min_parallax)


class DenseProxy:
    """The dense depth of the proxy-depth estimator: view selection, flow cache, and the
    last result per keyframe, reused while BA updates move its poses by less than
    ``_REUSE``. ``dc``: the ``depth`` config section (``dense_*`` fields)."""

    def __init__(self, dc, intr, keep: int = 32):
        self.dc, self.intr, self.keep = dc, intr, int(keep)
        self.flows = FlowCache(capacity=24 * max(1, int(dc.dense_views)))
        self._last: "OrderedDict[int, tuple]" = OrderedDict()   # k: (views, poses, d, count)

    def drop(self, kf_id: int) -> None:
        """Forget a keyframe (evicted, or a new image for it)."""
        self.flows.drop(kf_id)
        self._last.pop(int(kf_id), None)

    def _depth(self, k, grey, pose, views, med, device):
        dc = self.dc
        sel = [v[0] for v in views]
        poses = np.stack([pose] + [v[2] for v in views])
        old = self._last.get(k)
        if old is not None and old[0] == sel and \
                np.abs(old[1][:, :3, :3] - poses[:, :3, :3]).max() < _REUSE and \
                np.abs(old[1][:, :3, 3] - poses[:, :3, 3]).max() < _REUSE * med:
            self._last.move_to_end(k)
            return old[2], old[3]
        n_min = max(1, min(dc.dense_min_views, dc.dense_fill_views or dc.dense_min_views))
        dd, cnt = dense_depth(grey, pose, views, self.intr, dc.dense_eta, n_min,
                              np.radians(dc.dense_min_parallax_deg), self.flows, k, device)
        if dc.mv_max_depth_ratio > 0:                         # the Eq. 6 outlier bound
            dd = torch.where(dd <= dc.mv_max_depth_ratio * med, dd, torch.zeros_like(dd))
        self._last[k] = (sel, poses, dd, cnt)
        while len(self._last) > self.keep:
            self._last.popitem(last=False)
        return dd, cnt

    @torch.no_grad()
    def apply(self, k: int, grey: np.ndarray, pose: np.ndarray, cands, med: float,
              mv_depth: torch.Tensor, mv_valid: torch.Tensor
              ) -> Tuple[torch.Tensor, torch.Tensor]:
        """Keyframe ``k`` (grey image, pose, BA median depth ``med``) against candidate views
        (kf_id, grey, pose): where ``dense_min_views`` views agree the dense depth replaces
        ``mv_depth`` (the BA-grid depth), where ``dense_fill_views`` agree it fills its holes.
        Returns (depth, valid)."""
        dc = self.dc
        sel = select_views(pose, [(c[0], c[2]) for c in cands], med, dc.dense_views) \
            if med > 0 else []
        if not sel:
            return mv_depth, mv_valid
        byid = {c[0]: c for c in cands}
        dd, cnt = self._depth(int(k), grey, pose, [byid[n] for n in sel], med,
                              mv_depth.device)
        use = (cnt >= max(1, dc.dense_min_views)) & (dd > 0)
        if dc.dense_fill_views > 0:
            use |= (cnt >= dc.dense_fill_views) & (dd > 0) & ~mv_valid
        return torch.where(use, dd, mv_depth), mv_valid | use
