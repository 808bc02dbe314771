"""mapper_node: keyframes + proxy depth -> MapperRole (Gaussian map, Eq. 11) -> renders, map, status.

Subscribes  /splat/keyframes (images), /splat/proxy_depth (a keyframe is mapped once its
            depth is there; newer revisions deform its Gaussians, §3.2 "Map Deformation"),
            /splat/pose_graph_updates (reported in MapperStatus.last_update_seq),
            /splat/map/render_request (PoseStamped), /splat/graph_events (depth ``finalized``; the
            player's ``end_of_stream``: the refinement deadline counts from it).
Asks        while it lacks a revision of the depth node's final digest and no input is waiting
            (two checks RESYNC_S apart without progress), graph event ``resend_depth``
            {kf_ids}: the depth node sends their current proxy depth again (a DDS history
            can drop a message that a burst of newer revisions overtook).
Publishes   /splat/map/rendered_rgb + rendered_depth (at the latest keyframe, every
            ``mapping.render_every`` keyframes, when someone listens), /splat/map/view_rgb +
            view_depth (at a requested pose), rendered_camera_info + view_camera_info (their
            CameraInfo; images in ros.optical_frame), /splat/map/points (PointCloud2 of
            Gaussian centres with colours), /splat/map/status (MapperStatus),
            /splat/frame_ack (consumer "mapper", one per keyframe consumed: lockstep).
Outputs     (node.output_dir) at the end map.ply, renders/, mapper_metrics.json and the map's
            part of session/ (map_state.npz: a later run can load or extend the map).
Options     node.load_map (set by ``splat-slam-launch --load-map RUN``: start from the map
            the session RUN saved; new keyframes join it).
Services    /splat/map/save (SaveMap: PLY + trajectory + metrics), /splat/map/reset (Trigger),
            /splat/map/render (RenderPose). Inputs are checked by service_guard (save inside
            node.output_dir, reset only with node.allow_reset, renders <= node.max_render_pixels).
The protocol (pending keyframes/depths, replayed revisions, snapshots to ``node.state_dir``,
final refinement) is :class:`splat_slam_ros.mapper_role.MapperRole`.
"""
from __future__ import annotations

import sys
import time

import numpy as np
import torch

from .map_requests import answer_save, load_request, loaded_by_tracker, reply
from .map_services import MapServices
from .node_common import TOPICS, SplatNode, run_node
from .node_options import NODE_OPTIONS

MAX_QUEUED = 32           # live: queued jobs beyond which any input cuts the mapping steps
RESYNC_S = 2.0            # how often a mapper waiting on the final digest checks for lost depth


