"""The update protocol on its own: stage roles (splat_slam_ros.roles) and the in-process
coordinator that routes them as the ROS graph does (event order, update numbering, warm-up
batches, replays, finalisation), and splat-slam-run end to end with an accuracy bound."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from splat_slam_ros.config import MappingConfig
from splat_slam_ros.coordinator import Coordinator
from splat_slam_ros.mapper_role import MapperRole
from splat_slam_ros.roles import DepthRole, KeyframeBatcher, LoopRole, Outbox
from splat_slam_ros.types import (LOOP_SEQ_START, TRACKER_SEQ_START, KeyframeData, ProxyDepth,
                                  UpdateEvent)

from test_tracker import INTR, ate_cm, sequence, small_cfg


def cfg_full(loop: bool = True):
    cfg = small_cfg(loop_closure=loop, global_ba=loop, global_ba_every=3, loop_time_gap=4,
                    loop_window=4, warmup=4)
    cfg.mapping = MappingConfig.fast(iters_first=40, iters_per_keyframe=5, final_refine_iters=10)
    return cfg


class Recording(Coordinator):
    """Logs every delivery (receiver, kind, what) in the order the coordinator makes it."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.log = []

    def _deliver(self, out: Outbox, origin) -> None:
        for ev in out.updates:
            self.log.append((origin.name, "update", ev.seq))
        for kf in out.keyframes:
            self.log.append((origin.name, "keyframe", kf.kf_id))
        for pd in out.proxy_depths:
            self.log.append((origin.name, "proxy_depth", (pd.kf_id, pd.revision)))
        if out.final is not None:
            self.log.append((origin.name, "final", None))
        super()._deliver(out, origin)


@lru_cache(maxsize=1)
def full_run():
    frames, gt = sequence(40)
    co = Recording(cfg_full(), INTR)
    for f in frames:
        co.on_frame(f)
    co.finalize()
    return co, frames, gt


def kf(k: int, batch_id: int = -1, batch_size: int = 1) -> KeyframeData:
    return KeyframeData(kf_id=k, frame_index=k, timestamp=float(k), pose=np.eye(4),
                        image=np.zeros((8, 8, 3), np.uint8), intrinsics=INTR,
                        disparity=np.ones((2, 2), np.float32),
                        confidence=np.ones((2, 2), np.float32),
                        batch_id=batch_id, batch_size=batch_size)


# ------------------------------------------------------------------ units
def test_batcher_waits_for_the_whole_batch_and_drops_replays():
    b = KeyframeBatcher()
    assert [k.kf_id for k in b.add(kf(5), lambda k: False)] == [5]
    assert b.add(kf(5), lambda k: k == 5) == []               # a replayed single keyframe
    assert b.add(kf(2, 0, 3), lambda k: False) == []           # out of order
    assert b.add(kf(0, 0, 3), lambda k: False) == [] and b.waiting() == 2
    got = b.add(kf(1, 0, 3), lambda k: False)
    assert [k.kf_id for k in got] == [0, 1, 2] and b.waiting() == 0
    # a batch replayed after a restart: members already known are not handed on again
    for k in (0, 1):
        assert b.add(kf(k, 0, 3), lambda k: k in (0, 1)) == []
    assert [k.kf_id for k in b.add(kf(2, 0, 3), lambda k: k in (0, 1))] == [2]


def test_update_sources_and_ranges():
    assert UpdateEvent(1, "local_ba", [], np.zeros((0, 4, 4))).source == "tracker"
    for r in ("loop_closure", "global_ba", "final"):
        assert UpdateEvent(LOOP_SEQ_START, r, [], np.zeros((0, 4, 4))).source == "loop"
    assert 0 < TRACKER_SEQ_START < LOOP_SEQ_START


