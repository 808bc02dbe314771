"""Loop closure and global BA (paper Sec. 3.1) on a synthetic closed path of keyframes."""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
import pytest
import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.geometry import se3_exp, se3_inverse
from splat_slam_ros.types import KeyframeData, UpdateEvent

from test_tracker import INTR, render_room, small_cfg

N_KF = 32


def loop_poses(n: int = N_KF) -> np.ndarray:
    """Camera-to-world poses on a closed ellipse, looking at the far wall."""
    a = 2 * np.pi * np.arange(n) / n
    xi = np.zeros((n, 6))
    xi[:, 0] = 0.45 * np.cos(a) - 0.45
    xi[:, 1] = 0.3 * np.sin(a)
    xi[:, 2] = 0.1 * np.sin(2 * a)
    xi[:, 4] = 0.12 * np.sin(a)              # yaw follows the path a little
    xi[:, 3] = 0.05 * np.cos(a)
    return se3_exp(torch.from_numpy(xi)).numpy()


@lru_cache(maxsize=1)
def loop_keyframes():
    """Images, true poses and true disparities (BA grid 40x30) around the loop."""
    poses = loop_poses()
    out = []
    for k, P in enumerate(poses):
        img, depth = render_room(P, INTR)
        disp = 1.0 / cv2.resize(depth, (40, 30), interpolation=cv2.INTER_AREA)
        out.append((img, P, disp.astype(np.float32)))
    return out


def drifted(poses: np.ndarray, rot_deg=0.25, trans=0.004, scale=0.004) -> np.ndarray:
    """Accumulate a per-keyframe error (rotation, translation and scale drift)."""
    out = [poses[0]]
    rng = np.random.default_rng(0)
    d = np.array([trans, -trans, trans / 2, 0.0, np.radians(rot_deg), 0.0])
    for k in range(1, len(poses)):
        rel = se3_inverse(torch.from_numpy(poses[k - 1])) @ torch.from_numpy(poses[k])
        rel = rel.numpy().copy()
        rel[:3, 3] *= 1 + scale
        noise = se3_exp(torch.from_numpy(d + rng.normal(0, 1e-4, 6))).numpy()
        out.append(out[-1] @ rel @ noise)
    return np.stack(out)


def keyframe(k: int, pose: np.ndarray, data) -> KeyframeData:
    img, _, disp = data[k]
    return KeyframeData(kf_id=k, frame_index=10 * k, timestamp=k / 3.0, pose=pose, image=img,
                        intrinsics=INTR, disparity=disp, confidence=np.ones_like(disp))


def loop_cfg(**kw) -> SlamConfig:
    ref = 65.625 / 28.0          # flow thresholds in reference BA px: 8 and 6 BA px here
    cfg = small_cfg(loop_closure=True, global_ba=True, loop_time_gap=8, loop_window=6,
                    loop_nms=3, loop_flow_thresh=8.0 * ref, global_ba_every=1000,
                    global_ba_thresh=6.0 * ref, global_ba_max_edges=4, final_ba_iters=(4, 6))
    for k, v in kw.items():
        setattr(cfg.tracking, k, v)
    return cfg


def ate(est: np.ndarray, gt: np.ndarray) -> float:
    from splat_slam_ros.evaluation.trajectory import ate as ate_fn
    ts = np.arange(len(gt), dtype=np.float64)
    return ate_fn(ts, gt, ts, est)["rmse_cm"]


def end_gap_cm(P: np.ndarray, gt: np.ndarray) -> float:
    """Error of the last keyframe's position relative to the first (after scale alignment)."""
    from splat_slam_ros.evaluation.trajectory import umeyama_alignment
    s, _, _ = umeyama_alignment(P[:, :3, 3], gt[:, :3, 3])
    rel = np.linalg.inv(P[0]) @ P[-1]
    relg = np.linalg.inv(gt[0]) @ gt[-1]
    return float(np.linalg.norm(s * rel[:3, 3] - relg[:3, 3]) * 100)


def test_loop_edges_detected_on_a_revisit():
    from splat_slam_ros.tracking.loop_closure import LoopCloser
    data = loop_keyframes()
    gt = np.stack([d[1] for d in data])
    est = drifted(gt)
    lc = LoopCloser(loop_cfg(global_ba=False), INTR)
    events = []
    first_loop_at = None
    for k in range(N_KF):
        lc.add_keyframe(keyframe(k, est[k], data))
        ev = lc.step()
        if ev and first_loop_at is None:
            first_loop_at = k
        events += ev
    assert lc.loop_pairs, "no loop edge found"
    for a, o in lc.loop_pairs:
        assert a - o > 8                                     # the time-gap criterion
    # the revisit: the last keyframes close onto the first ones
    assert any(a >= N_KF - 4 and o <= 4 for a, o in lc.loop_pairs)
    assert all(e.reason == "loop_closure" for e in events)
    assert first_loop_at is not None and first_loop_at > 8


