"""depth_node: keyframes + pose-graph updates -> DepthRole (proxy depth, §3.2) -> ProxyDepth.

Subscribes  /splat/keyframes (Keyframe), /splat/pose_graph_updates (all reasons),
            /splat/graph_events (``finalized`` of tracker and loop closure; ``resend_depth``
            {kf_ids} of the mapper: their current proxy depth is published again).
Publishes   /splat/proxy_depth (ProxyDepth): one per new keyframe (revision 0) and one per
            keyframe whose pose / depth changed after an update (is_update, the next
            revision; while more updates wait in the queue, only the newest recomputes).
            This one ordered stream is what the mapper deforms from.
The protocol (warm-up batches, replays, pending updates, finalisation) is
:class:`splat_slam_ros.roles.DepthRole`; crash safety: its KeyframeStore in ``node.state_dir``
— a restarted node resumes from it and publishes the current depth of every keyframe again
(consumers skip the revisions they have).
Errors: a configuration error (``depth.mono_model`` missing, without a valid sidecar or not
loadable, a bad ``depth.*`` value) stops the node with one line and exit status 2 (the model
file and sidecar are checked at start, the network is loaded at the first keyframe); a
malformed message is dropped, logged and counted (``dropped_inputs`` in its graph events).
"""
from __future__ import annotations

import sys

from .node_common import SplatNode, run_node
from .node_options import NODE_OPTIONS

RESEND_MAX = 64           # keyframes re-sent per resend_depth request (bounded bursts)


class DepthNode(SplatNode):
    def __init__(self):
        super().__init__("depth", NODE_OPTIONS["depth"])
        from splat_slam_ros.roles import DepthRole
        if self.cfg.depth.mono_model:      # a bad path / sidecar stops the node now (exit 2)
            from splat_slam_ros.config import ConfigError
            from splat_slam_ros.tracking.mono_depth import check_mono_model
            try:
                check_mono_model(self.cfg.depth.mono_model)
            except ConfigError as e:
                raise ConfigError(f"depth.mono_model: {e}") from None
        self.publishers("proxy_depth")
        self.role = DepthRole(self.cfg, loop_closure=bool(self.opts["loop_closure"]),
                              store=self.store())
        if self.role.kf_stamp:
            self.emit(self.role.current())
            self.log.info(f"resumed from {self.state_dir}: {len(self.role.kf_stamp)} keyframes")
        # under load updates queue up: each moves most keyframes, so all but the newest only
        # store their poses and the newest recomputes once (DepthRole.on_update's defer)
        self.route(self.role, keyframes=True, updates=True, after=self._after,
                   on_update=lambda ev: self.role.on_update(ev, defer=self.waiting["updates"] > 0))
        self.on_events(lambda d: d.get("event") == "resend_depth" and
                       self.worker.submit(self._resend, d.get("kf_ids")))
        self.publish_event("ready")

    def _resend(self, kf_ids) -> None:
        """A consumer lacks these keyframes' latest revision: publish it again."""
        if not isinstance(kf_ids, list) or not all(isinstance(k, int) for k in kf_ids):
            self.warn_throttled("resend", f"dropping a resend_depth request with kf_ids "
                                f"{str(kf_ids)[:80]} (expected a list of integers)")
            return
        out = self.role.current(kf_ids[:RESEND_MAX])
        self.emit(out)
        self.log.info(f"sent the proxy depth of {len(out.proxy_depths)} keyframe(s) again "
                      f"(asked for {len(kf_ids)})")

    def _after(self, out) -> None:
        if out.final is not None:
            self.log.info(f"finalized: {out.final['keyframes']} keyframes")


def main(argv=None) -> int:
    return run_node(DepthNode, argv)


if __name__ == "__main__":
    sys.exit(main())
