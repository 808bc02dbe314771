"""KeyframeSet: the one keyframe store of the tracker and the loop closer."""
import numpy as np
import torch

from splat_slam_ros.geometry import se3_exp
from splat_slam_ros.tracking.keyframe_set import KeyframeSet, KeyframeState


def state(k, disp=1.0):
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = 0.1 * k
    return KeyframeState(T, torch.full((3, 4), disp), frame_index=10 * k, timestamp=0.5 * k,
                         prep=f"prep{k}", image=np.zeros((6, 8, 3), np.uint8))


def test_ids_sorted_and_records_drop_independently():
    ks = KeyframeSet()
    for k in (3, 0, 2, 1):
        ks.add(k, state(k))
    assert ks.ids == [0, 1, 2, 3] and list(ks) == [0, 1, 2, 3] and len(ks) == 4
    ks.drop_prep(1)
    ks.drop_image(2)
    assert ks.with_prep() == [0, 2, 3] and ks.with_image() == [0, 1, 3]
    assert 1 in ks and ks[1].image is not None
    ks.remove(2)
    assert ks.ids == [0, 1, 3] and 2 not in ks
    ts, P = ks.trajectory(ks.ids)
    assert np.allclose(ts, [0.0, 0.5, 1.5]) and np.allclose(P[:, 0, 3], [0.0, 0.1, 0.3])
    ks.clear()
    assert len(ks) == 0 and ks.trajectory([])[1].shape == (0, 4, 4)


def test_stack_write_back_and_changed_thresholds():
    ks = KeyframeSet()
    for k in range(4):
        ks.add(k, state(k, disp=2.0))
    before = ks.snapshot(ks.ids)
    P, D = ks.stack(ks.ids)
    assert P.shape == (4, 4, 4) and D.shape == (4, 3, 4)
    P = P.clone()
    D = D.clone()
    P[1] = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.01, 0.0], dtype=torch.float64)) @ P[1]
    D[2] = D[2] * 1.05                                   # 5 % disparity change
    P[3, 0, 3] += 1e-7                                   # below the pose threshold
    ks.write_back(ks.ids, P, D)
    assert torch.equal(before[1][0], state(1).pose)      # the snapshot is a copy
    assert ks.changed(before, pose_thresh=1e-4, disp_thresh=1e-3) == [1, 2]
    assert ks.changed(before, pose_thresh=0.1, disp_thresh=0.1) == []
    ev = ks.update_event(7, "global_ba", [1, 2])
    assert ev.seq == 7 and ev.reason == "global_ba" and ev.kf_ids == [1, 2]
    assert np.allclose(ev.poses[0], P[1].numpy()) and ev.disparities.dtype == np.float32
    assert np.allclose(ev.disparities[1], 2.1)