def test_global_ba_reduces_drift_on_a_loop():
    from splat_slam_ros.tracking.loop_closure import LoopCloser
    data = loop_keyframes()
    gt = np.stack([d[1] for d in data])
    est = drifted(gt)
    before = ate(est, gt)
    lc = LoopCloser(loop_cfg(loop_closure=False), INTR)
    for k in range(N_KF):
        lc.add_keyframe(keyframe(k, est[k], data))
        assert lc.step() == []                 # online global BA not due (every 1000)
    events = lc.finalize()
    assert events and events[-1].reason == "final"
    _, P = lc.trajectory_keyframes()
    after = ate(P, gt)
    assert after < 0.5 * before, f"ATE {before:.2f} -> {after:.2f} cm"
    # the loop's end-to-start gap (Sim(3)-aligned) shrinks most
    assert end_gap_cm(P, gt) < 0.35 * end_gap_cm(est, gt)


def test_loop_closer_events_list_exactly_the_changed_keyframes():
    from splat_slam_ros.geometry import se3_log
    from splat_slam_ros.tracking.loop_closure import LoopCloser
    data = loop_keyframes()
    gt = np.stack([d[1] for d in data])
    est = gt.copy()
    est[12:16] = drifted(gt[12:16], rot_deg=0.5, trans=0.01)   # only the tail is off
    cfg = loop_cfg()
    tc = cfg.tracking
    lc = LoopCloser(cfg, INTR)
    for k in range(16):
        lc.add_keyframe(keyframe(k, est[k], data))
    snap = {k: (lc.kfs[k].pose.clone(), lc.kfs[k].disp.clone()) for k in lc.kfs.ids}
    events = lc.global_ba(3)
    assert len(events) == 1
    ev = events[0]
    assert ev.reason == "global_ba" and ev.disparities.shape == (len(ev.kf_ids), 30, 40)
    listed = set(ev.kf_ids)
    assert {12, 13, 14, 15} <= listed
    for k in lc.kfs.ids:
        P0, D0 = snap[k]
        dxi = se3_log(se3_inverse(P0) @ lc.kfs[k].pose)
        scale = 1.0 / float(lc.kfs[k].disp.mean())
        pose_change = max(float(dxi[:3].norm()) / scale, float(dxi[3:].norm()))
        disp_change = float((lc.kfs[k].disp - D0).abs().mean() / D0.abs().mean())
        changed = pose_change > tc.event_pose_thresh or disp_change > tc.event_disp_thresh
        assert (k in listed) == changed, (k, pose_change, disp_change)
        if k in listed:
            n = ev.kf_ids.index(k)
            assert np.allclose(ev.poses[n], lc.kfs[k].pose.numpy())
            assert np.allclose(ev.disparities[n], lc.kfs[k].disp.numpy())
    for k in (0, 1):                                   # the gauge: poses fixed
        assert torch.allclose(lc.kfs[k].pose, snap[k][0], atol=1e-9)


def test_tracker_applies_loop_events_and_moves_later_keyframes_rigidly():
    from splat_slam_ros.tracking.keyframe_set import KeyframeState
    from splat_slam_ros.tracking.tracker import Tracker
    tr = Tracker(small_cfg(), INTR)
    eye = np.eye(4)
    for k in range(4):
        T = eye.copy()
        T[0, 3] = 0.1 * k
        tr.kfs.add(k, KeyframeState(torch.from_numpy(T), torch.ones(30, 40), k, 0.1 * k))
        tr.published.add(k)
    tr.last_pose = tr.kfs[3].pose.clone()
    corr = se3_exp(torch.tensor([0.0, 0.05, 0.0, 0.0, 0.02, 0.0], dtype=torch.float64)).numpy()
    new1 = corr @ tr.kfs[1].pose.numpy()
    tr.apply_update(UpdateEvent(seq=5, reason="loop_closure", kf_ids=[1], poses=new1[None],
                                disparities=np.full((1, 30, 40), 2.0, np.float32)))
    assert np.allclose(tr.kfs[1].pose.numpy(), new1)
    assert float(tr.kfs[1].disp.mean()) == pytest.approx(2.0)
    assert np.allclose(tr.kfs[0].pose.numpy(), eye)                     # older: untouched
    for k in (2, 3):                                                 # newer: same correction
        T = eye.copy()
        T[0, 3] = 0.1 * k
        assert np.allclose(tr.kfs[k].pose.numpy(), corr @ T, atol=1e-9)
    assert np.allclose(tr.last_pose.numpy(), tr.kfs[3].pose.numpy())


