"""loop_closure_node: keyframes -> splat_slam_ros.tracking.loop_closure.LoopCloser -> PoseGraphUpdate.

Subscribes  /splat/keyframes (Keyframe), /splat/pose_graph_updates (the tracker's local-BA
            updates -> LoopCloser.apply_update), /splat/graph_events (finalisation).
Publishes   /splat/pose_graph_updates (loop closure, online global BA, final global BA),
            /splat/frame_ack (consumer "loop_closure", one per keyframe handled: lockstep).
Keeps its own keyframe store (the loop closer's keyframes; persisted to ``node.state_dir``
with their latest poses / disparities); a restarted node re-adds them and continues.
"""
from __future__ import annotations

import sys
import threading
import time
from typing import Dict, List, Optional

from .node_common import TOPICS, TRACKER_REASONS, SplatNode, raw_hash, run_node

SEQ_START = 1_000_000_000          # loop-closure update numbers (the tracker's start at 1)
SEEN_KEEP = 5000
BURST_GAP_S = 0.05       # keyframes arriving closer than this are one burst (warm-up)


class LoopClosureNode(SplatNode):
    def __init__(self):
        super().__init__("loop_closure", {"loop_closure": True, "mapping": True})
        from splat_slam_msgs.msg import FrameAck, Keyframe, PoseGraphUpdate

        from . import qos as Q
        n = self.node
        self.pub = n.create_publisher(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos())
        self.pub_ack = n.create_publisher(FrameAck, TOPICS["ack"], Q.ack_qos())
        try:
            import splat_slam_ros.tracking.loop_closure  # noqa: F401  (torch before 'ready')
        except ImportError as e:
            self.log.fatal(f"the loop closure stage is not available: {e}")
            raise SystemExit(3)
        self.loop = None
        self.kf_ids: Dict[int, float] = {}
        self.seen: Dict[str, None] = {}
        self.trk_seq = 0
        self.last_seq = 0
        self.next_seq = SEQ_START
        self.trk_final: Optional[int] = None
        self.finalized = False
        self.store = None
        if self.state_dir is not None:
            from splat_slam_ros.io.keyframe_store import KeyframeStore
            self.store = KeyframeStore(self.state_dir)
            if self.store.exists:
                self._resume()
        self.subscribe(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos(), self._on_update,
                       "PoseGraphUpdate")
        self.inbox: List[tuple] = []
        self.inbox_lock = threading.Lock()
        self.last_kf_arrival = 0.0
        self.subscribe(Keyframe, TOPICS["keyframes"], Q.keyframe_qos(), self._on_keyframe,
                       "Keyframe")
        self.on_events(lambda d: self.worker.submit(self._event, d))
        self.publish_event("ready")

    def _make(self, intr):
        from splat_slam_ros.tracking.loop_closure import LoopCloser
        from splat_slam_ros.config import ConfigError
        try:
            return LoopCloser(self.cfg, intr, seq_start=self.next_seq)
        except TypeError:                     # a LoopCloser without seq_start
            return LoopCloser(self.cfg, intr)
        except ConfigError as e:              # e.g. a bad tracking.flow_model checkpoint
            self.log.fatal(f"cannot start loop closure: {e}")
            raise SystemExit(2)

    def _resume(self) -> None:
        meta = self.store.meta
        self.seen = dict.fromkeys(meta.get("seen", []))
        self.trk_seq = int(meta.get("trk_seq", 0))
        self.last_seq = int(meta.get("last_seq", 0))
        self.next_seq = max(SEQ_START, self.last_seq + 1)
        kfs = self.store.keyframes()
        if kfs:
            self.loop = self._make(kfs[0].intrinsics)
            for kf in kfs:
                self.loop.add_keyframe(kf)
                self.kf_ids[kf.kf_id] = kf.timestamp
        self.log.info(f"resumed from {self.state_dir}: {len(kfs)} keyframes")

    def _meta(self) -> dict:
        return {"seen": list(self.seen)[-SEEN_KEEP:], "trk_seq": self.trk_seq,
                "last_seq": self.last_seq}

    def _persist_events(self, events) -> None:
        if self.store is None:
            return
        staged = {}
        for ev in events:
            for i, k in enumerate(ev.kf_ids):
                staged.update(self.store.update_keyframe(
                    k, pose=ev.poses[i],
                    disparity=None if ev.disparities is None else ev.disparities[i],
                    commit=False))
        self.store.commit(staged, self._meta())

    def _publish(self, events) -> None:
        from .convert import update_to_msg
        for ev in events:
            self.pub.publish(update_to_msg(ev, self.now(), self.frame_id))
            self.last_seq = max(self.last_seq, int(ev.seq))

    # ------------------------------------------------------------ work
    def _on_update(self, msg, raw) -> None:
        from .convert import msg_to_update
        ev = msg_to_update(msg)
        if ev.reason not in TRACKER_REASONS:       # our own updates
            return
        self.worker.submit(self._update, ev, raw_hash(raw))

    def _update(self, ev, h: str) -> None:
        if h in self.seen:
            return
        if self.loop is not None:
            self.loop.apply_update(ev)
        self.trk_seq = max(self.trk_seq, int(ev.seq))
        self.seen[h] = None
        self._persist_events([ev])
        self._check_final()

    def _on_keyframe(self, msg, raw) -> None:
        with self.inbox_lock:
            self.inbox.append((msg, raw_hash(raw)))
            self.last_kf_arrival = time.monotonic()
        self.worker.submit(self._keyframes)

    def _keyframes(self) -> None:
        """The keyframes received so far as one batch (the tracker's warm-up burst), then one
        loop-closure step, as the in-process pipeline does."""
        from .convert import frame_ack_msg, msg_to_keyframe, to_stamp
        while time.monotonic() - self.last_kf_arrival < BURST_GAP_S:
            time.sleep(0.01)
        with self.inbox_lock:
            batch, self.inbox = self.inbox, []
        kfs = []
        for msg, h in batch:
            if h in self.seen:
                continue
            kf = msg_to_keyframe(msg)
            self.seen[h] = None
            if kf.kf_id in self.kf_ids:
                continue
            if self.loop is None:
                self.loop = self._make(kf.intrinsics)
            self.loop.add_keyframe(kf)
            self.kf_ids[kf.kf_id] = kf.timestamp
            kfs.append(kf)
        if not kfs:
            return
        events = self.loop.step()                  # loop detection + loop BA / online global BA
        self._publish(events)
        if self.store is not None:
            for kf in kfs:
                self.store.put_keyframe(kf, meta=self._meta())
            self._persist_events(events)
        for kf in kfs:
            ack = frame_ack_msg(kf.frame_index, "loop_closure", 0.0, kf.kf_id)
            ack.header.stamp = to_stamp(kf.timestamp)
            self.pub_ack.publish(ack)
        if events:
            self.log.info(f"keyframe {kfs[-1].kf_id}: {len(events)} update(s) "
                          f"({', '.join(sorted({e.reason for e in events}))})")

    def _event(self, d: dict) -> None:
        if d.get("node") == "tracker" and d.get("event") == "finalized":
            self.trk_final = int(d.get("last_seq", 0))
            self._check_final()

    def _check_final(self) -> None:
        if self.finalized or self.trk_final is None or self.trk_seq < self.trk_final:
            return
        self.finalized = True
        events = self.loop.finalize() if self.loop is not None else []   # final global BA
        self._publish(events)
        self._persist_events(events)
        self.log.info(f"finalized: {len(self.kf_ids)} keyframes, {len(events)} final update(s)")
        self.publish_event("finalized", last_seq=self.last_seq, keyframes=len(self.kf_ids))


def main(argv=None) -> int:
    return run_node(LoopClosureNode, argv)


if __name__ == "__main__":
    sys.exit(main())
