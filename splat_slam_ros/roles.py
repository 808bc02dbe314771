"""The four stage endpoints of the update protocol, ROS-free.

Each role wraps one stage of the paper and owns everything about its messages that is not
transport: which inputs it takes, in which order, what it recognises as a replay, how it
groups the tracker's warm-up batch, what it persists for a restart and when it is final.
A role never publishes; every handler returns an :class:`Outbox` of what the stage sends
on. The in-process :class:`~splat_slam_ros.coordinator.Coordinator` routes outboxes between
the four roles; each ROS node wraps one role and turns outboxes into messages. The tracker,
loop-closure and depth roles are here; the mapper's,
:class:`~splat_slam_ros.mapper_role.MapperRole`, is in mapper_role.py.

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

from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.depth.proxy_depth import (ProxyDepthEstimator, ProxyDepthResult,
                                              check_settings as check_depth_settings)
from splat_slam_ros.io.keyframe_store import KeyframeStore
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


def ack(kf: KeyframeData) -> Tuple[int, int, float]:
    """The (frame index, kf_id, timestamp) a stage acknowledges a consumed keyframe with."""
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

    def on_skip(self, frame: Frame) -> None:
        """A frame skipped as a busy live tracker skipped it (posed between its tracked
        neighbours, or tracked later as a bridge)."""
        self.tracker.skip(frame.index, frame.timestamp, frame)

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
        again = [ack(kf)] if kf.kf_id in self.kf_ids else []
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
        return Outbox(updates=events, acks=again + [ack(k) for k in batch])

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
        check_depth_settings(cfg.depth)               # the estimator comes with the first keyframe
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

