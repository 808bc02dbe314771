"""Full trajectory: poses of the non-keyframes (paper Sec. 3.1 / reference "trajectory filler").

Every tracked frame remembers its reference keyframe, the flow from that
keyframe into it (BA grid, stored as float16) and its pose relative to the
keyframe when it was tracked. At the end (or whenever asked) each frame's pose
is initialised from the keyframe's *current* pose (after local BA, loop
closure and global BA) - or, for frames without a usable flow (lost frames),
by interpolation between the neighbouring keyframes in time - and refined by
a short pose-only Gauss-Newton against its flow with the keyframe's current
disparity (the target-pose block of Eq. 1).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.geometry import pixel_grid, se3_exp, se3_inverse, se3_log
from splat_slam_ros.tracking.dense_ba import pose_only_refine_batch


@dataclass
class FrameRecord:
    index: int
    timestamp: float
    kf_id: Optional[int] = None              # set when the frame is a keyframe
    ref_kf: Optional[int] = None             # reference keyframe of a non-keyframe
    rel_pose: Optional[np.ndarray] = None    # T_ref^-1 T_frame when tracked (None: unknown)
    ref_scale: float = 1.0                   # mean disparity of the reference when tracked
    flow: Optional[torch.Tensor] = None      # (h, w, 2) float16, ref -> frame, BA pixels
    weight: Optional[torch.Tensor] = None    # (h, w, 2) float16
    lost: bool = False
    online_pose: Optional[np.ndarray] = None
    ref2_kf: Optional[int] = None            # the next keyframe (set once it exists)
    flow2: Optional[torch.Tensor] = None     # (h, w, 2) float16, ref2 -> frame, BA pixels
    weight2: Optional[torch.Tensor] = None
    skipped: bool = False                    # live input, tracker busy: never tracked (posed
                                             # between its neighbours, _interpolate_skipped)


def se3_interpolate(T0: torch.Tensor, T1: torch.Tensor, a: float) -> torch.Tensor:
    """Geodesic interpolation T0 exp(a log(T0^-1 T1)) of camera-to-world poses."""
    return T0 @ se3_exp(a * se3_log(se3_inverse(T0) @ T1))


def interpolate_from_keyframes(ts: float, kf_ts: np.ndarray, kf_poses: torch.Tensor
                               ) -> torch.Tensor:
    """Pose at time ``ts`` from keyframes sorted by time (clamped at the ends)."""
    n = len(kf_ts)
    k = int(np.searchsorted(kf_ts, ts))
    if k <= 0:
        return kf_poses[0].clone()
    if k >= n:
        return kf_poses[-1].clone()
    t0, t1 = kf_ts[k - 1], kf_ts[k]
    a = 0.0 if t1 <= t0 else float((ts - t0) / (t1 - t0))
    return se3_interpolate(kf_poses[k - 1], kf_poses[k], a)


def fill_trajectory(records: List[FrameRecord], kf_poses: Dict[int, torch.Tensor],
                    kf_disps: Dict[int, torch.Tensor], intr, iters: int = 3,
                    huber: Optional[float] = None) -> Tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and camera-to-world poses (N, 4, 4) of every recorded frame
    that can be placed (frames before the first keyframe pose exist are skipped).
    The non-keyframes' motion-only alignments are solved together
    (:func:`pose_only_refine_batch`)."""
    known = sorted(k for k in kf_poses)
    if not known:
        return np.zeros(0), np.zeros((0, 4, 4))
    by_id = {r.kf_id: r for r in records if r.kf_id is not None}
    # interpolation in time between the keyframes recorded here (a loaded map's keyframes
    # are references of tracked frames but have no time in this input)
    timed = [k for k in known if k in by_id]
    kf_ts = np.array([by_id[k].timestamp for k in timed])
    order = np.argsort(kf_ts)
    kf_ts = kf_ts[order]
    stack = torch.stack([kf_poses[timed[o]].to(torch.float64).cpu() for o in order]) \
        if timed else None
    pose = {k: kf_poses[k].to(torch.float64).cpu() for k in known}
    disp = {k: kf_disps[k].float().cpu() for k in known if k in kf_disps}
    ts_out, poses_out, fit, skipped = [], [], [], []
    for r in records:
        if r.skipped:
            skipped.append(len(poses_out))
            ts_out.append(r.timestamp)
            poses_out.append(None)
            continue
        if r.kf_id is not None:
            if r.kf_id in kf_poses:
                ts_out.append(r.timestamp)
                poses_out.append(pose[r.kf_id])
            continue
        lost = r.lost or r.ref_kf not in pose or r.ref_kf not in disp or r.flow is None
        if stack is None and (lost or r.rel_pose is None):   # nothing to place it by
            continue
        ts_out.append(r.timestamp)
        if lost:
            poses_out.append(interpolate_from_keyframes(r.timestamp, kf_ts, stack))
            continue
        if r.rel_pose is not None:
            rel = torch.as_tensor(r.rel_pose, dtype=torch.float64).clone()
            s_now = float(disp[r.ref_kf].mean())
            if s_now > 0 and r.ref_scale > 0:
                rel[:3, 3] *= r.ref_scale / s_now      # follow a disparity rescale
            T = pose[r.ref_kf] @ rel
        else:
            T = interpolate_from_keyframes(r.timestamp, kf_ts, stack)
        fit.append((len(poses_out), r))
        poses_out.append(T)
    if fit:
        _refine(fit, poses_out, pose, disp, intr, iters, huber)
    if skipped:
        _interpolate_skipped(ts_out, poses_out, skipped, kf_ts, stack)
    return (np.asarray(ts_out, dtype=np.float64),
            torch.stack(poses_out).numpy().astype(np.float64) if poses_out
            else np.zeros((0, 4, 4)))


