"""Depth metrics: the mean absolute depth error (depth L1, cm) of a depth map against a
reference, and the band around the reference's depth discontinuities that splits it into
"at object boundaries" and "on surfaces"."""
from __future__ import annotations

import numpy as np
import torch

from splat_slam_ros.evaluation.inputs import MetricError, as_mask, to_float64


def depth_l1_cm(depth, ref, mask=None) -> float:
    """Mean absolute depth error in cm over pixels valid in both maps (finite and > 0)."""
    d = torch.as_tensor(to_float64(depth, "depth"))
    r = torch.as_tensor(to_float64(ref, "reference depth"))
    d, r = d.squeeze(), r.squeeze()
    if d.shape != r.shape or d.ndim != 2:
        raise MetricError(f"depth maps must both be H x W, got {tuple(d.shape)} and "
                          f"{tuple(r.shape)}")
    valid = torch.isfinite(d) & torch.isfinite(r) & (d > 0) & (r > 0)
    if mask is not None:
        valid &= as_mask(mask, d.shape, d.device)
    if not bool(valid.any()):
        raise MetricError("depth_l1_cm: no pixel has a valid depth in both maps")
    return float(100.0 * (d[valid] - r[valid]).abs().mean())


def _jumps_along_rows(lg: np.ndarray, ok: np.ndarray, jump: float, edge: np.ndarray) -> None:
    """Mark in ``edge`` both pixels of every pair of valid pixels of a row with nothing but
    invalid pixels between them (none for neighbours) whose log depths differ by more than
    ``jump`` per pixel of distance."""
    H, W = lg.shape
    last = np.maximum.accumulate(np.where(ok, np.arange(W)[None, :], -1), axis=1)
    prev = np.concatenate([np.full((H, 1), -1), last[:, :-1]], axis=1)  # previous valid column
    rows, cols = np.nonzero(ok & (prev >= 0))
    pcols = prev[rows, cols]
    hit = np.abs(lg[rows, cols] - lg[rows, pcols]) > jump * (cols - pcols)
    edge[rows[hit], cols[hit]] = True
    edge[rows[hit], pcols[hit]] = True


def depth_edge_band(ref, radius: int, jump: float = 0.05) -> torch.Tensor:
    """(H, W) bool: pixels within ``radius`` px (square window) of a depth discontinuity of
    ``ref``: two valid pixels of a row or column, neighbours or with only invalid pixels
    between them, whose depths differ by more than ``jump`` in log depth (5 %) per pixel of
    distance. The invalid gap matters: depth sensors and many renderers leave no depth on
    the pixels along a silhouette (mixed or occluded pixels), and a test of neighbours only
    would find no edge there. Splits depth errors into "at object boundaries" (where a
    coarse depth bleeds from one surface onto the other) and "on surfaces"."""
    r = to_float64(ref, "reference depth").squeeze()
    if r.ndim != 2:
        raise MetricError(f"reference depth must be H x W, got {tuple(r.shape)}")
    ok = np.isfinite(r) & (r > 0)
    lg = np.log(np.where(ok, r, 1.0))
    edge = np.zeros(r.shape, bool)
    _jumps_along_rows(lg, ok, jump, edge)
    _jumps_along_rows(lg.T, ok.T, jump, edge.T)          # columns (edge.T is a view)
    out = torch.from_numpy(edge)
    if radius > 0:
        k = 2 * int(radius) + 1
        out = torch.nn.functional.max_pool2d(out[None, None].float(), k, 1,
                                             int(radius))[0, 0] > 0
    return out