class MapperNode(SplatNode):
    def __init__(self):
        super().__init__("mapper", NODE_OPTIONS["mapper"])
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2
        from splat_slam_msgs.msg import MapperStatus

        from splat_slam_ros.mapper_role import MapperRole

        from . import qos as Q
        n = self.node
        self.pub_rgb = n.create_publisher(Image, TOPICS["rendered_rgb"], Q.rendered_qos())
        self.pub_depth = n.create_publisher(Image, TOPICS["rendered_depth"], Q.rendered_qos())
        self.pub_vrgb = n.create_publisher(Image, TOPICS["view_rgb"], Q.rendered_qos())
        self.pub_vdepth = n.create_publisher(Image, TOPICS["view_depth"], Q.rendered_qos())
        self.pub_info = n.create_publisher(CameraInfo, TOPICS["rendered_info"], Q.rendered_qos())
        self.pub_vinfo = n.create_publisher(CameraInfo, TOPICS["view_info"], Q.rendered_qos())
        self.pub_points = n.create_publisher(PointCloud2, TOPICS["points"], Q.status_qos())
        self.pub_status = n.create_publisher(MapperStatus, TOPICS["status"], Q.status_qos())
        self.publishers("ack")
        self.MapperStatus = MapperStatus
        if self.opts["mapping"]:      # the first keyframe's one-off costs, before input
            from splat_slam_ros.mapping.gaussian_map import warm_up
            from splat_slam_ros.mapping.mapper import Mapper  # noqa: F401 (imported now)
            from splat_slam_ros.mapping.rasterizer import select_backend
            from splat_slam_ros.runtime import resolve_device
            warm_up()
            if self.cfg.mapping.mesh:   # Open3D (1-1.5 s to import) now, not after the input
                from splat_slam_ros.mapping import mesh  # noqa: F401
            # an explicit mapping.raster_backend that cannot run stops the node now (exit 2)
            select_backend(self.cfg.mapping.raster_backend,
                           resolve_device(self.cfg.mapping.device, "mapping.device"))
        self.role = MapperRole(self.cfg, store=self.store(),
                               snapshot_every=int(self.opts["snapshot_every"]))
        if self.role.offered:
            self.log.info(f"resumed from {self.state_dir}: {sum(self.role.offered.values())} "
                          f"mapped keyframes, {len(self.role.offered)} consumed")
        elif self.opts["load_map"]:
            self._load_map(str(self.opts["load_map"]))
        self.mapped_at: dict = {}      # kf id -> when it was mapped (epoch s; the map lag)
        # live input (mapping.time_budget): a keyframe's newer proxy depth replaces the one
        # still queued (each revision in turn kept the queue seconds behind the stream)
        live = bool(self.cfg.mapping.time_budget)
        self.route(self.role, keyframes=True, updates=True, proxy_depth=True, after=self._after,
                   newest_depth=live)
        # ... input that waits cuts the optimisation steps (_input_waiting), and background
        # steps run while none waits (mapping.background_steps): the map keeps pace
        self.role.input_waiting = self._input_waiting
        self.worker.idle = (self.role.wants_background, self.role.background)
        self.subscribe(PoseStamped, TOPICS["render_request"], Q.pose_qos(),
                       lambda m, raw: self.worker.submit(self._view, m), "render request")
        self.services = MapServices(self)                 # save / reset / render
        self.on_events(self._on_request)                  # the launcher's map services
        self._lack_prev: tuple = ()
        self._resync_queued = False
        # steady clock: with use_sim_time (bag replay) ROS time stops with the player's
        # /clock at the end of the stream, exactly when this check is needed
        from rclpy.clock import Clock, ClockType
        self.node.create_timer(RESYNC_S, self._resync_tick,
                               clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.publish_event("ready")

    def _input_waiting(self) -> bool:
        """Live input that cuts a keyframe's or the background's optimisation steps: any
        queued job but the newer depth of a keyframe already consumed (a deformation, applied
        after the steps, which ``mapping.keep_up`` bounds) or a pose-graph update (a counter
        here); any job once more than MAX_QUEUED wait."""
        pending = self.worker.pending()
        if pending > MAX_QUEUED:
            return True
        with self._waiting_lock:
            waiting = list(self.depth_waiting)      # keyframes whose newer depth waits
            cheap = self.waiting["updates"]
        return pending > cheap + sum(1 for k in waiting if k in self.role.offered)

    def _load_map(self, run_dir: str) -> None:
        """Extend runs (node.load_map): the map the session in ``run_dir`` saved, restored
        with its mapped keyframes; new keyframes join it (splat_slam_ros.extend). A session
        that cannot be read stops the node (exit 2)."""
        from splat_slam_ros.io.session import SessionError
        try:
            self._restore(run_dir)
        except SessionError as e:
            self.log.fatal(f"cannot load the map: {e}")
            raise SystemExit(2)

    def _restore(self, run_dir: str) -> None:
        from pathlib import Path

        from splat_slam_ros.io.session import load_session, map_state
        from splat_slam_ros.mapping.persistence import restore_map_state
        arrays, meta, cam = map_state(load_session(Path(run_dir)))
        self.role.restore(restore_map_state(arrays, meta, self.cfg, cam), cam)
        self.log.info(f"loaded the map of {run_dir}: {len(self.role.mapper.map)} Gaussians, "
                      f"{len(self.role.mapper.keyframes)} mapped keyframes")
        self._status()

    def _on_request(self, d: dict) -> None:
        if d.get("event") == "end_of_stream" and isinstance(d.get("t"), (int, float)):
            # the player's stream end (mapping.final_deadline_s); set at once, not queued:
            # a queued job would count as waiting input and cut a mapping step
            self.role.input_ended(float(d["t"]))
        elif d.get("event") == "save_map" and load_request(d, self.started):
            self.worker.submit(self._save_map, d)
        elif loaded_by_tracker(d, self.started):
            self.worker.submit(self._load_requested, d)

    def _save_map(self, d: dict) -> None:
        """/splat/save_map: map.ply, renders/, mapper_metrics.json and DIR/session/'s map
        state now."""
        from splat_slam_ros.io.session import write_map_state
        from splat_slam_ros.mapping.persistence import mapper_arrays
        if self.role.mapper is None:
            return reply(self, "map_saved", d, False, "the map is empty: nothing to save")

        def write(out):
            self.role.save(out, final=True)
            write_map_state(out, *mapper_arrays(self.role.mapper), self.role.mapper.K)
            return ["map.ply", "renders/", "mapper_metrics.json"]
        answer_save(self, d, write)

    def _load_requested(self, d: dict) -> None:
        """The launcher's /splat/load_map (extend), once the tracker took it: the loaded map,
        with the extend run's mapping settings the launcher chose."""
        from splat_slam_ros.config import ConfigError
        from splat_slam_ros.io.session import SessionError
        if self.role.mapper is not None:
            return reply(self, "map_loaded", d, False, "the mapper holds a map already")
        try:
            mapping = d.get("mapping") or {}
            for key, value in (mapping.items() if isinstance(mapping, dict) else ()):
                self.cfg.set(f"mapping.{key}", value)
                self.log.info(f"extend run: mapping.{key} {value}")
            self._restore(str(d.get("run")))
        except (SessionError, ConfigError) as e:
            return reply(self, "map_loaded", d, False, str(e))
        reply(self, "map_loaded", d, True, f"{len(self.role.mapper.map)} Gaussians loaded")

    # ------------------------------------------------------------ lost depth
    def _resync_tick(self) -> None:
        if not self._resync_queued and self.role.digest is not None and not self.role.finalized:
            self._resync_queued = True
            self.worker.submit(self._resync)

    def _resync(self) -> None:
        """On the worker: ask again for the revisions still lacking after a quiet interval."""
        self._resync_queued = False
        lack = tuple(self.role.lacking())
        if not lack or self.worker.pending() > 0:
            self._lack_prev = ()
            return
        if lack == self._lack_prev:
            self.warn_throttled("resync", f"final digest: {len(lack)} keyframe(s) lack their "
                                f"latest proxy depth (first {lack[0]}): asking the depth node "
                                f"to send it again", error=False)
            self.publish_event("resend_depth", kf_ids=list(lack))
        self._lack_prev = lack

    # ------------------------------------------------------------ outputs
    def _after(self, out) -> None:
        for st in out.mapped:
            if st.get("mapped"):
                self.mapped_at[int(st["kf_id"])] = time.time()
                self.log.info(f"keyframe {st['kf_id']} mapped ({st.get('reason')}): "
                              f"{st.get('gaussians')} Gaussians, {st.get('last_ms', 0):.0f} ms")
                if st["n_mapped"] % max(1, int(self.cfg.mapping.render_every)) == 0:
                    self._publish_renders(st["pose"], st["timestamp"])
                if st["n_mapped"] % max(1, int(self.opts["points_every"])) == 0:
                    self._publish_points(st["timestamp"])
        self._status()
        if out.final is not None:
            self._finish(out.final)

    def _finish(self, info: dict) -> None:
        t0 = time.perf_counter()
        mp = self.role.mapper
        metrics: dict = {}
        if mp is not None:
            self.log.info(f"final refinement: {info.get('refine')}")
            if self.output_dir is not None:
                metrics = self.role.save(self.output_dir, final=True)
                metrics["refine_s"] = (info.get("refine") or {}).get("refine_s")
                # the map's part of the run's session (the tracker writes the keyframes')
                from splat_slam_ros.io.session import write_map_state
                from splat_slam_ros.mapping.persistence import mapper_arrays
                write_map_state(self.output_dir, *mapper_arrays(mp), mp.K)
            if mp.keyframes:
                kf = mp.keyframes[max(mp.keyframes)]
                self._publish_renders(kf.pose, kf.timestamp)
                self._publish_points(kf.timestamp)
        self.log.info(f"saved outputs ({time.perf_counter() - t0:.1f} s)")
        self.publish_event("saved", metrics=metrics, keyframe_mapped={
            str(k): round(t, 4) for k, t in sorted(self.mapped_at.items())})

    def _status(self) -> None:
        m = self.MapperStatus()
        m.header.stamp = self.node.get_clock().now().to_msg()
        m.header.frame_id = self.frame_id
        mp = self.role.mapper
        if mp is not None:
            s = mp.stats()
            m.gaussian_count, m.keyframes_mapped = int(s["gaussians"]), int(s["keyframes"])
            m.map_size_mb = float(mp.map.nbytes() / 1e6)
            m.last_mapping_ms = float(s["last_ms"])
            m.deformations_applied, m.iterations = int(s["deformations"]), int(s["iterations"])
        m.last_update_seq = int(self.role.last_update_seq)
        self.pub_status.publish(m)

    def _render(self, pose, width=0, height=0, intrinsics=None):
        mp = self.role.mapper
        w = int(width or self.opts["render_width"] or mp.W)
        h = int(height or self.opts["render_height"] or mp.H)
        intr = None
        if intrinsics is not None and any(abs(float(x)) > 0 for x in intrinsics):
            intr = [float(x) for x in intrinsics]
        return mp.render(np.asarray(pose, np.float64), w, h, intrinsics=intr)

    def _images(self, rgb, depth, stamp, frame_id):
        from .convert import image_to_msg
        return (image_to_msg(rgb, "rgb8", stamp, frame_id),
                image_to_msg(depth.astype(np.float32), "32FC1", stamp, frame_id))

    def _publish_view(self, pose, stamp, pubs) -> None:
        """Render at ``pose``; rgb, depth and their CameraInfo in the optical frame."""
        from .tf_frames import render_camera_info
        fr = self.cfg.ros.optical_frame
        rgb, depth = self._render(pose)
        for pub, m in zip(pubs, self._images(rgb, depth, stamp, fr) + (render_camera_info(
                self.role.mapper, rgb.shape[1], rgb.shape[0], None, stamp, fr),)):
            pub.publish(m)

    def _publish_renders(self, pose, stamp) -> None:
        if self.pub_rgb.get_subscription_count() + self.pub_depth.get_subscription_count() == 0:
            return
        self._publish_view(pose, stamp, (self.pub_rgb, self.pub_depth, self.pub_info))

    def _publish_points(self, stamp) -> None:
        from .node_common import pointcloud2
        if self.pub_points.get_subscription_count() == 0:
            return
        g = self.role.mapper.map
        cols = (g.colors.detach().clamp(0, 1) * 255 + 0.5).to(dtype=torch.uint8)
        self.pub_points.publish(pointcloud2(g.means.detach().cpu().numpy(), cols.cpu().numpy(),
                                            stamp, self.frame_id))

    def _view(self, msg) -> None:
        from .convert import from_stamp, msg_to_pose
        if self.role.mapper is None:
            self.warn_throttled("view", "render request ignored: the map is empty", error=False)
            return
        self._publish_view(msg_to_pose(msg.pose), from_stamp(msg.header.stamp),
                           (self.pub_vrgb, self.pub_vdepth, self.pub_vinfo))


def main(argv=None) -> int:
    return run_node(MapperNode, argv)


if __name__ == "__main__":
    sys.exit(main())