def test_revisits_merge_into_older_keyframes_and_follow_them():
    """Two passes around the same loop: the second pass's keyframes, once settled, merge
    into the first pass's (the BA graph stays at about one pass), every keyframe keeps a
    pose in the trajectory, and merged ones follow their anchor through later updates."""
    from splat_slam_ros.tracking.keyframe_merge import components
    from splat_slam_ros.tracking.loop_closure import LoopCloser
    data = loop_keyframes()
    gt = np.stack([d[1] for d in data])
    est = np.concatenate([gt, drifted(gt, rot_deg=0.05, trans=0.001)])
    lc = LoopCloser(loop_cfg(global_ba_every=8, loop_closure=False), INTR)   # spatial edges
    events = []
    for k in range(2 * N_KF):
        img, _, disp = data[k % N_KF]
        lc.add_keyframe(KeyframeData(kf_id=k, frame_index=10 * k, timestamp=k / 3.0,
                                     pose=est[k], image=img, intrinsics=INTR, disparity=disp,
                                     confidence=np.ones_like(disp)))
        events += lc.step()
    assert len(lc.merged) >= N_KF // 2, sorted(lc.merged)
    assert len(lc.kfs) + len(lc.merged) == 2 * N_KF
    assert all(m.anchor < k and m.anchor in lc.kfs for k, m in lc.merged.items())
    assert components(lc.graph.pairs(), lc.kfs.ids) == 1
    assert not any(k in p for k in lc.merged for p in lc.graph.pairs())
    follower_events = [e for e in events if e.disparities is None]
    assert follower_events and all(set(e.kf_ids) <= set(lc.merged) for e in follower_events)
    events = lc.finalize()
    ts, P = lc.trajectory_keyframes()
    assert len(ts) == 2 * N_KF and np.allclose(ts, np.arange(2 * N_KF) / 3.0)
    gt2 = np.concatenate([gt, gt])
    assert ate(P, gt2) < 1.0, ate(P, gt2)
    # merged keyframes sit where their anchor and the frozen relative pose put them
    for k, m in lc.merged.items():
        assert np.allclose(P[k], (lc.kfs[m.anchor].pose @ m.rel).numpy(), atol=1e-9)
    # ... and the last update that lists a merged keyframe carries exactly that pose
    last = {}
    for e in events:
        for n, k in enumerate(e.kf_ids):
            last[k] = e.poses[n]
    moved = [k for k in lc.merged if k in last]
    for k in moved:
        assert np.allclose(last[k], P[k], atol=1e-9)


def test_splits_and_merge_rules():
    from splat_slam_ros.tracking.keyframe_merge import merge_candidates, splits
    chain = [(0, 1), (1, 2), (2, 3), (3, 1)]
    assert not splits(chain, [0, 1, 2, 3], 3)
    assert splits(chain, [0, 1, 2, 3], 1)                       # 0 would be cut off
    # a graph already in two pieces (a tracking gap no edge bridged): each piece's own
    # cut vertices are still found, and a removable keyframe is still removable
    two = chain + [(5, 6), (6, 7), (7, 5), (7, 8)]
    assert not splits(two, [0, 1, 2, 3, 5, 6, 7, 8], 3)
    assert not splits(two, [0, 1, 2, 3, 5, 6, 7, 8], 6)
    assert splits(two, [0, 1, 2, 3, 5, 6, 7, 8], 7)             # 8 would be cut off
    assert not splits(two, [0, 1, 2, 3, 4, 5, 6, 7, 8], 4)     # an isolated keyframe
    poses = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
    poses[4, 0, 3] = 0.5                                        # 4 is far from the others
    disps = torch.ones(5, 6, 8)
    intr = torch.tensor([8.0, 8.0, 4.0, 3.0])
    kinds = {(3, 0): "global", (4, 1): "loop", (2, 1): "odometry", (1, 0): "odometry"}
    # settled = all but the newest keyframe (settle=1): 3 -> 0 qualifies (same pose,
    # measured spatial edge); 4 is not settled; 2 -> 1 is only a temporal edge
    assert [(k, o) for k, o, _ in merge_candidates(range(5), poses, disps, intr, kinds, 1, 1.0)] \
        == [(3, 0)]
    assert merge_candidates(range(5), poses, disps, intr, kinds, 1, 0.0) == []
    # the measured edge ties 3 to the older map (here to the far keyframe 1); it merges into
    # the older keyframe nearest by induced flow, which no edge joins to it (0 and 2 tie: 0)
    poses[1, 0, 3] = 0.5
    kinds = {(3, 1): "loop", (2, 1): "odometry", (1, 0): "odometry"}
    assert [(k, o) for k, o, _ in merge_candidates(range(5), poses, disps, intr, kinds, 1, 1.0)] \
        == [(3, 0)]
    # nothing but temporal edges: no keyframe is tied to the older map, none merges
    kinds = {(3, 2): "odometry", (2, 1): "odometry", (1, 0): "odometry"}
    assert merge_candidates(range(5), poses, disps, intr, kinds, 1, 1.0) == []
