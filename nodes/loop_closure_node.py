"""loop_closure_node: keyframes -> LoopRole (loop closure + global BA, §3.1) -> PoseGraphUpdate.

Subscribes  /splat/keyframes (Keyframe), /splat/pose_graph_updates (the tracker's local-BA
            updates), /splat/graph_events (the tracker's ``finalized``).
Publishes   /splat/pose_graph_updates (loop closure, online global BA, final global BA),
            /splat/frame_ack (consumer "loop_closure", one per keyframe handled: lockstep).
The protocol is :class:`splat_slam_ros.roles.LoopRole`; its keyframes (latest poses and
disparities) and its loop edges persist in ``node.state_dir``: a restarted node re-adds them,
keeps the accepted loops and continues its update numbers where it stopped.
Options: node.load_map (set by ``splat-slam-launch --load-map RUN``: the keyframes of the
session RUN saved join before the first new one, held fixed: loops onto the loaded map).
"""
from __future__ import annotations

import sys

from .launch_services import loaded_by_tracker, reply
from .node_common import SplatNode, run_node


class LoopClosureNode(SplatNode):
    def __init__(self):
        super().__init__("loop_closure", {"loop_closure": True, "mapping": True,
                                          "load_map": ""})
        from splat_slam_ros.roles import LoopRole
        self.publishers("updates", "ack")
        self.role = LoopRole(self.cfg, store=self.store())
        self.loaded = None              # node.load_map: the loaded session's keyframes
        if self.opts["load_map"]:
            from pathlib import Path

            from splat_slam_ros.io.session import SessionError, load_session
            try:
                self.loaded = load_session(Path(str(self.opts["load_map"]))).keyframes
            except SessionError as e:
                self.log.fatal(f"cannot load the map: {e}")
                raise SystemExit(2)
        if self.role.kf_ids:
            self.log.info(f"resumed from {self.state_dir}: {len(self.role.kf_ids)} keyframes, "
                          f"{len(self.role.loop.loop_pairs)} loop edges")
            if self.loaded is not None:
                self._add_loaded(self.role.loop.raw_intrinsics)
        self.route(self.role, keyframes=True, updates=True, after=self._after,
                   on_keyframe=self._on_keyframe)
        self.on_events(lambda d: loaded_by_tracker(d, self.started) and
                       self.worker.submit(self._load_requested, d))
        self.publish_event("ready")

    def _load_requested(self, d: dict) -> None:
        """The launcher's /splat/load_map (extend), once the tracker took it."""
        from pathlib import Path

        from splat_slam_ros.io.session import SessionError, load_session
        if self.role.kf_ids or self.loaded is not None:
            return reply(self, "map_loaded", d, False, "keyframes were consumed already")
        try:
            self.loaded = load_session(Path(str(d.get("run")))).keyframes
        except SessionError as e:
            return reply(self, "map_loaded", d, False, str(e))
        reply(self, "map_loaded", d, True, f"{len(self.loaded)} keyframes to hold fixed")

    def _add_loaded(self, intrinsics) -> None:
        from splat_slam_ros.io.session import keyframe_data
        self.role.add_fixed(keyframe_data(self.loaded, intrinsics))
        self.log.info(f"{len(self.loaded)} keyframes of the loaded map held fixed")
        self.loaded = None

    def _on_keyframe(self, kf):
        """Extend runs (node.load_map): before the first new keyframe the loaded ones join,
        fixed in every BA (LoopRole.add_fixed), so loops to them pull the new ones onto the
        loaded map (a restarted node adds them again from the session; the loop edges to
        them it had found before the restart are not restored)."""
        if self.loaded is not None:
            self._add_loaded(kf.intrinsics)
        return self.role.on_keyframe(kf)

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
