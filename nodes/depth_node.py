"""depth_node: keyframes + pose-graph updates -> ProxyDepthEstimator -> ProxyDepth.

Subscribes  /splat/keyframes (Keyframe), /splat/pose_graph_updates (all reasons),
            /splat/graph_events (finalisation).
Publishes   /splat/proxy_depth (ProxyDepth): one per new keyframe (is_update false) and one
            per keyframe whose pose / depth changed after an update (is_update true, with
            update_seq = PoseGraphUpdate.seq). This one ordered stream is what the mapper
            deforms from, so no update can reach it out of order.
Mono depth runs when ``depth.mono_model`` is set (or comes with the keyframe).
Crash safety: keyframes (pose, disparity, confidence, mono depth) and the identities of the
messages already handled are persisted to ``node.state_dir``; a restarted node rebuilds its
estimator from there and skips messages it already handled when DDS replays them.
"""
from __future__ import annotations

import sys
import threading
import time
from typing import Dict, List

from .node_common import TOPICS, TRACKER_REASONS, SplatNode, raw_hash, run_node

SEEN_KEEP = 5000
BURST_GAP_S = 0.05       # keyframes arriving closer than this are one burst (warm-up)


class DepthNode(SplatNode):
    def __init__(self):
        super().__init__("depth", {"loop_closure": True, "mapping": True})
        from splat_slam_msgs.msg import Keyframe, PoseGraphUpdate, ProxyDepth

        from . import qos as Q
        n = self.node
        self.pub = n.create_publisher(ProxyDepth, TOPICS["proxy_depth"], Q.proxy_depth_qos())
        import splat_slam_ros.depth.proxy_depth  # noqa: F401  (torch before 'ready')
        self.est = None
        self.kf_stamp: Dict[int, float] = {}
        self.pending: Dict[int, tuple] = {}       # updates for keyframes not received yet
        self.seen: Dict[str, None] = {}
        self.digest: Dict[str, str] = {}          # kf_id -> hash of the last ProxyDepth sent
        self.seq = {"tracker": 0, "loop": 0}
        self.final = {"tracker": None, "loop": None}
        self.finalized = False
        self.store = None
        if self.state_dir is not None:
            from splat_slam_ros.io.keyframe_store import KeyframeStore
            self.store = KeyframeStore(self.state_dir)
            if self.store.exists:
                self._resume()
        self.subscribe(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos(),
                       lambda m, raw: self.worker.submit(self._update, m, raw_hash(raw)),
                       "PoseGraphUpdate")
        self.inbox: List[tuple] = []
        self.inbox_lock = threading.Lock()
        self.last_kf_arrival = 0.0
        self.subscribe(Keyframe, TOPICS["keyframes"], Q.keyframe_qos(), self._on_keyframe,
                       "Keyframe")
        self.on_events(lambda d: self.worker.submit(self._event, d))
        self.publish_event("ready")

    # ------------------------------------------------------------ persistence
    def _resume(self) -> None:
        from splat_slam_ros.depth.proxy_depth import ProxyDepthEstimator
        meta = self.store.meta
        kfs = self.store.keyframes()
        self.seen = dict.fromkeys(meta.get("seen", []))
        self.digest = dict(meta.get("digest", {}))
        self.seq.update(meta.get("seq", {}))
        if kfs:
            self.est = ProxyDepthEstimator(self.cfg, kfs[0].intrinsics)
            self.est.add_keyframes(kfs)
            self.est.take_refreshed()
            self.kf_stamp = {kf.kf_id: kf.timestamp for kf in kfs}
            # what this node published before it died left with its DDS history: publish
            # the current proxy depth of every keyframe again (a consumer that already has
            # it skips the identical message or applies a no-op update)
            for kf in kfs:
                res = self.est.get(kf.kf_id)
                if res is not None:
                    self._publish(res, True)
        self.log.info(f"resumed from {self.state_dir}: {len(kfs)} keyframes, "
                      f"{len(self.seen)} handled messages")

    def _meta(self) -> dict:
        seen = list(self.seen)[-SEEN_KEEP:]
        return {"seen": seen, "digest": self.digest, "seq": self.seq}

    def _mark(self, h: str) -> None:
        self.seen[h] = None
        if len(self.seen) > 2 * SEEN_KEEP:
            for k in list(self.seen)[:SEEN_KEEP]:
                del self.seen[k]

    # ------------------------------------------------------------ work
    def _publish(self, res, is_update: bool) -> None:
        from rclpy.serialization import serialize_message

        from .convert import proxy_depth_to_msg
        m = proxy_depth_to_msg(res.kf_id, res.depth, res.source, res.pose, res.update_seq,
                               is_update, self.kf_stamp.get(res.kf_id, 0.0), self.frame_id)
        raw = serialize_message(m)
        self.digest[str(res.kf_id)] = raw_hash(raw)
        self.pub.publish(raw)

    def _on_keyframe(self, msg, raw) -> None:
        with self.inbox_lock:
            self.inbox.append((msg, raw_hash(raw)))
            self.last_kf_arrival = time.monotonic()
        self.worker.submit(self._keyframes)

    def _keyframes(self) -> None:
        """All keyframes received so far, as one batch: the tracker's warm-up publishes
        several at once, and each must see the others as views (Eq. 5)."""
        from splat_slam_ros.depth.proxy_depth import ProxyDepthEstimator

        from .convert import msg_to_keyframe
        while time.monotonic() - self.last_kf_arrival < BURST_GAP_S:
            time.sleep(0.01)
        with self.inbox_lock:
            batch, self.inbox = self.inbox, []
        kfs, hashes = [], []
        for msg, h in batch:
            if h in self.seen:
                continue
            kf = msg_to_keyframe(msg)
            if (self.est is not None and kf.kf_id in self.est) or \
                    any(k.kf_id == kf.kf_id for k in kfs):
                self._mark(h)
                self.warn_throttled("dup-kf", f"keyframe {kf.kf_id} received twice with "
                                    "different content; keeping the first", error=False)
                continue
            if kf.kf_id in self.pending:              # an update overtook its keyframe
                pose, disp = self.pending.pop(kf.kf_id)
                kf.pose = pose
                if disp is not None:
                    kf.disparity = disp
            kfs.append(kf)
            hashes.append(h)
        if not kfs:
            return
        if self.est is None:
            self.est = ProxyDepthEstimator(self.cfg, kfs[0].intrinsics)
        for kf in kfs:
            self.kf_stamp[kf.kf_id] = kf.timestamp
        results = self.est.add_keyframes(kfs)
        for _old, new in self.est.take_refreshed():   # deformations before new mapping
            self._publish(new, True)
        for res in results:
            self._publish(res, False)
        for h in hashes:
            self._mark(h)
        if self.store is not None:
            for kf in kfs:
                self.store.put_keyframe(kf, with_image=False, meta=self._meta())
        self._check_final()

    def _update(self, msg, h: str) -> None:
        from .convert import msg_to_update
        if h in self.seen:
            return
        ev = msg_to_update(msg)
        src = "tracker" if ev.reason in TRACKER_REASONS else "loop"
        known_max = max(self.kf_stamp) if self.kf_stamp else -1
        for i, k in enumerate(ev.kf_ids):
            if k > known_max:
                self.pending[int(k)] = (ev.poses[i], None if ev.disparities is None
                                        else ev.disparities[i])
        changed = self.est.apply_update(ev) if self.est is not None else []
        for _old, new in changed:
            self._publish(new, True)
        self.seq[src] = max(self.seq[src], int(ev.seq))
        self._mark(h)
        if self.store is not None:
            staged = {}
            for i, k in enumerate(ev.kf_ids):
                staged.update(self.store.update_keyframe(
                    k, pose=ev.poses[i],
                    disparity=None if ev.disparities is None else ev.disparities[i],
                    commit=False))
            self.store.commit(staged, self._meta())
        self._check_final()

    def _event(self, d: dict) -> None:
        if d.get("event") != "finalized":
            return
        if d.get("node") == "tracker":
            self.final["tracker"] = int(d.get("last_seq", 0))
        elif d.get("node") == "loop_closure":
            self.final["loop"] = int(d.get("last_seq", 0))
        self._check_final()

    def _check_final(self) -> None:
        if self.finalized or self.final["tracker"] is None:
            return
        if self.seq["tracker"] < self.final["tracker"]:
            return
        if self.opts["loop_closure"]:
            if self.final["loop"] is None or self.seq["loop"] < self.final["loop"]:
                return
        self.finalized = True
        self.log.info(f"finalized: {len(self.kf_stamp)} keyframes")
        self.publish_event("finalized", digest=self.digest, keyframes=len(self.kf_stamp))


def main(argv=None) -> int:
    return run_node(DepthNode, argv)


if __name__ == "__main__":
    sys.exit(main())