def test_loop_role_takes_each_tracker_update_once_and_finalises_after_the_last():
    role = LoopRole(cfg_full())
    ev = UpdateEvent(3, "local_ba", [], np.zeros((0, 4, 4)))
    assert role.on_update(ev).final is None and role.trk_seq == 3
    assert role.on_final("tracker", {"last_seq": 4}).final is None      # 4 not seen yet
    role.on_update(replace(ev, seq=2))                                   # older: a replay
    assert role.trk_seq == 3 and not role.finalized
    out = role.on_update(replace(ev, seq=4))
    assert role.finalized and out.final == {"last_seq": 0, "keyframes": 0, "merged": 0}
    assert role.on_update(replace(ev, seq=5)).final is None             # final only once


def mapper_role_inputs():
    """A MapperRole, keyframe 0 of the test sequence and its ground-truth depth + frame."""
    frames, _ = sequence(40)
    f = frames[0]
    k0 = replace(kf(0), image=f.image, disparity=np.ones((30, 40), np.float32),
                 confidence=np.ones((30, 40), np.float32))
    return MapperRole(cfg_full()), k0, f.gt_depth.astype(np.float32), f


def test_mapper_role_skips_old_revisions_and_waits_for_the_digest():
    role, k0, depth, f = mapper_role_inputs()
    pd = ProxyDepth(0, depth, np.ones_like(depth, np.uint8), f.gt_pose, revision=0)
    assert role.on_keyframe(k0).mapped == []               # waits for its depth
    out = role.on_proxy_depth(pd)
    assert [m["kf_id"] for m in out.mapped] == [0] and out.acks == [(0, 0, 0.0)]
    assert role.on_proxy_depth(pd).mapped == [] and role.timings["deformation"] == 0.0
    assert role.lacking() == []                                           # no digest yet
    assert role.on_final("depth", {"digest": {"0": 1}}).final is None    # revision 1 missing
    assert role.lacking() == [0]                   # what the mapper node asks the depth node for
    out = role.on_proxy_depth(replace(pd, revision=1, is_update=True))
    assert role.timings["deformation"] > 0 and role.taken[0] == 1
    assert out.final is not None and role.finalized                       # then the refinement
    assert role.lacking() == []


def test_mapper_role_background_steps_only_on_live_input_and_within_the_allowance():
    """Live input (mapping.time_budget): between keyframes the mapper goes on optimising, at
    most mapping.background_steps after each mapped keyframe and never after the final
    refinement; offline (step budgets) never, so a replay stays reproducible."""
    role, k0, depth, f = mapper_role_inputs()
    pd = ProxyDepth(0, depth, np.ones_like(depth, np.uint8), f.gt_pose, revision=0)
    role.on_keyframe(k0)
    role.on_proxy_depth(pd)
    assert role.mapper is not None and not role.wants_background()      # offline: never
    role, k0, depth, f = mapper_role_inputs()
    role.cfg.mapping.time_budget = True
    role.cfg.mapping.background_steps = 6
    assert not role.wants_background()                                  # no map yet
    role.on_keyframe(k0)
    role.on_proxy_depth(pd)
    it0 = role.mapper.iteration
    while role.wants_background():
        role.background(4)
    assert role.mapper.iteration - it0 == 8 == role.mapper.background_iters   # 4 + 4 >= 6
    assert role.mapper.stats()["background_iterations"] == 8
    role.on_final("depth", {"digest": {"0": 0}})
    assert role.finalized and not role.wants_background()


def test_mapper_role_refinement_deadline_counts_from_when_the_input_ended():
    """mapping.final_deadline_s (live): the depth stage's digest may wait in the mapper's
    queue behind keyframes; the deadline counts from when it was sent (the event's "t"), or
    from the player's end of stream when that came first."""
    import time

    def refine_steps(digest_ago: float, stream_end_ago=None, stream_end_after=False) -> int:
        role, k0, depth, f = mapper_role_inputs()
        role.cfg.mapping.time_budget = True
        role.cfg.mapping.final_deadline_s = 1.0
        role.cfg.mapping.final_refine_s = 0.0
        role.cfg.mapping.final_refine_iters = role.cfg.mapping.final_refine_per_keyframe = 50
        role.on_keyframe(k0)
        role.on_proxy_depth(ProxyDepth(0, depth, np.ones_like(depth, np.uint8), f.gt_pose))
        if stream_end_ago is not None and not stream_end_after:
            role.input_ended(time.time() - stream_end_ago)
        out = role.on_final("depth", {"digest": {"0": 0}, "t": time.time() - digest_ago})
        if stream_end_ago is not None and stream_end_after:
            role.input_ended(time.time() - stream_end_ago)      # too late: already refined
        return out.final["refine"]["refine_iters"]
    assert refine_steps(60.0) == 1                     # the digest was sent a minute ago
    assert refine_steps(0.0) > 1
    # the player's end of stream came first (the depth stage lagged): the deadline counts
    # from it, whichever of the two arrived first
    assert refine_steps(0.0, stream_end_ago=60.0) == 1
    assert refine_steps(0.0, stream_end_ago=60.0, stream_end_after=True) > 1


