"""Global BA (paper Sec. 3.1 "Global BA"): Eq. 1 over a graph of all keyframes.

The graph connects every keyframe to its temporal neighbours (``|i - j| <=
radius``) and to spatial neighbours: keyframes whose current poses and
disparities induce a small mean flow (the GO-SLAM rule the paper follows).
Before optimising, disparities are divided and translations multiplied by the
mean disparity (numerical conditioning, as in the paper); the result is mapped
back to the incoming scale afterwards, so consumers (tracker window, Gaussian
map) never see a gauge change - only the corrections.
"""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import torch

from splat_slam_ros.tracking.dense_ba import BAInfo, bundle_adjust
from splat_slam_ros.tracking.factor_graph import proximity_pairs


def temporal_pairs(ids: Sequence[int], radius: int) -> List[Tuple[int, int]]:
    """Directed pairs between keyframes at most ``radius`` apart in the (sorted) id list."""
    ids = sorted(ids)
    out = []
    for n, a in enumerate(ids):
        for b in ids[n + 1:n + 1 + radius]:
            out += [(a, b), (b, a)]
    return out


def spatial_pairs(ids: Sequence[int], poses: torch.Tensor, disps: torch.Tensor, intr,
                  sources: Sequence[int], radius: int, thresh: float, max_per_kf: int,
                  exclude=()) -> List[Tuple[int, int, float]]:
    """Spatial (non-temporal) neighbour pairs for ``sources`` among ``ids``:
    induced mean flow below ``thresh``, id gap above ``radius``, at most
    ``max_per_kf`` per source keyframe (with non-maximum suppression)."""
    out: List[Tuple[int, int, float]] = []
    excl = set(exclude)
    for s in sources:
        cands = proximity_pairs(ids, poses, disps, intr, [s], thresh, max_per_kf,
                                exclude=excl, min_gap=radius + 1, nms=radius)
        for a, b, d in cands:
            excl.add((a, b))
            out.append((a, b, d))
    return out


def normalized_global_ba(poses: torch.Tensor, disps: torch.Tensor, intr, ii, jj, target,
                         weight, iters: int, fixed: int = 2, huber: Optional[float] = None,
                         rtol: float = 1e-3) -> Tuple[torch.Tensor, torch.Tensor, List[BAInfo]]:
    """Eq. 1 over all keyframes with the mean-disparity normalisation of Sec. 3.1:
    ``d_norm = d / d_mean``, ``t_norm = d_mean t``; BA; then back to the input scale."""
    dbar = float(disps.mean())
    if not (dbar > 0):
        dbar = 1.0
    P = poses.clone()
    P[:, :3, 3] *= dbar
    D = disps / dbar
    P, D, infos = bundle_adjust(P, D, intr, ii, jj, target, weight, iters=iters, fixed=fixed,
                                huber=huber, rtol=rtol)
    P = P.clone()
    P[:, :3, 3] /= dbar
    return P, D * dbar, infos