def _interpolate_skipped(ts_out, poses_out, skipped, kf_ts, kf_stack) -> None:
    """Frames the tracker skipped (live input, busy) take the geodesic interpolation between
    the nearest posed frames before and after them in time (in place); at the ends of the
    trajectory, between the nearest keyframes."""
    ts = np.asarray(ts_out, dtype=np.float64)
    have = np.array([p is not None for p in poses_out])
    known = np.flatnonzero(have)
    kt = ts[known]
    order = np.argsort(kt, kind="stable")
    known, kt = known[order], kt[order]
    for i in skipped:
        k = int(np.searchsorted(kt, ts[i]))
        if 0 < k < len(kt) and kt[k] > kt[k - 1]:
            a = (ts[i] - kt[k - 1]) / (kt[k] - kt[k - 1])
            poses_out[i] = se3_interpolate(poses_out[known[k - 1]], poses_out[known[k]],
                                           float(a))
        elif kf_stack is not None:
            poses_out[i] = interpolate_from_keyframes(float(ts[i]), kf_ts, kf_stack)
        else:                           # no keyframe of this input: the nearest posed frame
            poses_out[i] = poses_out[known[min(k, len(known) - 1)]].clone()


def _refine(fit, poses_out, pose, disp, intr, iters, huber, max_cells: int = 1 << 14):
    """Pose-only alignment (Eq. 1 target block) of the frames in ``fit`` (index into
    ``poses_out``, record) against their reference keyframe and, where it has one, the next
    keyframe (two edges); ``poses_out`` is updated in place. Solved in batches of
    ``max_cells`` BA cells, so the flows are stacked a batch at a time."""
    h, w = fit[0][1].flow.shape[:2]
    grid = pixel_grid(h, w)
    step = max(1, max_cells // (2 * h * w))
    for s in range(0, len(fit), step):
        batch = fit[s:s + step]
        refs, disps, flows, wts, n_it = [], [], [], [], []
        for _i, r in batch:
            two = r.flow2 is not None and r.ref2_kf in pose and r.ref2_kf in disp
            k2 = r.ref2_kf if two else r.ref_kf
            refs.append(torch.stack([pose[r.ref_kf], pose[k2]]))
            disps.append(torch.stack([disp[r.ref_kf], disp[k2]]))
            flows.append(torch.stack([r.flow, r.flow2 if two else r.flow]).float())
            w2 = r.weight2 if two else torch.zeros_like(r.weight)  # a missing edge weighs 0
            wts.append(torch.stack([r.weight, w2]).float())
            n_it.append(iters + (0 if r.rel_pose is not None else 3))
        T = pose_only_refine_batch(torch.stack(refs), torch.stack(disps),
                                   torch.stack([poses_out[i] for i, _ in batch]), intr,
                                   grid + torch.stack(flows), torch.stack(wts),
                                   torch.tensor(n_it), huber=huber)
        for (i, _r), Ti in zip(batch, T):
            poses_out[i] = Ti