def test_mapper_role_after_the_input_ended_queued_keyframes_leave_their_steps_to_the_refinement():
    """Live input: a keyframe mapped while more input waits gets its minimum steps; once the
    input ended (the player's end of stream), none: the keyframes still queued are mapped
    at once and the final refinement, before its deadline, has the time."""
    import time
    frames, _ = sequence(40)
    for ended in (False, True):
        role, k0, depth, f = mapper_role_inputs()
        role.cfg.mapping.time_budget = True
        role.cfg.mapping.min_iters_per_keyframe = 3
        role.input_waiting = lambda: True               # more input queued all along
        role.on_keyframe(k0)
        role.on_proxy_depth(ProxyDepth(0, depth, np.ones_like(depth, np.uint8), f.gt_pose))
        if ended:
            role.input_ended(time.time())
        f1 = frames[20]
        k1 = replace(kf(1), image=f1.image, timestamp=1.0, disparity=np.ones((30, 40), np.float32),
                     confidence=np.ones((30, 40), np.float32))
        role.on_keyframe(k1)
        out = role.on_proxy_depth(ProxyDepth(1, f1.gt_depth.astype(np.float32),
                                             np.ones_like(depth, np.uint8), f1.gt_pose))
        assert [m["kf_id"] for m in out.mapped] == [1] and out.mapped[0]["mapped"]
        assert out.mapped[0]["steps"] == (0 if ended else 3), (ended, out.mapped[0]["steps"])


def test_node_worker_runs_idle_work_only_while_nothing_is_queued():
    """The node worker runs queued jobs first and the idle work (the mapper's background
    steps) in pieces while the queue is empty and the work is wanted."""
    pytest.importorskip("rclpy", reason="the node worker needs rclpy (./run.sh setup)")
    import threading
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from nodes.node_common import Worker

    class Owner:
        name = "t"
    w = Worker(Owner())
    log, left, done = [], [3], threading.Event()

    def idle_work():
        left[0] -= 1
        log.append("idle")
        if left[0] == 0:
            done.set()
    w.idle = (lambda: left[0] > 0, idle_work)
    w.submit(log.append, "job1")
    w.submit(log.append, "job2")
    w.start()
    assert done.wait(10)
    last = threading.Event()
    w.submit(lambda: (log.append("job3"), last.set()))
    assert last.wait(10)
    w.stop()
    assert log[:2] == ["job1", "job2"] and log.count("idle") == 3 and log[-1] == "job3"


def test_consumers_ack_a_replayed_keyframe_again():
    """A keyframe replayed to a restarted consumer that had consumed it (its ack may have died
    with the old process) is acked again, so a lockstep player waiting for it goes on; it is
    not consumed twice. (Without it a lost ack makes the player wait out its 300 s timeout.)"""
    role, k0, depth, f = mapper_role_inputs()
    role.on_keyframe(k0)
    pd = ProxyDepth(0, depth, np.ones_like(depth, np.uint8), f.gt_pose, revision=0)
    assert role.on_proxy_depth(pd).acks == [(0, 0, 0.0)]
    out = role.on_keyframe(k0)                             # the replay
    assert out.acks == [(0, 0, 0.0)] and out.mapped == [] and role.pending_kf == {}
    assert role.on_keyframe(replace(k0, kf_id=1, frame_index=1, timestamp=1.0)).acks == []
    loop = LoopRole(cfg_full())
    k = replace(k0, disparity=np.ones((30, 40), np.float32))
    assert loop.on_keyframe(k).acks == [(0, 0, 0.0)]
    n = len(loop.loop.kfs.ids)
    assert loop.on_keyframe(k).acks == [(0, 0, 0.0)] and len(loop.loop.kfs.ids) == n


