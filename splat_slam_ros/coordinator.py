"""The in-process coordinator: the four stage roles wired together exactly as the ROS graph
wires them, with one FIFO queue in place of the DDS topics.

``on_frame`` hands a frame to the tracker and then delivers every outbox, in publication
order, to the roles that subscribe to it, until nothing is left in flight; ``finalize``
starts the end-of-stream sequence (see :mod:`splat_slam_ros.roles`) and runs it to the
mapper's final refinement. Topics and subscribers (the same in ``nodes/``):

  updates      tracker, loop closure -> each role whose ``update_sources`` has the source:
                                       tracker (loop's), loop closure (tracker's), depth, mapper
  keyframes    tracker               -> loop closure, depth, mapper
  proxy depth  depth                 -> mapper
  finalized    every role            -> every other role
"""
from __future__ import annotations

import time
from collections import defaultdict, deque
from typing import Callable, Dict, Iterable, List, Optional

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.io.prefetch import read_frames
from splat_slam_ros.mapper_role import MapperRole
from splat_slam_ros.roles import DepthRole, LoopRole, Outbox, TrackerRole
from splat_slam_ros.tracking.flow_frontend import make_flow_predictor
from splat_slam_ros.types import TrackingResult, TrackStep
from splat_slam_ros.types import Frame, Intrinsics, UpdateEvent

# role name -> the stage name used in timings / metrics
STAGE_OF = {"tracker": "tracking", "loop_closure": "loop_closure", "depth": "depth",
            "mapper": "mapping"}


class ProtocolError(RuntimeError):
    """The stages did not reach their final state (a bug, never a user error)."""


class Coordinator:
    """Tracker + loop closer + proxy depth + mapper in one process (see module docstring)."""

    def __init__(self, cfg: SlamConfig, intrinsics: Intrinsics, mapping: bool = True,
                 loop_closure: Optional[bool] = None, make_tracker=None):
        """``make_tracker(flow_predictor)``: the tracker to use (default a new Tracker)."""
        tc = cfg.tracking
        use_loop = bool(tc.loop_closure or tc.global_ba) if loop_closure is None \
            else bool(loop_closure)
        self.cfg = cfg
        flow = make_flow_predictor(tc)           # one front end (DIS or the network) for both
        self.tracker = TrackerRole(cfg, intrinsics, loop_closure=use_loop, flow_predictor=flow,
                                   tracker=make_tracker(flow) if make_tracker else None)
        self.loop = LoopRole(cfg, flow_predictor=flow) if use_loop else None
        self.depth = DepthRole(cfg, loop_closure=use_loop) if mapping else None
        self.mapper = MapperRole(cfg) if mapping else None
        self.roles = [r for r in (self.tracker, self.loop, self.depth, self.mapper)
                      if r is not None]
        self._queue: deque = deque()
        self.updates: List[UpdateEvent] = []      # every update, in publication order
        self.timings: Dict[str, float] = defaultdict(float)
        self.n_keyframes = 0

    # ------------------------------------------------------------ protocol
    def on_frame(self, frame: Frame) -> TrackStep:
        t0 = time.perf_counter()
        step, out = self.tracker.on_frame(frame)
        self.timings["tracking"] += time.perf_counter() - t0
        self._deliver(out, self.tracker)
        self._drain()
        return step

    def finalize(self) -> None:
        t0 = time.perf_counter()
        out = self.tracker.finalize()
        self.timings["tracking"] += time.perf_counter() - t0
        self._deliver(out, self.tracker)
        self._drain()
        stuck = [r.name for r in self.roles if not (r.complete if r is self.tracker
                                                     else r.finalized)]
        if stuck:
            raise ProtocolError(f"finalisation did not complete for: {', '.join(stuck)}")

    def _deliver(self, out: Outbox, origin) -> None:
        q = self._queue
        for ev in out.updates:                   # before keyframes: the order of publication
            self.updates.append(ev)
            q.extend((r, "update", ev) for r in self.roles
                     if r is not origin and ev.source in r.update_sources)
        for kf in out.keyframes:
            self.n_keyframes += 1
            q.extend((r, "keyframe", kf) for r in (self.loop, self.depth, self.mapper)
                     if r is not None)
        if self.mapper is not None:
            q.extend((self.mapper, "proxy_depth", pd) for pd in out.proxy_depths)
        if out.final is not None:
            q.extend((r, "final", (origin.name, out.final)) for r in self.roles
                     if r is not origin)

    def _drain(self) -> None:
        while self._queue:
            role, kind, item = self._queue.popleft()
            t0 = time.perf_counter()
            if kind == "update":
                out = role.on_update(item)
            elif kind == "keyframe":
                out = role.on_keyframe(item)
            elif kind == "proxy_depth":
                out = role.on_proxy_depth(item)
            else:
                out = role.on_final(*item)
            self.timings[STAGE_OF[role.name]] += time.perf_counter() - t0
            self._deliver(out, role)

    # ------------------------------------------------------------ driver
    def run(self, frames: Iterable[Frame], progress: bool = True, total: Optional[int] = None,
            max_frames: Optional[int] = None,
            skip: Optional[Callable[[Frame], bool]] = None) -> int:
        """Every frame, then :meth:`finalize`; returns the number of frames. ``skip(frame)``
        true: the tracker skips it as a busy live tracker did (a live run replayed)."""
        t_start, n = time.perf_counter(), 0

        def postfix(k):
            return dict(kf=self.n_keyframes, lost=self.tracker.tracker.n_lost,
                        fps=f"{k / max(time.perf_counter() - t_start, 1e-9):.2f}")
        for frame in read_frames(frames, progress, total, max_frames, postfix):
            if skip is not None and skip(frame):
                self.tracker.on_skip(frame)
            else:
                self.on_frame(frame)
            n += 1
        self.finalize()
        return n


def track_sequence(frames: Iterable[Frame], cfg: SlamConfig, intrinsics: Intrinsics,
                   progress: bool = True, loop_closure: Optional[bool] = None,
                   total: Optional[int] = None) -> TrackingResult:
    """Tracking only (tracker + loop closer, §3.1) over a whole sequence, in-process."""
    t_start = time.perf_counter()
    co = Coordinator(cfg, intrinsics, mapping=False, loop_closure=loop_closure)
    n = co.run(frames, progress=progress, total=total)
    trk = co.tracker.tracker
    ts, poses = trk.trajectory_full()
    kts, kposes = trk.trajectory_keyframes()
    wall = time.perf_counter() - t_start
    timings: Dict[str, float] = dict(trk.timings)
    if co.loop is not None and co.loop.loop is not None:
        timings.update({"loop_" + k: v for k, v in co.loop.loop.timings.items()})
    timings["loop_closure"] = co.timings.get("loop_closure", 0.0)
    timings["wall"] = wall
    timings["fps"] = n / max(wall, 1e-9)
    return TrackingResult(ts, poses, kts, kposes, trk.keyframe_ids(), list(co.updates),
                          timings, n, len(trk.published), trk.n_lost, wall)
