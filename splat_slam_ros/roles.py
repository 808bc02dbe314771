"""The four stage endpoints of the update protocol, ROS-free.

Each role wraps one stage of the paper and owns everything about its messages that is not
transport: which inputs it takes, in which order, what it recognises as a replay, how it
groups the tracker's warm-up batch, what it persists for a restart and when it is final.
A role never publishes; every handler returns an :class:`Outbox` of what the stage sends
on. The in-process :class:`~splat_slam_ros.coordinator.Coordinator` routes outboxes between
the four roles; each ROS node wraps one role and turns outboxes into messages.

Identity of a message (replays after a restart are skipped, never applied twice):
  keyframe        its ``kf_id``                     (dense from 0, never reused)
  PoseGraphUpdate its ``seq`` within its source     (tracker from TRACKER_SEQ_START,
                                                     loop closer from LOOP_SEQ_START)
  ProxyDepth      ``(kf_id, revision)``             (revision 0, 1, 2, ... per keyframe)

Finalisation (each ``final`` dict becomes a ``finalized`` graph event):
  tracker.finalize() -> {last_seq} -> loop closer, once it applied the tracker's updates
  up to last_seq: final global BA -> {last_seq} -> tracker complete once it applied those;
  depth, once both streams reached their last_seq -> {digest: kf_id -> last revision} ->
  mapper, once it took every revision in the digest: final refinement -> {metrics}.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.depth.proxy_depth import ProxyDepthEstimator, ProxyDepthResult
from splat_slam_ros.io.keyframe_store import (KeyframeStore, keyframe_depth, mapper_state,
                                              restore_mapper)
from splat_slam_ros.io.trajectory_io import write_tum
from splat_slam_ros.tracking.loop_closure import LoopCloser
from splat_slam_ros.tracking.tracker import Tracker
from splat_slam_ros.tracking.tracker_state import (TrackerCheckpoint, intrinsics_from_list,
                                                   intrinsics_to_list)
from splat_slam_ros.types import (LOOP_SEQ_START, TRACKER_SEQ_START, Frame, Intrinsics,
                                  KeyframeData, ProxyDepth, TrackStep, UpdateEvent)


@dataclass
class Outbox:
    """What a stage sends on after handling one input."""
    updates: List[UpdateEvent] = field(default_factory=list)
    keyframes: List[KeyframeData] = field(default_factory=list)
    proxy_depths: List[ProxyDepth] = field(default_factory=list)
    acks: List[Tuple[int, int, float]] = field(default_factory=list)  # frame, kf_id, stamp
    mapped: List[dict] = field(default_factory=list)    # mapper: status of mapped keyframes
    final: Optional[dict] = None                        # the stage became final

    def extend(self, other: "Outbox") -> "Outbox":
        for name in ("updates", "keyframes", "proxy_depths", "acks", "mapped"):
            getattr(self, name).extend(getattr(other, name))
        if other.final is not None:
            self.final = other.final
        return self


class KeyframeBatcher:
    """Groups the keyframes of one batch (``KeyframeData.batch_id``/``batch_size``); a batch
    is handed on once all its members arrived, without the ones ``known`` already (replays)."""

    def __init__(self):
        self._parts: Dict[int, Dict[int, KeyframeData]] = {}

    def add(self, kf: KeyframeData, known: Callable[[int], bool]) -> List[KeyframeData]:
        if kf.batch_size <= 1:
            return [] if known(kf.kf_id) else [kf]
        parts = self._parts.setdefault(int(kf.batch_id), {})
        parts[int(kf.kf_id)] = kf
        if len(parts) < kf.batch_size:
            return []
        del self._parts[int(kf.batch_id)]
        return [parts[k] for k in sorted(parts) if not known(k)]

    def waiting(self) -> int:
        return sum(len(p) for p in self._parts.values())


def _newest_seq(seq: int, events) -> int:
    return max([int(seq)] + [int(e.seq) for e in events])


MIN_DEPTH_FRACTION = 0.01   # a proxy depth anchoring fewer pixels is held by the mapper


def _anchoring_fraction(pd: ProxyDepth, ba_weight: float) -> float:
    """Share of pixels whose depth anchors new Gaussians: full-weight depth (the mapper
    seeds none from down-weighted BA depth in multi-view holes)."""
    d = np.asarray(pd.depth)
    ok = np.isfinite(d) & (d > 0) & (np.asarray(pd.depth_weight(ba_weight)) >= 1)
    return float(ok.mean()) if ok.size else 0.0


def _ack(kf: KeyframeData) -> Tuple[int, int, float]:
    return int(kf.frame_index), int(kf.kf_id), float(kf.timestamp)


def _persist_events(store: Optional[KeyframeStore], events, meta: dict) -> None:
    """New poses / disparities of stored keyframes, committed with ``meta`` in one step."""
    if store is None:
        return
    staged = {}
    for ev in events:
        for i, k in enumerate(ev.kf_ids):
            staged.update(store.update_keyframe(
                k, pose=ev.poses[i],
                disparity=None if ev.disparities is None else ev.disparities[i], commit=False))
    store.commit(staged, meta)


# ============================================================================ tracker
class TrackerRole:
    """Frames -> local-BA updates + keyframes (§3.1); applies the loop closer's updates.

    With a ``store`` the tracker checkpoints itself after every step that changed the pose
    graph (:mod:`splat_slam_ros.tracking.tracker_state`) and a new role on the same store
    resumes: new keyframe ids and update numbers continue after the published ones, and
    :attr:`resume_stamp` says after which frame the input must continue."""
    name = "tracker"
    update_sources = ("loop",)              # whose PoseGraphUpdates it applies

    def __init__(self, cfg: SlamConfig, intrinsics: Intrinsics, loop_closure: bool,
                 flow_predictor=None, store: Optional[KeyframeStore] = None, tracker=None):
        self.tracker = tracker or Tracker(cfg, intrinsics, flow_predictor=flow_predictor)
        self.intrinsics = intrinsics
        self.wait_loop = bool(loop_closure)
        self.last_seq = 0                   # our newest update
        self.loop_seq = 0                   # the loop closer's newest update applied
        self.loop_final: Optional[int] = None
        self.finalized = False
        self.ckpt = TrackerCheckpoint(store) if store is not None else None
        self.resumed = self.ckpt is not None and self.ckpt.exists
        if self.resumed:
            m = self.ckpt.meta
            self.last_seq, self.loop_seq = int(m.get("last_seq", 0)), int(m.get("loop_seq", 0))
            self.ckpt.restore(self.tracker, max(TRACKER_SEQ_START, self.last_seq + 1))
        elif self.ckpt is not None and "trk_intrinsics" not in self.ckpt.meta:
            # the camera, at once: a crash before the first checkpoint (warm-up) is a restart
            # from the first frame, not a new run
            self.ckpt.store.commit({}, {"trk_intrinsics": intrinsics_to_list(intrinsics)})

    @staticmethod
    def stored_intrinsics(store: Optional[KeyframeStore]) -> Optional[Intrinsics]:
        """The camera a checkpointed tracker ran on (None: nothing to resume)."""
        if store is None or "trk_intrinsics" not in store.meta:
            return None
        return intrinsics_from_list(store.meta["trk_intrinsics"])

    @property
    def resume_stamp(self) -> Optional[float]:
        """Timestamp of the newest frame the restored tracker holds (None: from the start)."""
        return self.ckpt.resume_stamp if self.resumed else None

    def _checkpoint(self, published=(), events=None) -> None:
        if self.ckpt is None:
            return
        meta = {"last_seq": self.last_seq, "loop_seq": self.loop_seq,
                "trk_intrinsics": intrinsics_to_list(self.intrinsics)}
        if events is not None:              # what the step sent: sent again after a restart
            meta["trk_last_events"] = [[int(e.seq), e.reason, [int(k) for k in e.kf_ids]]
                                       for e in events]
        self.ckpt.save(self.tracker, published, meta)

    def resume_outbox(self) -> Outbox:
        """After a restart: the window's published keyframes and the last step's updates again
        (a crash may have come between the checkpoint and the messages; consumers skip the
        ids / update numbers they hold)."""
        out = Outbox()
        if not self.resumed:
            return out
        trk = self.tracker
        for k in trk.window:
            if k in trk.published and self.ckpt.store.has(f"timg{k}"):
                kd = trk._keyframe_data(k)
                kd.image = self.ckpt.store.get(f"timg{k}")["image"]
                out.keyframes.append(kd)
        for seq, reason, ids in self.ckpt.meta.get("trk_last_events", []):
            ids = [k for k in ids if k in trk.kfs]
            if ids:
                out.updates.append(trk.kfs.update_event(int(seq), reason, ids))
        return out

    def on_frame(self, frame: Frame) -> Tuple[TrackStep, Outbox]:
        step = self.tracker.track(frame)
        kfs = list(step.keyframes)
        if len(kfs) > 1:                    # the warm-up's keyframes: one batch
            for kf in kfs:
                kf.batch_id, kf.batch_size = int(kfs[0].kf_id), len(kfs)
        self.last_seq = _newest_seq(self.last_seq, step.events)
        if kfs or step.events:
            self._checkpoint(kfs, list(step.events))
        return step, Outbox(updates=list(step.events), keyframes=kfs)

    def on_update(self, ev: UpdateEvent) -> Outbox:
        if ev.source not in self.update_sources or ev.seq <= self.loop_seq:   # ours, a replay
            return Outbox()
        self.tracker.apply_update(ev)
        self.loop_seq = int(ev.seq)
        self._checkpoint()
        return Outbox()

    def finalize(self) -> Outbox:
        """End of the input: last local BA and the trajectory filler's final pass."""
        if self.finalized:
            return Outbox()
        evs = list(self.tracker.finalize())
        self.last_seq = _newest_seq(self.last_seq, evs)
        self.finalized = True
        kfs = list(self.tracker.final_keyframes)    # a late initialisation's (one batch)
        for kf in kfs:
            kf.batch_id, kf.batch_size = int(kfs[0].kf_id), len(kfs)
        self._checkpoint(events=evs)
        return Outbox(updates=evs, keyframes=kfs, final={"last_seq": self.last_seq,
                                          "keyframes": len(self.tracker.published)})

    def on_final(self, node: str, info: dict) -> Outbox:
        if node == "loop_closure":
            self.loop_final = int(info.get("last_seq", 0))
        return Outbox()

    @property
    def complete(self) -> bool:
        """Final, and every update of the loop closer's final global BA applied."""
        if not self.finalized:
            return False
        return not self.wait_loop or (self.loop_final is not None and
                                      self.loop_seq >= self.loop_final)