def test_mapper_role_holds_a_keyframe_without_depth_until_a_revision_has_some():
    """Revision 0 of the first keyframe of a 2-keyframe warm-up has no valid pixel (no views
    yet): mapped, it anchored no Gaussians and left the map without a scene depth (every
    later Gaussian "large": 6x the splits, PSNR 27 instead of 30 dB on fr2/desk)."""
    role, k0, depth, f = mapper_role_inputs()
    empty = ProxyDepth(0, np.zeros_like(depth), np.zeros_like(depth, np.uint8), f.gt_pose,
                       revision=0)
    role.on_keyframe(k0)
    out = role.on_proxy_depth(empty)
    assert out.mapped == [] and out.acks == [(0, 0, 0.0)] and role.held == {0}   # lockstep goes on
    # BA depth filling the holes anchors nothing: a depth of (almost) only that is held too
    ba_only = np.full_like(depth, ProxyDepth.SOURCE_BA, dtype=np.uint8)
    ba_only.flat[:10] = ProxyDepth.SOURCE_MULTIVIEW
    assert role.on_proxy_depth(replace(empty, depth=depth, source=ba_only, revision=1,
                                       is_update=True)).mapped == [] and role.held == {0}
    out = role.on_proxy_depth(replace(empty, depth=depth, source=np.ones_like(depth, np.uint8),
                                      revision=2, is_update=True))
    assert [m["kf_id"] for m in out.mapped] == [0] and out.acks == [] and role.held == set()
    assert role.mapper.scene_extent() == pytest.approx(float(np.median(depth)), rel=0.05)
    # at the end a keyframe still without depth is mapped with what there is
    k1 = replace(k0, kf_id=1, frame_index=1, timestamp=1.0)
    role.on_keyframe(k1)
    assert role.on_proxy_depth(replace(empty, kf_id=1)).mapped == [] and role.held == {1}
    out = role.on_final("depth", {"digest": {"0": 1, "1": 0}})
    assert [m["kf_id"] for m in out.mapped] == [1] and out.final is not None


# ------------------------------------------------------------------ in-process graph
def test_coordinator_routes_like_the_graph():
    co, frames, gt = full_run()
    log = co.log
    # warm-up keyframes go out as one batch, later ones alone
    kfs = co.tracker.tracker.published
    batch = [e for e in log if e[:2] == ("tracker", "keyframe")]
    assert len(kfs) >= 6 and len(batch) == len(kfs)
    # update numbering: per source strictly increasing, in its own range
    for src, lo, hi in (("tracker", TRACKER_SEQ_START, LOOP_SEQ_START),
                        ("loop_closure", LOOP_SEQ_START, 2 * LOOP_SEQ_START)):
        seqs = [e[2] for e in log if e[0] == src and e[1] == "update"]
        assert seqs and seqs == sorted(set(seqs)) and lo <= seqs[0] < hi and seqs[-1] < hi
    # depth sends revision 0 first for each keyframe, then increasing revisions
    revs = {}
    for name, kind, what in log:
        if kind == "proxy_depth":
            k, r = what
            assert r == revs.get(k, -1) + 1
            revs[k] = r
    assert set(revs) == set(kfs)
    # finalisation order: tracker -> loop closure -> depth -> mapper, each exactly once
    finals = [e[0] for e in log if e[1] == "final"]
    assert finals == ["tracker", "loop_closure", "depth", "mapper"]
    assert co.tracker.complete and co.mapper.finalized
    # the mapper took the last revision of every keyframe the depth stage announced
    assert all(co.mapper.taken[k] == r for k, r in revs.items())
    assert ate_cm(frames, gt, *co.tracker.tracker.trajectory_full()) < 3.0


