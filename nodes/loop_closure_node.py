"""loop_closure_node: keyframes -> LoopRole (loop closure + global BA, §3.1) -> PoseGraphUpdate.

Subscribes  /splat/keyframes (Keyframe), /splat/pose_graph_updates (the tracker's local-BA
            updates), /splat/graph_events (the tracker's ``finalized``).
Publishes   /splat/pose_graph_updates (loop closure, online global BA, final global BA),
            /splat/frame_ack (consumer "loop_closure", one per keyframe handled: lockstep).
The protocol is :class:`splat_slam_ros.roles.LoopRole`; its keyframes (latest poses and
disparities) and its loop edges persist in ``node.state_dir``: a restarted node re-adds them,
keeps the accepted loops and continues its update numbers where it stopped.
"""
from __future__ import annotations

import sys

from .node_common import SplatNode, run_node


class LoopClosureNode(SplatNode):
    def __init__(self):
        super().__init__("loop_closure", {"loop_closure": True, "mapping": True})
        from splat_slam_ros.roles import LoopRole
        self.publishers("updates", "ack")
        self.role = LoopRole(self.cfg, store=self.store())
        if self.role.kf_ids:
            self.log.info(f"resumed from {self.state_dir}: {len(self.role.kf_ids)} keyframes, "
                          f"{len(self.role.loop.loop_pairs)} loop edges")
        self.route(self.role, keyframes=True, updates=True, after=self._after)
        self.publish_event("ready")

    def _after(self, out) -> None:
        if out.updates and out.final is None:
            self.log.info(f"keyframe {out.acks[-1][1] if out.acks else '?'}: "
                          f"{len(out.updates)} update(s) "
                          f"({', '.join(sorted({e.reason for e in out.updates}))})")
        if out.final is not None:
            self.log.info(f"finalized: {out.final['keyframes']} keyframes "
                          f"({out.final['merged']} merged into older views), "
                          f"{len(out.updates)} final update(s)")


def main(argv=None) -> int:
    return run_node(LoopClosureNode, argv)


if __name__ == "__main__":
    sys.exit(main())