# ============================================================================ loop closure
class LoopRole:
    """Keyframes -> loop closure, online global BA and final global BA updates (§3.1)."""
    name = "loop_closure"
    update_sources = ("tracker",)

    def __init__(self, cfg: SlamConfig, store: Optional[KeyframeStore] = None,
                 flow_predictor=None):
        self.cfg = cfg
        self.flow = flow_predictor
        self.loop: Optional[LoopCloser] = None
        self.kf_ids: Dict[int, float] = {}
        self.trk_seq = 0                     # the tracker's newest update applied
        self.last_seq = 0                    # our newest update
        self.trk_final: Optional[int] = None
        self.finalized = False
        self.batcher = KeyframeBatcher()
        self.store = store
        if store is not None and store.exists:
            self._resume()

    def _make(self, intr: Intrinsics) -> LoopCloser:
        return LoopCloser(self.cfg, intr, flow_predictor=self.flow,
                          seq_start=max(LOOP_SEQ_START, self.last_seq + 1))

    def _resume(self) -> None:
        meta = self.store.meta
        self.trk_seq = int(meta.get("trk_seq", 0))
        self.last_seq = int(meta.get("last_seq", 0))
        kfs = self.store.keyframes()
        if kfs:
            self.loop = self._make(kfs[0].intrinsics)
            for kf in kfs:
                self.loop.add_keyframe(kf)
                self.kf_ids[kf.kf_id] = kf.timestamp
            self._restore_loop_edges(meta)

    def add_fixed(self, kfs: List[KeyframeData]) -> None:   # a loaded map's (extend runs)
        for kf in kfs:
            self.loop = self.loop or self._make(kf.intrinsics)
            self.loop.add_fixed(kf)
            self.kf_ids[kf.kf_id] = kf.timestamp

    def meta(self) -> dict:
        m = {"trk_seq": self.trk_seq, "last_seq": self.last_seq}
        if self.loop is not None:
            # a pair is listed once its edge records are committed (the same commit or an
            # earlier one): a crash in between must not keep a loop without its edges
            st = self.store
            unsaved = {p for p in self.loop.loop_pairs if st is not None and not (
                st.has(f"loop{int(p[0])}_{int(p[1])}") or st.has(f"loop{int(p[1])}_{int(p[0])}"))}
            m.update(loop_pairs=sorted([int(a), int(o)] for a, o in self.loop.loop_pairs
                                       if (a, o) not in unsaved),
                     checked=sorted([int(a), int(o)] for a, o in self.loop.checked
                                    if (a, o) not in unsaved),
                     n_loops=int(self.loop.n_loops) - len(unsaved), merged=self.loop.merged_list())
        return m

    def _loop_edges_staged(self) -> dict:
        """Loop edges of the graph not stored yet, one record per directed edge: the flow
        targets and weights (Eq. 1 terms) a restarted loop closer could not measure again
        once the older keyframe's image left its buffer."""
        staged = {}
        if self.store is None or self.loop is None:
            return staged
        g = self.loop.graph
        for (i, j), kind in sorted(g.kind.items()):
            name = f"loop{int(i)}_{int(j)}"
            if kind == "loop" and not self.store.has(name):
                staged[name] = self.store.stage(name, target=g.edges[(i, j)][0].cpu().numpy(),
                                                weight=g.edges[(i, j)][1].cpu().numpy())
        return staged

    def _restore_loop_edges(self, meta: dict) -> None:
        g = self.loop.graph
        for name in self.store.names():
            if name.startswith("loop") and "_" in name:
                i, j = (int(x) for x in name[4:].split("_"))
                if i in self.kf_ids and j in self.kf_ids:
                    rec = self.store.get(name)
                    g.edges[(i, j)] = (torch.as_tensor(rec["target"], device=g.device),
                                       torch.as_tensor(rec["weight"], device=g.device))
                    g.age[(i, j)], g.kind[(i, j)] = 0, "loop"
        self.loop.loop_pairs |= {(int(a), int(o)) for a, o in meta.get("loop_pairs", [])}
        self.loop.checked |= {(int(a), int(o)) for a, o in meta.get("checked", [])}
        self.loop.n_loops = int(meta.get("n_loops", len(self.loop.loop_pairs)))
        self.loop.restore_merged(meta.get("merged", []))

    def on_keyframe(self, kf: KeyframeData) -> Outbox:
        # a replay of a keyframe consumed before a restart is acked again: the first ack may
        # have died with the old process, and the lockstep player waits for it
        again = [_ack(kf)] if kf.kf_id in self.kf_ids else []
        batch = self.batcher.add(kf, lambda k: k in self.kf_ids)
        if not batch:
            return Outbox(acks=again)
        for k in batch:
            if self.loop is None:
                self.loop = self._make(k.intrinsics)
            self.loop.add_keyframe(k)
            self.kf_ids[k.kf_id] = k.timestamp
        events = self.loop.step()           # loop detection + loop BA / online global BA
        self.last_seq = _newest_seq(self.last_seq, events)
        if self.store is not None:
            for k in batch:
                self.store.put_keyframe(k, meta=self.meta())
            _persist_events(self.store, events, self.meta())
            staged = self._loop_edges_staged()
            self.store.commit(staged, None)          # the edge records ...
            self.store.commit({}, self.meta())       # ... then the pairs that use them
        return Outbox(updates=events, acks=again + [_ack(k) for k in batch])

    def on_update(self, ev: UpdateEvent) -> Outbox:
        if ev.source not in self.update_sources or ev.seq <= self.trk_seq:
            return Outbox()
        if self.loop is not None:
            self.loop.apply_update(ev)
        self.trk_seq = int(ev.seq)
        _persist_events(self.store, [ev], self.meta())
        return self._check_final()

    def on_final(self, node: str, info: dict) -> Outbox:
        if node == "tracker":
            self.trk_final = int(info.get("last_seq", 0))
            return self._check_final()
        return Outbox()

    def _check_final(self) -> Outbox:
        if self.finalized or self.trk_final is None or self.trk_seq < self.trk_final:
            return Outbox()
        self.finalized = True
        events = self.loop.finalize() if self.loop is not None else []   # final global BA
        self.last_seq = _newest_seq(self.last_seq, events)
        _persist_events(self.store, events, self.meta())
        if self.store is not None:
            self.store.commit(self._loop_edges_staged(), None)
            self.store.commit({}, self.meta())
        return Outbox(updates=list(events), final={
            "last_seq": self.last_seq, "keyframes": len(self.kf_ids),
            **(self.loop.loop_stats() if self.loop is not None else {"merged": 0})})