def test_depth_role_handles_a_warmup_batch_as_one():
    co, _, _ = full_run()
    est = co.depth.est
    first = sorted(co.tracker.tracker.published)[:4]
    # each warm-up keyframe was filtered against the others of its batch (Eq. 6 views)
    assert all(len(est.neighbours(k)) >= 2 for k in first)
    # replaying the stage's inputs changes nothing
    k0 = first[0]
    n_rev = dict(co.depth.revision)
    out = co.depth.on_update(co.updates[0])
    assert out.proxy_depths == [] and co.depth.revision == n_rev
    assert co.depth.on_keyframe(kf(k0)).proxy_depths == [] and co.depth.revision == n_rev
    # asked again (a mapper lacking a revision of the digest): the current revision of the
    # keyframes asked for that it knows, nothing new
    again = co.depth.current([first[1], k0, 10_000]).proxy_depths
    assert [(p.kf_id, p.revision) for p in again] == [(k, n_rev[k]) for k in sorted(first[:2])]
    assert co.depth.revision == n_rev


def test_tracking_only_needs_no_depth_or_mapper():
    frames, gt = sequence(40)
    co = Coordinator(cfg_full(loop=False), INTR, mapping=False)
    assert co.run(frames, progress=False) == 40
    assert co.depth is None and co.mapper is None and co.tracker.complete
    assert all(e.source == "tracker" for e in co.updates)


# ------------------------------------------------------------------ splat-slam-run
@pytest.fixture(scope="module")
def synth_seq(tmp_path_factory):
    from splat_slam_synth import generate_sequence
    d = tmp_path_factory.mktemp("coord") / "seq"
    generate_sequence("builtin", 36, (160, 120), d, overwrite=True, progress=False,
                      realism="clean", fps=10)
    return d


RUN_CFG = """
tracking: {warmup: 4, motion_filter_thresh: 2.0, keyframe_thresh: 2.0, ba_downsample: 4}
mapping: {iters_first: 60, iters_per_keyframe: 10, final_refine_iters: 30,
          random_views_per_iter: 1, window_views_per_iter: 3}
"""


def test_splat_slam_run_end_to_end(synth_seq, tmp_path):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(RUN_CFG)
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "splat_slam_ros.cli.run", str(synth_seq),
                        "--out", str(out), "--config", str(cfg), "--no-progress"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["keyframes"] >= 5 and m["frames"] == 36
    # keyframes per second of input and by cause (the 36 frames at 10 Hz span 3.5 s)
    assert sum(m["keyframe_causes"].values()) == m["keyframes"]
    assert set(m["keyframe_causes"]) <= {"warmup", "threshold", "fast", "losing", "promoted",
                                         "final"} and m["keyframe_causes"]["warmup"] >= 2
    assert m["keyframes_per_s"] == pytest.approx(m["keyframes"] / 3.5, rel=1e-2)
    assert f"keyframes per second of input {m['keyframes_per_s']:.2f} (warmup " in r.stdout
    assert m["ate_rmse_cm_full"] < 5.0, m
    assert m["psnr"] > 18.0, m
    assert (out / "map.ply").stat().st_size > 1000
    assert set(m["timings_s"]) >= {"tracking", "loop_closure", "depth", "mapping"}


def _static_copy(seq, dst, n: int = 6):
    """The first frame of ``seq`` shown ``n`` times at 10 Hz (a camera that does not move)."""
    dst.mkdir()
    for name in ("rgb", "depth", "intrinsics.yaml"):
        src = seq / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, dst / name)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        rows = [ln for ln in (seq / name).read_text().splitlines() if not ln.startswith("#")]
        first = rows[0].split(" ", 1)[1]
        (dst / name).write_text("".join(f"{0.1 * i:.6f} {first}\n" for i in range(n)))
    return dst


def test_splat_slam_run_without_motion_fails_clearly(synth_seq, tmp_path):
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "splat_slam_ros.cli.run",
                        str(_static_copy(synth_seq, tmp_path / "static")),
                        "--out", str(out), "--no-progress"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 3, (r.returncode, r.stderr[-2000:])
    assert "never initialised" in r.stderr and "tracking.motion_filter_thresh" in r.stderr
    assert "Traceback" not in r.stderr
    assert "error" in json.loads((out / "metrics.json").read_text())
    assert not (out / "trajectory_full.txt").exists()


