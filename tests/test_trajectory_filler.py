"""The full trajectory's filler (tracking/trajectory_filler.py): every input frame gets a pose."""
from __future__ import annotations

import numpy as np
import torch

from splat_slam_ros.tracking.trajectory_filler import FrameRecord, fill_trajectory

H, W = 6, 8
INTR = torch.tensor([8.0, 8.0, 4.0, 3.0])


def _pose(x: float) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = x
    return T


def test_a_frame_whose_keyframe_is_gone_is_placed_as_a_lost_frame():
    # frame 1 was the first keyframe of a warm-up that started again (its keyframe 5 was
    # dropped, never published): it is interpolated in time between the keyframes beside it,
    # as a lost frame is, instead of leaving the trajectory a frame short
    recs = [FrameRecord(0, 1.0, kf_id=0), FrameRecord(1, 1.5, kf_id=5),
            FrameRecord(2, 1.75, lost=True), FrameRecord(3, 2.0, kf_id=1)]
    kf_poses = {0: _pose(0.0), 1: _pose(1.0)}
    disps = {k: torch.ones(H, W) for k in kf_poses}
    ts, P = fill_trajectory(recs, kf_poses, disps, INTR, iters=0)
    np.testing.assert_allclose(ts, [1.0, 1.5, 1.75, 2.0])
    np.testing.assert_allclose(P[:, 0, 3], [0.0, 0.5, 0.75, 1.0], atol=1e-9)
    np.testing.assert_allclose(P[:, :3, :3], np.broadcast_to(np.eye(3), (4, 3, 3)), atol=1e-9)
