"""Two-view starting point for the initialisation BA (warm-up keyframes, paper Sec. 3.1).

The initialisation BA (Eq. 1 over the warm-up keyframes) starts every pose at the first
keyframe's. With a few degrees of rotation and a sideways step it can settle in the wrong
basin: rotation and translation trade against each other, the residual gets small, and the
first keyframes' wrong relative pose is then held as the gauge for the rest of the run (the
demo's built-in trajectory: the first step 2.4x too long, 5.5 cm ATE). This module gives the
BA a second start: for each warm-up keyframe k, the essential matrix of the flow first -> k
(five-point RANSAC, OpenCV) gives R_k and the direction of t_k; the length of t_k is the
rotation-compensated flow of k relative to the newest keyframe's (the newest gets length 1).
The tracker runs the BA from both starts and keeps the one with the smaller residual.
"""
from __future__ import annotations

from typing import Optional, Sequence

import cv2
import numpy as np
import torch

from splat_slam_ros.tracking.motion_filter import flow_correspondences

MIN_CELLS = 30             # confident cells needed for an essential matrix
MIN_INLIER_FRAC = 0.5      # of them consistent with it (RANSAC), and in front of both cameras


def relative_motion(flow: torch.Tensor, weight: torch.Tensor, K: np.ndarray,
                    cell_weight: float = 0.2, thresh_px: float = 0.3):
    """(R, t_unit, parallax) of a second view from the flow first -> second (BA pixels) with
    X_2 = R X_1 + t, or None when the flow does not determine it (too few confident cells,
    no essential matrix with enough inliers in front of both cameras). ``parallax``: median
    flow left after removing the rotation's (K R K^-1), the translation's share."""
    src, dst = (x.astype(np.float64) for x in flow_correspondences(flow, weight, cell_weight))
    if len(src) < MIN_CELLS:
        return None
    E, inl = cv2.findEssentialMat(src, dst, K, method=cv2.RANSAC, prob=0.999,
                                  threshold=thresh_px)
    if E is None or E.shape[0] < 3:
        return None
    E = E[:3]                                   # several solutions: the first (best) one
    n_good, R, t, mask = cv2.recoverPose(E, src, dst, K, mask=inl.copy())
    if n_good < MIN_INLIER_FRAC * len(src):
        return None
    H = K @ R @ np.linalg.inv(K)                # flow of the rotation alone
    p = np.concatenate([src, np.ones((len(src), 1))], 1) @ H.T
    p = p[:, :2] / p[:, 2:]
    par = float(np.median(np.linalg.norm(dst - p, axis=1)))
    return R, t.reshape(3), par


def two_view_start(flows: Sequence[torch.Tensor], weights: Sequence[torch.Tensor],
                   intr: torch.Tensor, cell_weight: float = 0.2) -> Optional[torch.Tensor]:
    """Camera-to-world start poses (n+1, 4, 4), float64, for the first keyframe (identity) and
    the n keyframes whose flows from the first are ``flows`` (each (h, w, 2) BA px, weights
    (h, w, 2)); ``intr`` = (fx, fy, cx, cy) at BA resolution. A view whose motion the flow does
    not determine starts at the previous view's pose. Translations are scaled so that the view
    with the most parallax moves by 1. None when no view is determined (then the BA starts
    from the identity only)."""
    fx, fy, cx, cy = (float(x) for x in intr)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)
    motions = [relative_motion(f, w, K, cell_weight) for f, w in zip(flows, weights)]
    pars = [m[2] for m in motions if m is not None]
    if not pars or max(pars) <= 0:
        return None
    out = [np.eye(4)]
    for m in motions:
        if m is None:
            out.append(out[-1].copy())
            continue
        R, t, par = m
        T = np.eye(4)                           # first -> k (world = the first camera)
        T[:3, :3], T[:3, 3] = R, t * (par / max(pars))
        out.append(np.linalg.inv(T))
    return torch.from_numpy(np.stack(out))