# ============================================================================ proxy depth
class DepthRole:
    """Keyframes + updates -> proxy depth (Eq. 4-6, 10), one ordered stream per keyframe (§3.2)."""
    name = "depth"
    update_sources = ("tracker", "loop")

    def __init__(self, cfg: SlamConfig, loop_closure: bool, store: Optional[KeyframeStore] = None):
        self.cfg = cfg
        self.wait_loop = bool(loop_closure)
        self.est: Optional[ProxyDepthEstimator] = None
        self.kf_stamp: Dict[int, float] = {}
        self.pending: Dict[int, tuple] = {}       # updates that overtook their keyframe
        self.revision: Dict[int, int] = {}        # kf_id -> last revision sent
        self.seq = {"tracker": 0, "loop": 0}
        self.final: Dict[str, Optional[int]] = {"tracker": None, "loop": None}
        self.finalized = False
        self.batcher = KeyframeBatcher()
        self.store = store
        if store is not None and store.exists:
            self._resume()

    def meta(self) -> dict:
        return {"seq": self.seq, "revision": {str(k): v for k, v in self.revision.items()},
                "dirty": sorted(self.est.dirty) if self.est is not None else []}

    def _resume(self) -> None:
        meta = self.store.meta
        self.seq.update(meta.get("seq", {}))
        self.revision = {int(k): int(v) for k, v in meta.get("revision", {}).items()}
        kfs = self.store.keyframes()
        if kfs:
            self.est = ProxyDepthEstimator(self.cfg, kfs[0].intrinsics)
            self.est.add_keyframes(kfs)
            self.est.take_refreshed()
            self.kf_stamp = {kf.kf_id: kf.timestamp for kf in kfs}
            # moved by deferred updates before the crash: sent at a new revision by current()
            self.est.dirty.update(int(k) for k in meta.get("dirty", []))

    def current(self, kf_ids: Optional[List[int]] = None) -> Outbox:
        """The latest proxy depth of every keyframe (or of ``kf_ids``) at its current revision:
        after a restart this node's earlier messages left with its DDS history, and a mapper
        that lacks a revision of the final digest asks for it again (consumers skip what they
        have). Unknown ids are ignored."""
        out = self._flush()
        if self.est is not None:
            for k in sorted(self.kf_stamp if kf_ids is None else set(kf_ids) & set(self.kf_stamp)):
                res = self.est.get(k)
                if res is not None and k in self.revision:
                    out.proxy_depths.append(self._wrap(res, True, self.revision[k]))
        return out

    def _wrap(self, res: ProxyDepthResult, is_update: bool, revision: int) -> ProxyDepth:
        return ProxyDepth(kf_id=int(res.kf_id), depth=res.depth, source=res.source,
                          pose=res.pose, update_seq=int(res.update_seq), is_update=is_update,
                          timestamp=self.kf_stamp.get(int(res.kf_id), 0.0), revision=revision)

    def _send(self, res: ProxyDepthResult, is_update: bool) -> ProxyDepth:
        k = int(res.kf_id)
        self.revision[k] = self.revision.get(k, -1) + 1
        return self._wrap(res, is_update, self.revision[k])

    def _flush(self) -> Outbox:
        """Proxy depths of the keyframes that deferred updates moved (next revisions)."""
        if self.est is None or not self.est.dirty:
            return Outbox()
        return Outbox(proxy_depths=[self._send(new, True) for _old, new in self.est.flush()])

    def on_keyframe(self, kf: KeyframeData) -> Outbox:
        flushed = self._flush()              # deferred updates first, in arrival order
        batch = self.batcher.add(kf, lambda k: k in self.kf_stamp)
        if not batch:
            return flushed
        for k in batch:
            if k.kf_id in self.pending:
                k.pose, disp = self.pending.pop(k.kf_id)
                if disp is not None:
                    k.disparity = disp
            self.kf_stamp[k.kf_id] = k.timestamp
        if self.est is None:
            self.est = ProxyDepthEstimator(self.cfg, batch[0].intrinsics)
        results = self.est.add_keyframes(batch)       # each sees the others as views (Eq. 6)
        out = flushed
        # earlier keyframes that gained a view: their deformation before the new mapping
        out.proxy_depths += [self._send(new, True) for _old, new in self.est.take_refreshed()]
        out.proxy_depths += [self._send(res, False) for res in results]
        if self.store is not None:
            for k in batch:
                self.store.put_keyframe(k, with_image=False, meta=self.meta())
        return out.extend(self._check_final())

    def on_update(self, ev: UpdateEvent, defer: bool = False) -> Outbox:
        """``defer``: a newer update is already waiting (graph node under load): store the
        new poses now, recompute once for both (the mapper needs the latest, not each)."""
        src = ev.source
        if ev.seq <= self.seq[src]:
            return Outbox() if defer else self._flush().extend(self._check_final())
        known_max = max(self.kf_stamp) if self.kf_stamp else -1
        for i, k in enumerate(ev.kf_ids):
            if k > known_max:
                self.pending[int(k)] = (ev.poses[i], None if ev.disparities is None
                                        else ev.disparities[i])
        # the loop closer's poses-only updates move the keyframes it merged (rigid followers)
        follow = src == "loop" and ev.disparities is None
        changed = self.est.apply_update(ev, defer, follow) if self.est is not None else []
        self.seq[src] = int(ev.seq)
        out = Outbox(proxy_depths=[self._send(new, True) for _old, new in changed])
        _persist_events(self.store, [ev], self.meta())
        return out if defer else out.extend(self._check_final())

    def on_final(self, node: str, info: dict) -> Outbox:
        if node == "tracker":
            self.final["tracker"] = int(info.get("last_seq", 0))
        elif node == "loop_closure":
            self.final["loop"] = int(info.get("last_seq", 0))
        return self._flush().extend(self._check_final())

    def _check_final(self) -> Outbox:
        if self.finalized or self.final["tracker"] is None or \
                (self.est is not None and self.est.dirty):
            return Outbox()
        if self.seq["tracker"] < self.final["tracker"]:
            return Outbox()
        if self.wait_loop and (self.final["loop"] is None or self.seq["loop"] < self.final["loop"]):
            return Outbox()
        self.finalized = True
        return Outbox(final={"digest": {str(k): v for k, v in self.revision.items()},
                             "keyframes": len(self.kf_stamp)})


