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
Outputs: at the end the loop-closure graph (edges, loop pairs, merged keyframes) in
node.output_dir's session/ manifest; the launcher's /splat/save_map the same into DIR.
"""
from __future__ import annotations

import sys

from .map_requests import answer_save, load_request, loaded_by_tracker, reply
from .node_common import SplatNode, run_node
from .node_options import NODE_OPTIONS


class LoopClosureNode(SplatNode):
    def __init__(self):
        super().__init__("loop_closure", NODE_OPTIONS["loop_closure"])
        from splat_slam_ros.roles import LoopRole
        self.publishers("updates", "ack")
        self.role = LoopRole(self.cfg, store=self.store())
        self.loaded = self.loaded_graph = None   # node.load_map: the session's keyframes, graph
        if self.opts["load_map"]:
            from splat_slam_ros.io.session import SessionError
            try:
                self._read(str(self.opts["load_map"]))
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
        self.on_events(self._on_request)
        self.publish_event("ready")

    def _read(self, run: str) -> None:
        from pathlib import Path

        from splat_slam_ros.io.session import load_session, loop_graph
        session = load_session(Path(run))
        self.loaded, self.loaded_graph = session.keyframes, loop_graph(session)

    def _on_request(self, d: dict) -> None:
        if loaded_by_tracker(d, self.started):
            self.worker.submit(self._load_requested, d)
        elif d.get("event") == "save_map" and load_request(d, self.started):
            self.worker.submit(self._save_map, d)

    def _save_map(self, d: dict) -> None:
        """/splat/save_map: the loop-closure graph in DIR/session/'s manifest."""
        from splat_slam_ros.io.session import write_loop_graph

        def write(out):
            write_loop_graph(out, self._summary())
            return ["session/ (loop-closure graph)"]
        answer_save(self, d, write)

    def _summary(self) -> dict:
        lc = self.role.loop
        return lc.graph_summary() if lc is not None else {"edges": [], "loop_pairs": [],
                                                            "merged": []}

    def _load_requested(self, d: dict) -> None:
        """The launcher's /splat/load_map (extend), once the tracker took it."""
        from splat_slam_ros.io.session import SessionError
        if self.role.kf_ids or self.loaded is not None:
            return reply(self, "map_loaded", d, False, "keyframes were consumed already")
        try:
            self._read(str(d.get("run")))
        except SessionError as e:
            return reply(self, "map_loaded", d, False, str(e))
        reply(self, "map_loaded", d, True, f"{len(self.loaded)} keyframes to hold fixed")

    def _add_loaded(self, intrinsics) -> None:
        from splat_slam_ros.io.session import keyframe_data
        self.role.add_fixed(keyframe_data(self.loaded, intrinsics))
        self.role.loop.restore_graph_summary(self.loaded_graph)
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
        if out.final is not None and self.output_dir is not None:
            from splat_slam_ros.io.session import write_loop_graph
            write_loop_graph(self.output_dir, self._summary())   # the session's graph part
        if out.final is not None:
            self.log.info(f"finalized: {out.final['keyframes']} keyframes "
                          f"({out.final['merged']} merged into older views), "
                          f"{len(out.updates)} final update(s)")


def main(argv=None) -> int:
    return run_node(LoopClosureNode, argv)


if __name__ == "__main__":
    sys.exit(main())
