"""Live input at the mapper node: a keyframe's newer proxy depth replaces the one still
queued (the queue no longer runs seconds behind the stream), only input that maps cuts the
optimisation steps, and the map lag (a keyframe's frame arrives -> mapped) in metrics.json."""
import threading
from types import SimpleNamespace

import pytest

rclpy = pytest.importorskip("rclpy", reason="the node code needs rclpy (./run.sh setup)")

from splat_slam_nodes.camera_input import spread  # noqa: E402
from splat_slam_nodes.mapper_node import MAX_QUEUED, MapperNode  # noqa: E402
from splat_slam_nodes.node_common import NewestWaiting  # noqa: E402
from splat_slam_nodes.tools.launch_results import map_lag  # noqa: E402


def test_a_newer_revision_replaces_the_waiting_one_and_queues_no_second_job():
    w = NewestWaiting()
    jobs = [k for k, rev in ((3, 0), (4, 0), (3, 1), (3, 2), (4, 1), (5, 0), (3, 1))
            if w.offer(k, f"kf{k}r{rev}", rev)]
    assert jobs == [3, 4, 5]                      # one job per keyframe, first arrival order
    assert sorted(w) == [3, 4, 5] and len(w) == 3
    assert w.take(3) == "kf3r2"                   # the newest, not the late older replay
    assert w.take(4) == "kf4r1" and w.take(5) == "kf5r0"
    assert len(w) == 0
    assert w.offer(3, "kf3r3", 3)                 # taken: the next revision queues a job again


def _node(pending, updates=0, depth_for=(), offered=()):
    """What MapperNode._input_waiting reads: the worker's queue length, the queued update
    jobs, the keyframes whose depth waits and those the mapper consumed already."""
    dw = NewestWaiting()
    for k in depth_for:
        dw.offer(k, object(), 0)
    return SimpleNamespace(worker=SimpleNamespace(pending=lambda: pending),
                           _waiting_lock=threading.Lock(), depth_waiting=dw,
                           waiting={"updates": updates, "keyframes": 0, "proxy_depth": len(dw)},
                           role=SimpleNamespace(offered={k: True for k in offered}))


def test_only_input_that_maps_cuts_the_mapping_steps():
    waiting = MapperNode._input_waiting
    assert not waiting(_node(0))
    # deformations of mapped keyframes and pose-graph updates wait for the steps' end
    assert not waiting(_node(3, updates=1, depth_for=(1, 2), offered=(1, 2)))
    # the depth of a keyframe not mapped yet (it can be mapped now), a keyframe, a request
    assert waiting(_node(3, updates=1, depth_for=(1, 7), offered=(1, 2)))
    assert waiting(_node(4, updates=1, depth_for=(1, 2), offered=(1, 2)))
    # beyond the bound any queued job cuts them
    many = tuple(range(MAX_QUEUED + 1))
    assert waiting(_node(len(many), depth_for=many, offered=many))


def test_map_lag_is_per_keyframe_from_its_frames_arrival_to_mapped():
    arrival = {"0": 100.0, "1": 101.0, "2": 102.0, "3": 103.0}
    mapped = {"0": 104.0, "1": 101.5, "3": 103.2, "9": 200.0}     # 2: not mapped (redundant)
    lag = map_lag(arrival, mapped)
    assert lag["keyframes"] == 3
    assert lag["max"] == pytest.approx(4.0)
    assert lag["p50"] == pytest.approx(0.5)
    assert 0.5 < lag["p95"] <= 4.0
    assert map_lag(arrival, None) == {} and map_lag({}, mapped) == {}
    assert spread([]) == {}