def test_splat_slam_run_with_an_empty_map_fails_clearly(synth_seq, tmp_path):
    """Three frames: the tracker initialises from two keyframes, but no proxy-depth pixel has
    the two confirming views, so the map stays empty - an error, not a success."""
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "splat_slam_ros.cli.run", str(synth_seq),
                        "--out", str(out), "--max-frames", "3", "--no-progress"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 3, (r.returncode, r.stderr[-2000:])
    assert "the map is empty" in r.stderr and "depth.mv_min_views" in r.stderr
    assert "Traceback" not in r.stderr
    m = json.loads((out / "metrics.json").read_text())
    assert m["keyframes"] >= 2 and m["gaussians"] == 0 and "map is empty" in m["error"]


def test_splat_slam_run_without_texture_names_the_flow_not_the_motion(synth_seq, tmp_path):
    """Every frame uniform grey (no flow can be confident on it): the tracker never
    initialises, and the reason is the flow (tracking.lost_min_valid), not the motion."""
    import cv2
    seq = tmp_path / "grey"
    shutil.copytree(synth_seq, seq)
    for png in (seq / "rgb").glob("*.png"):
        cv2.imwrite(str(png), np.full(cv2.imread(str(png)).shape, 128, np.uint8))
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "splat_slam_ros.cli.run", str(seq), "--out",
                        str(out), "--tracking-only", "--no-progress"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 3, (r.returncode, r.stderr[-2000:])
    assert "not confident on 36 of them" in r.stderr and "tracking.lost_min_valid" in r.stderr
    assert "motion_filter_thresh" not in r.stderr and "Traceback" not in r.stderr
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames_lost"] == 36 and m["frames_posed"] == 0 and m["keyframes"] == 0


def test_no_result_reason_covers_both_failures_and_only_them():
    """The rule splat-slam-run and splat-slam-launch share (exit status 3)."""
    from splat_slam_ros.config import SlamConfig
    from splat_slam_ros.pipeline import no_result_reason
    cfg = SlamConfig()
    assert "never initialised over 40 frames" in no_result_reason(cfg, {"frames": 40})
    assert "map is empty" in no_result_reason(cfg, {"keyframes": 3, "gaussians": 0})
    assert no_result_reason(cfg, {"keyframes": 3, "gaussians": 120}) is None
    assert no_result_reason(cfg, {"keyframes": 3}) is None          # tracking only: no map
    # most frames lost (little texture): the flow, not the motion, and the setting to try
    msg = no_result_reason(cfg, {"frames": 150, "frames_lost": 133})
    assert "not confident on 133 of them" in msg and "motion_filter_thresh" not in msg
    assert "--set tracking.lost_min_valid=0.04;" in msg
    assert "tracking.lost_rel_texture=0.25 of the cells its texture allows" in msg
    cfg.tracking.lost_rel_texture = 0.0                 # off: only the absolute threshold
    assert "lost_rel_texture" not in no_result_reason(cfg, {"frames": 150, "frames_lost": 133})
    assert "moved too little" in no_result_reason(cfg, {"frames": 150, "frames_lost": 20})


def test_not_initialised_hint_lowers_the_values_in_use():
    from splat_slam_ros.config import SlamConfig
    from splat_slam_ros.pipeline import not_initialized_reason
    cfg = SlamConfig()
    cfg.tracking.motion_filter_thresh, cfg.tracking.init_parallax = 2.0, 1.5
    msg = not_initialized_reason(cfg, 60)
    assert "over 60 frames" in msg and "thresh=2 reference BA px" in msg
    assert "--set tracking.motion_filter_thresh=1 --set tracking.init_parallax=0.75)" in msg
    cfg.tracking.init_parallax = 0                       # parallax check off: nothing to lower
    assert "tracking.init_parallax=" not in not_initialized_reason(cfg, 60).split("e.g.")[1]