# ============================================================================ mapper
class MapperRole:
    """Keyframes + proxy depths -> Gaussian map (Eq. 11), deformed by every newer depth (§3.2)."""
    name = "mapper"
    update_sources = ("tracker", "loop")

    def __init__(self, cfg: SlamConfig, store: Optional[KeyframeStore] = None,
                 snapshot_every: int = 1):
        self.cfg = cfg
        self.mapper: Optional["Mapper"] = None   # noqa: F821 (mapping.mapper, imported in _map)
        self.intr: Optional[Intrinsics] = None
        self.pending_kf: Dict[int, KeyframeData] = {}
        self.pending_depth: Dict[int, ProxyDepth] = {}
        self.offered: Dict[int, bool] = {}          # kf_id -> mapped?
        self.taken: Dict[int, int] = {}             # kf_id -> last revision taken
        self.last_update_seq = 0
        self.digest: Optional[Dict[int, int]] = None
        self.finalized = False
        self.dirty: set = set()                     # keyframes whose depth changed
        self.held: set = set()                      # acked, waiting for a depth (see _try_map)
        self.gone: set = set()                      # merged since the last snapshot
        self.loop_seen = False                      # a loop closer's updates arrive
        self.settled: set = set()                   # keyframes loop closure has corrected
        self.newest_kf = -1
        self.background_mark = 0                    # Mapper.background_iters at the last keyframe
        self.input_waiting: Optional[Callable[[], bool]] = None  # the node's queue (live)
        self.snapshot_every = max(1, int(snapshot_every))
        self.n_since_snapshot = 0
        self.timings: Dict[str, float] = {"mapping": 0.0, "deformation": 0.0, "refine": 0.0}
        self.store = store
        if store is not None and store.exists:
            self._resume()

    # ------------------------------------------------------------ persistence
    def _resume(self) -> None:
        meta = self.store.meta
        self.offered = {int(k): bool(v) for k, v in meta.get("offered", {}).items()}
        self.taken = {int(k): int(v) for k, v in meta.get("taken", {}).items()}
        self.last_update_seq = int(meta.get("last_update_seq", 0))
        if self.store.has("map") and meta.get("intrinsics"):
            self.intr = Intrinsics(*meta["intrinsics"][:4], *map(int, meta["intrinsics"][4:6]))
            self.mapper = restore_mapper(self.store.get("map"), meta["map"], self.cfg, self.intr,
                                         lambda k: self.store.get(f"kf{k}_image")["image"],
                                         lambda k: self.store.get(f"kf{k}_mdepth"))

    def snapshot(self) -> None:
        """Commit the map with exactly the inputs it reflects (offered, taken revisions)."""
        if self.store is None or self.mapper is None:
            return
        arrays, meta = mapper_state(self.mapper)
        staged = {f"kf{k}_mdepth": self.store.stage(f"kf{k}_mdepth",
                                                     **keyframe_depth(self.mapper, k))
                  for k in sorted(self.dirty) if k in self.mapper.keyframes}
        staged.update({f"kf{k}_image": self.store.stage(f"kf{k}_image", image=np.asarray(
            self.mapper.keyframes[k].image.cpu(), np.uint8)) for k in sorted(self.dirty) if
            k in self.mapper.keyframes and not self.store.has(f"kf{k}_image")})
        for k in sorted(self.gone):                    # merged keyframes: records deleted
            staged[f"kf{k}_mdepth"] = staged[f"kf{k}_image"] = None
        self.dirty.clear()
        self.gone.clear()
        i = self.intr
        staged["map"] = self.store.stage("map", **arrays)
        self.store.commit(staged, {"map": meta,
                                   "offered": {str(k): v for k, v in self.offered.items()},
                                   "taken": {str(k): v for k, v in self.taken.items()},
                                   "intrinsics": [i.fx, i.fy, i.cx, i.cy, i.width, i.height],
                                   "last_update_seq": self.last_update_seq})
        self.n_since_snapshot = 0

    def restore(self, mapper: "Mapper", intr: Intrinsics) -> None:  # noqa: F821
        """Start from a loaded map (extend runs): its keyframes count as mapped."""
        self.mapper, self.intr = mapper, intr
        self.offered = {int(k): True for k in mapper.keyframes}
        self.dirty = set(self.offered)
        self.snapshot()

    def reset(self) -> None:
        """Drop the map and everything it consumed; the next keyframes start a new map."""
        self.mapper = None
        for d in (self.pending_kf, self.pending_depth, self.offered, self.taken, self.dirty,
                  self.gone, self.settled):
            d.clear()
        if self.store is not None:
            self.store.clear()

    def save(self, directory: Path, final: bool = False) -> dict:
        """map.ply (+ map_mesh.ply), renders/ and metrics of the map now (``final``: mapper_metrics.json, the
        tracker writes the run's trajectories; else also trajectory_keyframes + metrics.json)."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        metrics: dict = {}
        if self.mapper is None:
            return metrics
        self.mapper.save_ply(d / "map.ply")
        if self.cfg.mapping.mesh:
            # Open3D takes 1.5 s to import: loaded when a mesh is written, not by every stage
            from splat_slam_ros.mapping.mesh import map_mesh_output
            metrics["mesh"] = map_mesh_output(self.mapper, d / "map_mesh.ply")
        metrics.update(self.mapper.evaluate_keyframes(d / "renders"))
        metrics["map"] = self.mapper.stats()
        if not final:
            write_tum(d / "trajectory_keyframes.txt", *self.mapper.keyframe_trajectory())
        (d / ("mapper_metrics.json" if final else "metrics.json")).write_text(
            json.dumps(metrics, indent=2, default=str))
        return metrics

    # ------------------------------------------------------------ inputs
    def on_keyframe(self, kf: KeyframeData) -> Outbox:
        if kf.kf_id in self.offered:        # consumed before a restart: ack again (LoopRole)
            return Outbox(acks=[_ack(kf)])
        if kf.kf_id in self.pending_kf:
            return Outbox()
        self.newest_kf = max(self.newest_kf, int(kf.kf_id))
        self.pending_kf[kf.kf_id] = kf
        return self._try_map()

    def on_proxy_depth(self, pd: ProxyDepth) -> Outbox:
        k = int(pd.kf_id)
        if pd.revision <= self.taken.get(k, -1):        # a replay
            return Outbox()
        if int(pd.update_seq) >= LOOP_SEQ_START:        # made after a loop-closure update
            self.loop_seen = True
            self.settled.add(k)
        if self.mapper is not None and k in self.mapper.keyframes:
            # Map deformation (§3.2): the keyframe's Gaussians follow its new pose and depth
            t0 = time.perf_counter()
            self.mapper.apply_update(k, pd.pose, pd.depth,
                                     pd.depth_weight(self.cfg.mapping.ba_depth_weight))
            self.taken[k] = int(pd.revision)
            self.dirty.add(k)
            self._merge_revisit(k, pd)
            self.timings["deformation"] += time.perf_counter() - t0
            self.last_update_seq = max(self.last_update_seq, int(pd.update_seq))
            out = Outbox()
        elif k in self.offered:                         # consumed, not mapped (redundant view)
            self.taken[k] = int(pd.revision)
            out = Outbox()
        else:
            old = self.pending_depth.get(k)
            if old is None or pd.revision > old.revision:
                self.pending_depth[k] = pd
            out = self._try_map()
        return out.extend(self._check_final())

    def on_update(self, ev: UpdateEvent) -> Outbox:  # deformation: the ProxyDepth stream
        self.last_update_seq = max(self.last_update_seq, int(ev.seq))
        self.loop_seen |= int(ev.seq) >= LOOP_SEQ_START
        return Outbox()

    def on_final(self, node: str, info: dict) -> Outbox:
        if node == "depth":
            self.digest = {int(k): int(v) for k, v in (info.get("digest") or {}).items()}
            return self._try_map()                  # held keyframes: mapped with what is there
        return Outbox()

    # ------------------------------------------------------------ work
    def _try_map(self) -> Outbox:
        """Map every keyframe that has its depth. A proxy depth with (almost) no valid pixel
        (revision 0 of a keyframe that had no views yet: the first of a small warm-up batch)
        would anchor no Gaussians and leave the map without a scene depth: such a keyframe
        is acked (lockstep goes on) and held until a revision with depth or the final digest.
        In revisit mode a keyframe is also held until loop closure has corrected its pose
        (:meth:`_unsettled`)."""
        out = Outbox()
        for k in sorted(self.pending_kf):
            if k not in self.pending_depth:
                continue
            pd = self.pending_depth[k]
            thin = _anchoring_fraction(pd, self.cfg.mapping.ba_depth_weight) < MIN_DEPTH_FRACTION
            if self.digest is None and (thin or self._unsettled(k)):
                if k not in self.held:
                    self.held.add(k)
                    out.acks.append(_ack(self.pending_kf[k]))
                continue
            out.extend(self._map(self.pending_kf.pop(k), self.pending_depth.pop(k)))
        return out.extend(self._check_final())

    def _unsettled(self, k: int) -> bool:
        """Revisit mode (``mapping.revisit_cull_deg``) with a loop closer: mapped with the
        tracker's drifting pose a revisit looks like a new place (duplicate Gaussians). Such a
        keyframe waits, acked, for a depth revision made after a loop-closure update, for at
        most ``mapping.window_size`` newer keyframes (then mapped, merged later if need be),
        or the final digest; the map's first keyframe never waits."""
        return (self.cfg.mapping.revisit_cull_deg > 0 and self.loop_seen and
                self.mapper is not None and bool(self.mapper.keyframes) and
                k not in self.settled and self.newest_kf - k < self.cfg.mapping.window_size)

    def _revisit(self, pd: ProxyDepth, exclude: Optional[int] = None) -> Optional[int]:
        """The mapped keyframe (other than ``exclude``) nearest to ``pd``'s keyframe that sees
        what it sees (``mapping.revisit_cull_deg``: centre within kf_translation x median
        depth, optical axes within that angle); None when there is none or the test is off."""
        mc = self.cfg.mapping
        if mc.revisit_cull_deg <= 0 or self.mapper is None or not self.mapper.keyframes:
            return None
        d = np.asarray(pd.depth, np.float32)
        ok = (d > 0) if pd.valid is None else (np.asarray(pd.valid, bool) & (d > 0))
        med = float(np.median(d[ok])) if ok.any() else 0.0
        T = np.asarray(pd.pose, np.float64)
        cos_max = np.cos(np.radians(mc.revisit_cull_deg))
        best = None
        for k, m in self.mapper.keyframes.items():
            if k == exclude:
                continue
            P = np.asarray(m.pose, np.float64)
            dist = float(np.linalg.norm(P[:3, 3] - T[:3, 3]))
            if dist < mc.kf_translation * med and float(P[:3, 2] @ T[:3, 2]) > cos_max and \
                    (best is None or dist < best[0]):
                best = (dist, k)
        return None if best is None else best[1]

    def _merge_revisit(self, k: int, pd: ProxyDepth) -> None:
        """Keyframe ``k`` (mapped) moved: a new keyframe is mapped with the tracker's pose
        before loop closure corrects it, so a revisit is often recognised only after a later
        update. When ``k`` now sees what another mapped keyframe sees, the newer of the two
        is merged into the older (``Mapper.merge_keyframe``: its Gaussians in the older view
        are removed as duplicates, the rest follow the older keyframe), so keyframes and
        Gaussians stay bounded in a revisited room."""
        twin = self._revisit(pd, exclude=k)
        if twin is None:
            return
        drop, keep = max(k, twin), min(k, twin)
        if self.mapper.keyframes[drop].index == 0:       # the exposure gauge stays
            drop, keep = keep, drop
        self.mapper.merge_keyframe(drop, keep)
        self.offered[drop] = False                      # later revisions: taken, not applied
        self.dirty.discard(drop)
        self.gone.add(drop)

    def _map(self, kf: KeyframeData, pd: ProxyDepth) -> Outbox:
        t0 = time.perf_counter()
        if self.mapper is None:
            # imported here: the mapper (and scipy) is ~30 MB a tracking-only run never needs
            from splat_slam_ros.mapping.mapper import Mapper
            self.intr = kf.intrinsics
            self.mapper = Mapper(self.cfg, kf.intrinsics)
        twin = self._revisit(pd)
        cov = 0.0                           # a render, only when the pose test found no twin
        if twin is None and self.cfg.mapping.revisit_cull_deg > 0:
            cov = self.mapper.coverage(pd.pose)
        if twin is not None or cov >= self.cfg.mapping.revisit_coverage:
            # a revisit: consumed, not mapped (bounded map)
            st = dict(self.mapper.stats(), kf_id=int(kf.kf_id), mapped=False,
                      reason=f"revisit of {twin}" if twin is not None else
                      f"map covers {cov:.0%} of its view")
        else:
            st = self.mapper.add_keyframe(kf.kf_id, kf.image, pd.pose, pd.depth,
                                          pd.depth_weight(self.cfg.mapping.ba_depth_weight),
                                          timestamp=kf.timestamp, yield_to=self.input_waiting)
        self.timings["mapping"] += time.perf_counter() - t0
        mapped = bool(st.get("mapped"))
        self.background_mark = self.mapper.background_iters     # a new allowance
        self.offered[kf.kf_id] = mapped
        self.taken[kf.kf_id] = int(pd.revision)
        if mapped:
            self.dirty.add(kf.kf_id)
        self.n_since_snapshot += 1
        if self.n_since_snapshot >= self.snapshot_every:
            self.snapshot()
        info = dict(st, kf_id=int(kf.kf_id), pose=pd.pose, timestamp=float(kf.timestamp),
                    n_mapped=sum(self.offered.values()))
        held = kf.kf_id in self.held
        self.held.discard(kf.kf_id)
        return Outbox(acks=[] if held else [_ack(kf)], mapped=[info])

    def wants_background(self) -> bool:
        """Live input (``mapping.time_budget``): steps left of ``mapping.background_steps``
        since the last mapped keyframe, until the final refinement. The node runs them
        (:meth:`background`) while no input waits, and sets ``input_waiting``: input that
        arrives cuts a keyframe's or the background's steps."""
        m = self.mapper
        return (self.cfg.mapping.time_budget and m is not None and not self.finalized and
                m.background_iters - self.background_mark < self.cfg.mapping.background_steps)

    def background(self, steps: int = 4) -> None:
        self.mapper.background(steps, self.input_waiting)

    def lacking(self) -> List[int]:
        """Keyframes whose revision in the depth stage's final digest this stage has not taken
        (empty before the digest and once final). A node asks the depth stage to send them
        again: a DDS history can drop a message that a burst of newer ones overtook."""
        if self.digest is None or self.finalized:
            return []
        return [k for k, rev in sorted(self.digest.items()) if self.taken.get(k, -1) < rev]

    def _check_final(self) -> Outbox:
        if self.digest is None or self.finalized or self.lacking():
            return Outbox()
        self.finalized = True
        info: dict = {"keyframes": sum(self.offered.values())}
        if self.mapper is not None:
            t0 = time.perf_counter()
            info["refine"] = self.mapper.final_refine()
            self.timings["refine"] += time.perf_counter() - t0
            self.snapshot()
        return Outbox(final=info)
