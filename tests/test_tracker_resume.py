"""Tracker checkpoints (splat_slam_ros/tracking/tracker_state.py): a TrackerRole dropped
mid-sequence (as kill -9 would) and rebuilt on its store continues the same run."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from splat_slam_ros.io.keyframe_store import KeyframeStore
from splat_slam_ros.roles import TrackerRole
from splat_slam_ros.types import LOOP_SEQ_START, UpdateEvent

from test_tracker import INTR, ate_cm, sequence, small_cfg


def _feed(role, frames, seqs, kf_ids):
    for f in frames:
        _step, out = role.on_frame(f)
        seqs += [e.seq for e in out.updates]
        kf_ids += [k.kf_id for k in out.keyframes]


@pytest.mark.parametrize("map_size", [None, (80, 60)])
def test_tracker_resumes_from_its_checkpoint_like_an_uninterrupted_run(tmp_path, map_size):
    """``map_size``: keyframes handed on (and checkpointed) at a smaller mapping size than
    the tracking size; the restored window prepares its flow inputs from those images."""
    frames, gt = sequence()
    cfg = small_cfg(frontend_window=5)                 # keyframes leave the window
    if map_size is not None:
        cfg.camera.width, cfg.camera.height = map_size
        cfg.tracking.max_pixels = 0                    # tracking at the input size, 160x120
    W, H = map_size or (INTR.width, INTR.height)
    ref = TrackerRole(cfg, INTR, loop_closure=False)
    ref_seqs, ref_kfs = [], []
    _feed(ref, frames, ref_seqs, ref_kfs)
    ref.finalize()
    n_ref = len(ref.tracker.published)

    store_dir = tmp_path / "tracker"
    a = TrackerRole(cfg, INTR, False, store=KeyframeStore(store_dir))
    assert not a.resumed and a.resume_stamp is None
    early = TrackerRole(cfg, INTR, False, store=KeyframeStore(store_dir))   # crash in warm-up:
    assert not early.resumed and early.resume_stamp is None                # from frame 0 again
    assert TrackerRole.stored_intrinsics(KeyframeStore(store_dir)).width == INTR.width
    seqs, kfs = [], []
    _feed(a, frames[:31], seqs, kfs)
    assert kfs, "the first part must publish keyframes"
    # a loop closer's update reaches the tracker (and its checkpoint) before the crash
    k0 = kfs[0]
    ev = UpdateEvent(seq=LOOP_SEQ_START, reason="global_ba", kf_ids=[k0],
                     poses=a.tracker.kfs[k0].pose.cpu().numpy()[None].copy(), disparities=None)
    a.on_update(ev)
    a_records = list(a.tracker.records)
    a_causes = {k: a.tracker.kfs[k].cause for k in a.tracker.kfs}
    del a                                              # "kill -9": nothing else is written

    two_sided = {r.index: r.ref2_kf for r in a_records if r.ref2_kf is not None}
    b = TrackerRole(cfg, INTR, False, store=KeyframeStore(store_dir))
    assert b.resumed and b.loop_seq == LOOP_SEQ_START
    # non-keyframes aligned against both keyframes keep their second flow (the filler's)
    restored = {r.index: r for r in b.tracker.records}
    assert two_sided and all(restored[i].ref2_kf == k and restored[i].flow2 is not None
                             for i, k in two_sided.items() if i in restored)
    stamp = b.resume_stamp
    assert stamp is not None and stamp <= frames[30].timestamp
    assert b.tracker.next_kf == max(kfs) + 1 and set(b.tracker.published) == set(kfs)
    # why each keyframe was made survives (the rate bound counts by it)
    causes = {k: a_causes[k] for k in b.tracker.kfs if k in a_causes}
    assert causes and all(b.tracker.kfs[k].cause == c for k, c in causes.items())
    assert {"warmup", "threshold"} <= set(a_causes.values()), a_causes
    assert TrackerRole.stored_intrinsics(KeyframeStore(store_dir)).fx == INTR.fx
    again = b.resume_outbox()                          # sent again, consumers skip by id / seq
    assert again.keyframes and {k.kf_id for k in again.keyframes} <= set(kfs)
    assert all(k.image.shape[:2] == (H, W) for k in again.keyframes)
    assert all(k.disparity.shape == (30, 40) for k in again.keyframes)
    rest = [f for f in frames if f.timestamp > stamp + 1e-9]
    _feed(b, rest, seqs, kfs)
    b.finalize()
    # new keyframe ids and update numbers continue after the published ones, never reused
    assert kfs == list(range(len(kfs))) and seqs == sorted(set(seqs))
    assert abs(len(b.tracker.published) - n_ref) <= 1
    ts, P = b.tracker.trajectory_full()
    assert np.allclose(np.sort(ts), [f.timestamp for f in frames])      # every frame posed
    path = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    assert ate_cm(frames, gt, ts, P) < 0.03 * path * 100
    # incremental: keyframes that left the window are not written again; a checkpoint
    # without changes rewrites only the small motion-state record
    after = dict(KeyframeStore(store_dir)._records)
    assert not any(n.startswith("timg") and int(n[4:]) < b.tracker.window[0] for n in after)
    b._checkpoint()
    again = KeyframeStore(store_dir)._records
    assert {n for n in after if after[n] != again.get(n)} == {"tstate"}


def test_loop_role_keeps_its_accepted_loop_edges_across_a_restart(tmp_path):
    import torch

    from splat_slam_ros.roles import LoopRole
    from test_loop_closure import N_KF, drifted, keyframe, loop_cfg, loop_keyframes
    data = loop_keyframes()
    est = drifted(np.stack([d[1] for d in data]))
    cfg = loop_cfg(global_ba=False)
    a = LoopRole(cfg, store=KeyframeStore(tmp_path / "loop"))
    for k in range(N_KF):
        a.on_keyframe(keyframe(k, est[k], data))
    pairs = set(a.loop.loop_pairs)
    assert pairs, "no loop edge found"
    edges = {e: v for e, v in a.loop.graph.edges.items() if a.loop.graph.kind[e] == "loop"}
    del a                                                  # "kill -9"
    b = LoopRole(cfg, store=KeyframeStore(tmp_path / "loop"))
    assert b.loop.loop_pairs == pairs and b.loop.n_loops >= len(pairs)
    assert b.loop.checked >= pairs
    for e, (tgt, wgt) in edges.items():                    # the measured flows, not re-measured
        assert b.loop.graph.kind[e] == "loop"
        assert torch.equal(b.loop.graph.edges[e][0].cpu(), tgt.cpu())
        assert torch.equal(b.loop.graph.edges[e][1].cpu(), wgt.cpu())
    # the restarted closer does not look for the same loops again, and its final global BA
    # uses the kept edges
    assert not [c for c in b.loop.detect() if (c[0], c[1]) in pairs]
    b.on_final("tracker", {"last_seq": 0})
    assert b.finalized and set(b.loop.loop_pairs) >= pairs


def test_loop_role_keeps_its_merged_keyframes_across_a_restart(tmp_path):
    """Keyframes the loop closer merged into older views stay merged after a restart (the
    BA graph stays bounded), following the same anchors with the same relative poses."""
    import torch

    from splat_slam_ros.roles import LoopRole
    from test_loop_closure import N_KF, drifted, keyframe, loop_cfg, loop_keyframes
    data = loop_keyframes()
    gt = np.stack([d[1] for d in data])
    est = np.concatenate([gt, drifted(gt, rot_deg=0.05, trans=0.001)])
    cfg = loop_cfg(global_ba_every=8, loop_closure=False)
    a = LoopRole(cfg, store=KeyframeStore(tmp_path / "loop"))
    for k in range(2 * N_KF):
        a.on_keyframe(keyframe(k, est[k], data * 2))
    merged = {k: (m.anchor, m.rel.clone()) for k, m in a.loop.merged.items()}
    assert merged, "nothing merged"
    kept = list(a.loop.kfs.ids)
    del a                                                  # "kill -9"
    b = LoopRole(cfg, store=KeyframeStore(tmp_path / "loop"))
    assert list(b.loop.kfs.ids) == kept
    assert {k: m.anchor for k, m in b.loop.merged.items()} == {k: v[0] for k, v in merged.items()}
    for k, (_, rel) in merged.items():
        assert torch.allclose(b.loop.merged[k].rel.cpu(), rel.cpu(), atol=1e-6)
    assert not any(k in p for k in merged for p in b.loop.graph.pairs())


def _revisit_run(cull_deg: float):
    from splat_slam_ros.config import MappingConfig, SlamConfig
    from splat_slam_ros.mapper_role import MapperRole
    from splat_slam_ros.types import KeyframeData, ProxyDepth
    from test_tracker import render_room
    cfg = SlamConfig()
    cfg.mapping = MappingConfig.fast(iters_first=5, iters_per_keyframe=1, revisit_cull_deg=cull_deg)
    role = MapperRole(cfg)
    xs = [0.0, 0.5, 1.0, 1.5, 1.0, 0.5, 0.0, 0.52]          # there and back (+ a near twin)
    for k, x in enumerate(xs):
        T = np.eye(4)
        T[0, 3] = x
        img, depth = render_room(T, INTR)
        kf = KeyframeData(k, k, float(k), T, img, INTR, np.ones((30, 40), np.float32),
                          np.ones((30, 40), np.float32))
        role.on_keyframe(kf)
        role.on_proxy_depth(ProxyDepth(k, depth, np.ones_like(depth, np.uint8), T, timestamp=k))
    return role


def test_mapper_role_does_not_map_revisits_when_asked():
    off, on = _revisit_run(0.0), _revisit_run(10.0)
    assert sorted(off.offered) == sorted(on.offered) == list(range(8))   # all consumed
    assert sum(off.offered.values()) >= 6                 # the window rules map the way back
    assert [k for k, m in on.offered.items() if m] == [0, 1, 2, 3]       # revisits are not
    assert len(on.mapper.keyframes) == 4


def test_revisit_mode_does_not_map_a_view_the_map_already_covers():
    """A keyframe whose pose is too far from every mapped one for the pose test (drift, or
    a step forward) but whose view the map already covers is consumed, not mapped."""
    from splat_slam_ros.config import MappingConfig, SlamConfig
    from splat_slam_ros.mapper_role import MapperRole
    from splat_slam_ros.mapping.revisit import revisit_of
    from splat_slam_ros.types import KeyframeData, ProxyDepth
    from test_tracker import render_room

    def run(cull_deg):
        cfg = SlamConfig()
        cfg.mapping = MappingConfig.fast(iters_first=5, iters_per_keyframe=1,
                                         revisit_cull_deg=cull_deg)
        role = MapperRole(cfg)
        for k, z in enumerate([0.0, 0.6]):                 # a step forward into the room
            T = np.eye(4)
            T[2, 3] = z
            img, depth = render_room(T, INTR)
            role.on_keyframe(KeyframeData(k, k, float(k), T, img, INTR,
                                          np.ones((30, 40), np.float32),
                                          np.ones((30, 40), np.float32)))
            role.on_proxy_depth(ProxyDepth(k, depth, np.ones_like(depth, np.uint8), T,
                                           timestamp=k))
        return role

    off, on = run(0.0), run(10.0)
    assert off.offered == {0: True, 1: True}              # the window rules map it
    assert on.offered == {0: True, 1: False}
    T = np.eye(4)
    T[2, 3] = 0.6
    depth = render_room(T, INTR)[1]
    assert revisit_of(on.cfg.mapping, on.mapper.keyframes,
                      ProxyDepth(1, depth, np.ones_like(depth, np.uint8), T)) is None  # pose
    assert on.mapper.coverage(T) >= on.cfg.mapping.revisit_coverage


def test_densification_stops_at_the_view_budget():
    """``mapping.densify_max_per_view``: a keyframe's Gaussians stop growing by clone/split
    at that multiple of what a mapped keyframe anchors; the highest gradients go first."""
    from splat_slam_ros.config import MappingConfig, SlamConfig
    from splat_slam_ros.mapping.mapper import Mapper
    from test_tracker import render_room

    def densified(cap):
        cfg = SlamConfig()
        cfg.mapping = MappingConfig.fast(iters_first=3, densify_every=10 ** 6,
                                         densify_grad_thresh=1e-12, densify_max_per_view=cap)
        m = Mapper(cfg, INTR)
        img, depth = render_room(np.eye(4), INTR)
        m.add_keyframe(0, img, np.eye(4), depth)
        n0 = len(m.map)
        grad = (m.map.grad_accum / m.map.grad_count.clamp_min(1)).clone()
        uid = m.map.uid.clone()
        m.strategy.densify(m)
        return m, n0, grad, uid

    free, n0, _, _ = densified(0.0)
    assert len(free.map) > 1.5 * n0                        # everything selected: ~doubles
    budget = int(1.2 * INTR.width * INTR.height / MappingConfig.fast().downsample_first)
    capped, n0c, grad, uid = densified(1.2)
    assert n0c == n0 and n0 < budget < len(free.map)
    assert len(capped.map) == budget
    # the ones densified were the highest-gradient ones (a split parent leaves the map)
    top = set(uid[torch.argsort(grad, descending=True)[:budget - n0]].tolist())
    split = set(uid.tolist()) - set(capped.map.uid.tolist())
    assert split and split <= top


def test_mapper_role_merges_a_keyframe_that_an_update_shows_to_be_a_revisit(tmp_path):
    """A revisit keyframe arrives with a drifted pose (mapped as a new place); the update that
    corrects it puts it on an older mapped keyframe: it is merged, its Gaussians stay and follow
    the older keyframe, and a restart restores the merged map."""
    from splat_slam_ros.config import MappingConfig, SlamConfig
    from splat_slam_ros.mapper_role import MapperRole
    from splat_slam_ros.mapping.deformation import in_view
    from splat_slam_ros.types import KeyframeData, ProxyDepth
    from test_tracker import render_room
    cfg = SlamConfig()
    cfg.mapping = MappingConfig.fast(iters_first=5, iters_per_keyframe=1, revisit_cull_deg=10.0)
    role = MapperRole(cfg, store=KeyframeStore(tmp_path / "mapper"))

    def pose(x, y=0.0):
        T = np.eye(4)
        T[0, 3], T[1, 3] = x, y
        return T

    def offer(k, true_x, est_x):
        img, depth = render_room(pose(true_x), INTR)
        role.on_keyframe(KeyframeData(k, k, float(k), pose(est_x), img, INTR,
                                      np.ones((30, 40), np.float32), np.ones((30, 40), np.float32)))
        role.on_proxy_depth(ProxyDepth(k, depth, np.ones_like(depth, np.uint8), pose(est_x),
                                       timestamp=k))
        return depth

    for k, x in enumerate([0.0, 0.5, 1.0]):
        offer(k, x, x)
    depth3 = offer(3, 0.55, 1.6)                             # drifted: a "new place"
    assert sorted(role.mapper.keyframes) == [0, 1, 2, 3]
    m = role.mapper
    n_gauss = len(m.map)
    uid3 = m.map.uid[m.map.kf_id == 3].clone()
    assert len(uid3) > 0
    # loop closure corrects kf 3 to its true pose, next to kf 1: merged into kf 1
    role.on_proxy_depth(ProxyDepth(3, depth3, np.ones_like(depth3, np.uint8), pose(0.55),
                                   revision=1, timestamp=3))
    assert sorted(m.keyframes) == [0, 1, 2] and role.offered[3] is False
    assert m.counts["merged_keyframes"] == 1 and 3 not in m.window.window
    assert int((m.map.kf_id == 3).sum()) == 0
    # what kf 1 sees is there already (removed as duplicates); the strip only kf 3 saw stays
    left = torch.isin(m.map.uid, uid3)
    assert 0 < int(left.sum()) < len(uid3) // 4
    assert len(m.map) == n_gauss - (len(uid3) - int(left.sum()))
    assert bool((m.map.kf_id[left] == 1).all())
    assert not bool(in_view(m, m.map.means[left], pose(0.5)).any())
    before = m.map.means[left].clone()
    # the older keyframe moves: the re-anchored Gaussians move with it
    depth1 = render_room(pose(0.5), INTR)[1]
    role.on_proxy_depth(ProxyDepth(1, depth1, np.ones_like(depth1, np.uint8), pose(0.5, 0.1),
                                   revision=1, timestamp=1))
    after = m.map.means[torch.isin(m.map.uid, uid3)]
    assert torch.allclose(after - before, torch.tensor([0.0, 0.1, 0.0]), atol=1e-4)
    n_gauss = len(m.map)
    # a later revision of the merged keyframe is taken, not applied
    role.on_proxy_depth(ProxyDepth(3, depth3, np.ones_like(depth3, np.uint8), pose(0.5),
                                   revision=2, timestamp=3))
    assert role.taken[3] == 2 and sorted(m.keyframes) == [0, 1, 2]
    role.snapshot()
    assert not role.store.has("kf3_image") and not role.store.has("kf3_mdepth")
    again = MapperRole(cfg, store=KeyframeStore(tmp_path / "mapper"))
    assert sorted(again.mapper.keyframes) == [0, 1, 2] and len(again.mapper.map) == n_gauss
    assert again.offered[3] is False
    # the next new keyframe gets a fresh index (no clash with the merged one's)
    assert again.mapper.next_index == 4
    assert again.mapper.counts["merged_keyframes"] == 1
    # merges keep the window from filling: visibility pruning runs once the window holds every
    # mapped keyframe and more than prune_covis_min of them
    role = again
    assert not role.mapper.window.full and not role.mapper.strategy.enough_views(role.mapper)
    offer(4, 1.5, 1.5)
    assert len(role.mapper.keyframes) == 4 == len(role.mapper.window)
    assert not role.mapper.window.full and role.mapper.strategy.enough_views(role.mapper)


def test_mapper_role_in_revisit_mode_waits_for_a_loop_corrected_pose():
    """With a loop closer running, a new keyframe is mapped once a depth revision made after a
    loop-closure update arrives (its drifted pose corrected), so a revisit is recognised on
    arrival instead of being mapped as a new place; without loop updates nothing waits."""
    from splat_slam_ros.config import MappingConfig, SlamConfig
    from splat_slam_ros.mapper_role import MapperRole
    from splat_slam_ros.types import LOOP_SEQ_START, KeyframeData, ProxyDepth, UpdateEvent
    from test_tracker import render_room
    cfg = SlamConfig()
    cfg.mapping = MappingConfig.fast(iters_first=5, iters_per_keyframe=1, revisit_cull_deg=10.0)
    role = MapperRole(cfg)

    def pose(x):
        T = np.eye(4)
        T[0, 3] = x
        return T

    def depth_of(k, true_x, est_x, rev=0, seq=0):
        depth = render_room(pose(true_x), INTR)[1]
        return role.on_proxy_depth(ProxyDepth(k, depth, np.ones_like(depth, np.uint8),
                                              pose(est_x), revision=rev, update_seq=seq,
                                              timestamp=k))

    def keyframe(k, true_x, est_x):
        img = render_room(pose(true_x), INTR)[0]
        return role.on_keyframe(KeyframeData(k, k, float(k), pose(est_x), img, INTR,
                                             np.ones((30, 40), np.float32),
                                             np.ones((30, 40), np.float32)))

    for k, x in enumerate([0.0, 0.5]):                      # no loop closer seen yet
        keyframe(k, x, x)
        depth_of(k, x, x)
    assert sorted(role.mapper.keyframes) == [0, 1]
    role.on_update(UpdateEvent(seq=LOOP_SEQ_START, reason="loop_closure", kf_ids=[],
                               poses=np.zeros((0, 4, 4)), disparities=np.zeros((0, 30, 40))))
    assert role.loop_seen
    out = keyframe(2, 0.0, 0.9)                             # a revisit of kf 0, drifted
    out.extend(depth_of(2, 0.0, 0.9))
    assert 2 in role.held and 2 not in role.offered and len(out.acks) == 1   # acked, waiting
    assert not depth_of(2, 0.0, 0.85, rev=1, seq=7).acks    # a tracker update: still waiting
    assert 2 not in role.offered
    out = depth_of(2, 0.0, 0.0, rev=2, seq=LOOP_SEQ_START + 1)   # loop closure corrected it
    assert role.offered[2] is False and sorted(role.mapper.keyframes) == [0, 1]
    assert not out.acks and 2 not in role.held              # acked once, when it was held

    # a held keyframe waits for at most mapping.window_size newer keyframes
    keyframe(5, 1.5, 1.5)
    depth_of(5, 1.5, 1.5)
    assert 5 in role.held
    keyframe(5 + cfg.mapping.window_size - 1, 0.2, 0.2)
    assert 5 in role.held
    keyframe(5 + cfg.mapping.window_size, 0.3, 0.3)
    assert 5 in role.offered and 5 not in role.held

def test_checkpoint_packs_one_record_per_checkpoint_and_bounded_disk(tmp_path):
    """Changed keyframes of one checkpoint go into one record; records nobody refers to are
    deleted, and mostly stale ones are rewritten, so the stored items stay O(live items)."""
    from splat_slam_ros.tracking.tracker_state import _Packs
    st = KeyframeStore(tmp_path / "s")
    packs = _Packs("tkfp", None)
    rng = np.random.default_rng(0)
    version = {}

    def arrays(key):
        return {"v": np.array([version[key]])}

    for step in range(60):
        changed = [str(k) for k in rng.choice(40, size=rng.integers(1, 30), replace=False)]
        for key in changed:
            version[key] = step
        staged = {}
        packs.write(st, staged, {key: arrays(key) for key in changed}, arrays)
        assert len([n for n, f in staged.items() if f is not None]) <= 1     # one file
        st.commit(staged, {"packs": packs.state()})
        stored = sum(packs.size.values())
        assert stored <= 2 * len(version) + len(changed)
    again = _Packs("tkfp", KeyframeStore(tmp_path / "s").meta["packs"])
    for key, v in version.items():                      # the newest version of every item
        assert int(again.read(st, key)["v"][0]) == v
    assert set(st.names()) == set(again.size)


def test_skipped_frames_survive_a_restart(tmp_path):
    """A busy live tracker's skips (frames_skipped.txt, splat-slam-run --skip-frames) and
    its skipped / bridged counts are in the checkpoint: a restart keeps the earlier ones."""
    frames, _ = sequence()
    cfg = small_cfg()
    store_dir = tmp_path / "tracker"
    a = TrackerRole(cfg, INTR, False, store=KeyframeStore(store_dir))
    skipped = []
    for f in frames[:31]:
        if f.index > 12 and f.index % 5 == 0:
            a.on_skip(f)
            skipped.append((f.index, f.timestamp))
        else:
            a.on_frame(f)
    a._checkpoint()
    before = (list(a.tracker.skipped_at), a.tracker.n_skipped, a.tracker.n_bridged)
    assert before[0] == skipped and before[1] + before[2] == len(skipped) > 0
    del a
    b = TrackerRole(cfg, INTR, False, store=KeyframeStore(store_dir))
    assert b.resumed
    assert (b.tracker.skipped_at, b.tracker.n_skipped, b.tracker.n_bridged) == before
