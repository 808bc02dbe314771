"""mapper_node: keyframes + proxy depth -> splat_slam_ros.mapping.mapper.Mapper -> renders, map, status.

Subscribes  /splat/keyframes (images), /splat/proxy_depth (new keyframes are mapped once their
            depth is there; ``is_update`` depths deform the keyframe's Gaussians first),
            /splat/pose_graph_updates (reported in MapperStatus.last_update_seq; the
            deformation itself follows the depth node's ProxyDepth updates, which carry the
            new pose together with the re-filtered depth in one ordered stream),
            /splat/map/render_request (PoseStamped), /splat/graph_events (finalisation).
Publishes   /splat/map/rendered_rgb + rendered_depth (at the latest keyframe, every
            ``mapping.render_every`` keyframes, when someone listens), /splat/map/view_rgb +
            view_depth (at a requested pose), /splat/map/points (PointCloud2 of Gaussian centres
            with colours), /splat/map/status (MapperStatus), /splat/frame_ack (consumer
            "mapper", one per keyframe consumed: lockstep).
Services    /splat/map/save (SaveMap: PLY + trajectory + metrics), /splat/map/reset (Trigger),
            /splat/map/render (RenderPose).
Crash safety: after each mapped keyframe the map (Gaussians, keyframes, window) is written to
``node.state_dir`` (keyframe_store); a restarted mapper restores it and skips the messages
whose effect the snapshot already holds.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from splat_slam_ros.mapping.mesh import map_mesh_output

from .node_common import SERVICES, TOPICS, SplatNode, raw_hash, run_node

SEEN_KEEP = 5000


class MapperNode(SplatNode):
    def __init__(self):
        super().__init__("mapper", {"loop_closure": True, "mapping": True, "snapshot_every": 1,
                                    "points_every": 1, "render_width": 0, "render_height": 0})
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import Image, PointCloud2
        from splat_slam_msgs.msg import (FrameAck, Keyframe, MapperStatus, PoseGraphUpdate,
                                         ProxyDepth)
        from splat_slam_msgs.srv import RenderPose, SaveMap
        from std_srvs.srv import Trigger

        from . import qos as Q
        n = self.node
        self.pub_rgb = n.create_publisher(Image, TOPICS["rendered_rgb"], Q.rendered_qos())
        self.pub_depth = n.create_publisher(Image, TOPICS["rendered_depth"], Q.rendered_qos())
        self.pub_vrgb = n.create_publisher(Image, TOPICS["view_rgb"], Q.rendered_qos())
        self.pub_vdepth = n.create_publisher(Image, TOPICS["view_depth"], Q.rendered_qos())
        self.pub_points = n.create_publisher(PointCloud2, TOPICS["points"], Q.status_qos())
        self.pub_status = n.create_publisher(MapperStatus, TOPICS["status"], Q.status_qos())
        self.pub_ack = n.create_publisher(FrameAck, TOPICS["ack"], Q.ack_qos())
        self.MapperStatus = MapperStatus
        import splat_slam_ros.mapping.mapper  # noqa: F401  (torch + rasterizer before 'ready')
        self.mapper = None
        self.intr = None
        self.pending_kf: Dict[int, object] = {}    # kf_id -> KeyframeData waiting for depth
        self.pending_depth: Dict[int, object] = {}  # kf_id -> ProxyDepthData waiting for kf
        self.offered: Dict[int, bool] = {}          # kf_id -> mapped?
        self.seen: Dict[str, None] = {}             # handled messages in the snapshot
        self.seen_new: Dict[str, None] = {}         # handled since the snapshot
        self.last_update_seq = 0
        self.digest: Optional[dict] = None
        self.saved = False
        self.n_mapped_since_snap = 0
        self.dirty = set()                          # keyframes whose depth changed since
        self.store = None
        if self.state_dir is not None:
            from splat_slam_ros.io.keyframe_store import KeyframeStore
            self.store = KeyframeStore(self.state_dir)
            if self.store.exists:
                self._resume()
        self.subscribe(ProxyDepth, TOPICS["proxy_depth"], Q.proxy_depth_qos(),
                       lambda m, raw: self.worker.submit(self._depth, m, raw_hash(raw)),
                       "ProxyDepth")
        self.subscribe(Keyframe, TOPICS["keyframes"], Q.keyframe_qos(),
                       lambda m, raw: self.worker.submit(self._keyframe, m, raw_hash(raw)),
                       "Keyframe")
        self.subscribe(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos(), self._update,
                       "PoseGraphUpdate")
        self.subscribe(PoseStamped, TOPICS["render_request"], Q.pose_qos(),
                       lambda m, raw: self.worker.submit(self._view, m), "render request")
        self.on_events(lambda d: self.worker.submit(self._event, d))
        n.create_service(SaveMap, SERVICES["save_map"], self._srv_save)
        n.create_service(Trigger, SERVICES["reset_map"], self._srv_reset)
        n.create_service(RenderPose, SERVICES["render"], self._srv_render)
        self.publish_event("ready")

    # ------------------------------------------------------------ persistence
    def _resume(self) -> None:
        from splat_slam_ros.io.keyframe_store import restore_mapper
        from splat_slam_ros.types import Intrinsics
        meta = self.store.meta
        self.seen = dict.fromkeys(meta.get("seen", []))
        self.offered = {int(k): bool(v) for k, v in meta.get("offered", {}).items()}
        self.last_update_seq = int(meta.get("last_update_seq", 0))
        if self.store.has("map") and meta.get("intrinsics"):
            i = meta["intrinsics"]
            self.intr = Intrinsics(i[0], i[1], i[2], i[3], int(i[4]), int(i[5]))
            self.mapper = restore_mapper(self.store.get("map"), meta["map"], self.cfg, self.intr,
                                         lambda k: self.store.get(f"kf{k}_image")["image"],
                                         lambda k: self.store.get(f"kf{k}_mdepth"))
        n = len(self.mapper.keyframes) if self.mapper is not None else 0
        self.log.info(f"resumed from {self.state_dir}: {n} mapped keyframes, "
                      f"{len(self.offered)} keyframes consumed")

    def _snapshot(self) -> None:
        if self.store is None or self.mapper is None:
            return
        from splat_slam_ros.io.keyframe_store import keyframe_depth, mapper_state
        arrays, meta = mapper_state(self.mapper)
        staged = {f"kf{k}_mdepth": self.store.stage(f"kf{k}_mdepth",
                                                     **keyframe_depth(self.mapper, k))
                  for k in sorted(self.dirty) if k in self.mapper.keyframes}
        self.dirty.clear()
        self.seen.update(self.seen_new)
        self.seen_new = {}
        if len(self.seen) > 2 * SEEN_KEEP:
            self.seen = dict.fromkeys(list(self.seen)[-SEEN_KEEP:])
        i = self.intr
        staged["map"] = self.store.stage("map", **arrays)
        self.store.commit(staged, {"map": meta, "seen": list(self.seen),
                                   "offered": {str(k): v for k, v in self.offered.items()},
                                   "intrinsics": [i.fx, i.fy, i.cx, i.cy, i.width, i.height],
                                   "last_update_seq": self.last_update_seq})
        self.n_mapped_since_snap = 0

    def _handled(self, h: str) -> bool:
        return h in self.seen or h in self.seen_new

    # ------------------------------------------------------------ callbacks
    def _update(self, msg, raw) -> None:
        self.last_update_seq = max(self.last_update_seq, int(msg.seq))

    def _keyframe(self, msg, h: str) -> None:
        from .convert import msg_to_keyframe
        if self._handled(h):
            return
        kf = msg_to_keyframe(msg)
        if kf.kf_id in self.offered or kf.kf_id in self.pending_kf:
            return
        # marked handled only once mapped: a pending keyframe is not in the snapshot, so a
        # restarted mapper must take its replay again
        self.pending_kf[kf.kf_id] = (kf, h)
        self._try_map()

    def _depth(self, msg, h: str) -> None:
        from .convert import msg_to_proxy_depth
        if self._handled(h):
            return
        pd = msg_to_proxy_depth(msg)
        k = pd.kf_id
        if self.mapper is not None and k in self.mapper.keyframes:
            # Map deformation (§3.2): the keyframe's Gaussians follow its new pose and depth
            self.mapper.apply_update(k, pd.pose, pd.depth, pd.source > 0)
            self.dirty.add(k)
            self.last_update_seq = max(self.last_update_seq, int(pd.update_seq))
            self.seen_new[h] = None
            self._status()
        elif k in self.offered:
            self.seen_new[h] = None                 # consumed but not mapped (redundant view)
        else:
            old = self.pending_depth.get(k)
            self.pending_depth[k] = (pd, (old[1] if old else []) + [h])
            self._try_map()
        self._check_final()

    def _try_map(self) -> None:
        for k in sorted(self.pending_kf):
            if k not in self.pending_depth:
                continue
            kf, h_kf = self.pending_kf.pop(k)
            pd, h_pd = self.pending_depth.pop(k)
            for h in [h_kf] + h_pd:
                self.seen_new[h] = None             # in the snapshot taken by _map
            self._map(kf, pd)
        self._check_final()

    def _map(self, kf, pd) -> None:
        from splat_slam_ros.mapping.mapper import Mapper

        from .convert import frame_ack_msg, to_stamp
        if self.mapper is None:
            self.intr = kf.intrinsics
            self.mapper = Mapper(self.cfg, kf.intrinsics)
        st = self.mapper.add_keyframe(kf.kf_id, kf.image, pd.pose, pd.depth, pd.source > 0,
                                      timestamp=kf.timestamp)
        self.offered[kf.kf_id] = bool(st.get("mapped"))
        if st.get("mapped"):
            self.dirty.add(kf.kf_id)
        if st.get("mapped") and self.store is not None and not self.store.has(f"kf{kf.kf_id}_image"):
            self.store.put(f"kf{kf.kf_id}_image", image=np.asarray(kf.image, np.uint8))
        self.n_mapped_since_snap += 1
        if self.n_mapped_since_snap >= max(1, int(self.opts["snapshot_every"])):
            self._snapshot()
        ack = frame_ack_msg(kf.frame_index, "mapper", 0.0, kf.kf_id)
        ack.header.stamp = to_stamp(kf.timestamp)
        self.pub_ack.publish(ack)
        n_map = sum(self.offered.values())
        if st.get("mapped"):
            self.log.info(f"keyframe {kf.kf_id} mapped ({st.get('reason')}): "
                          f"{st.get('gaussians')} Gaussians, {st.get('last_ms', 0):.0f} ms")
        self._status()
        every = max(1, int(self.cfg.mapping.render_every))
        if st.get("mapped") and n_map % every == 0:
            self._publish_renders(kf.kf_id, pd.pose, kf.timestamp)
        if st.get("mapped") and n_map % max(1, int(self.opts["points_every"])) == 0:
            self._publish_points(kf.timestamp)

    # ------------------------------------------------------------ outputs
    def _status(self) -> None:
        m = self.MapperStatus()
        m.header.stamp = self.node.get_clock().now().to_msg()
        m.header.frame_id = self.frame_id
        if self.mapper is not None:
            s = self.mapper.stats()
            m.gaussian_count = int(s["gaussians"])
            m.keyframes_mapped = int(s["keyframes"])
            m.map_size_mb = float(self.mapper.map.nbytes() / 1e6)
            m.last_mapping_ms = float(s["last_ms"])
            m.deformations_applied = int(s["deformations"])
            m.iterations = int(s["iterations"])
        m.last_update_seq = int(self.last_update_seq)
        self.pub_status.publish(m)

    def _render(self, pose, width=0, height=0, intrinsics=None):
        mp = self.mapper
        w = int(width or self.opts["render_width"] or mp.W)
        h = int(height or self.opts["render_height"] or mp.H)
        intr = None
        if intrinsics is not None and any(abs(float(x)) > 0 for x in intrinsics):
            intr = [float(x) for x in intrinsics]
        return mp.render(np.asarray(pose, np.float64), w, h, intrinsics=intr)

    def _publish_renders(self, kf_id, pose, stamp) -> None:
        from .convert import image_to_msg
        if self.pub_rgb.get_subscription_count() + self.pub_depth.get_subscription_count() == 0:
            return
        rgb, depth = self._render(pose)
        self.pub_rgb.publish(image_to_msg(rgb, "rgb8", stamp, self.cfg.ros.camera_frame))
        self.pub_depth.publish(image_to_msg(depth.astype(np.float32), "32FC1", stamp,
                                            self.cfg.ros.camera_frame))

    def _publish_points(self, stamp) -> None:
        from .node_common import pointcloud2
        if self.pub_points.get_subscription_count() == 0:
            return
        g = self.mapper.map
        cols = (g.colors.detach().clamp(0, 1) * 255 + 0.5).to(dtype=__import__("torch").uint8)
        self.pub_points.publish(pointcloud2(g.means.detach().cpu().numpy(), cols.cpu().numpy(),
                                            stamp, self.frame_id))

    def _view(self, msg) -> None:
        from .convert import from_stamp, image_to_msg, msg_to_pose
        if self.mapper is None:
            self.warn_throttled("view", "render request ignored: the map is empty", error=False)
            return
        stamp = from_stamp(msg.header.stamp)
        rgb, depth = self._render(msg_to_pose(msg.pose))
        self.pub_vrgb.publish(image_to_msg(rgb, "rgb8", stamp, self.cfg.ros.camera_frame))
        self.pub_vdepth.publish(image_to_msg(depth.astype(np.float32), "32FC1", stamp,
                                             self.cfg.ros.camera_frame))

    def save(self, directory: Path, final: bool = False) -> dict:
        """map.ply, trajectory_keyframes (mapped keyframes), renders/, metrics."""
        from splat_slam_ros.io.trajectory_io import write_tum
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        metrics: dict = {}
        if self.mapper is None:
            return metrics
        self.mapper.save_ply(d / "map.ply")
        if self.cfg.mapping.mesh:
            metrics["mesh"] = map_mesh_output(self.mapper, d / "map_mesh.ply")
        metrics.update(self.mapper.evaluate_keyframes(d / "renders"))
        metrics["map"] = self.mapper.stats()
        if not final:                              # the tracker writes the graph's own
            write_tum(d / "trajectory_keyframes.txt", *self.mapper.keyframe_trajectory())
            (d / "metrics.json").write_text(json.dumps(metrics, indent=2, default=str))
        else:
            (d / "mapper_metrics.json").write_text(json.dumps(metrics, indent=2, default=str))
        return metrics

    # ------------------------------------------------------------ services
    def _srv_save(self, req, resp):
        d = Path(req.directory or (str(self.output_dir) if self.output_dir else "map_save"))
        try:
            with self.worker.lock:
                if self.mapper is None:
                    resp.success, resp.message = False, "the map is empty: nothing to save"
                    return resp
                self.save(d)
            resp.success = True
            resp.message = f"wrote {d / 'map.ply'}, {d / 'trajectory_keyframes.txt'}, " \
                           f"{d / 'metrics.json'}, {d / 'renders'}" \
                           + (f", {d / 'map_mesh.ply'}" if self.cfg.mapping.mesh else "")
        except Exception as e:
            resp.success, resp.message = False, f"{type(e).__name__}: {e}"
        return resp

    def _srv_reset(self, req, resp):
        with self.worker.lock:
            self.mapper = None
            self.pending_kf.clear()
            self.pending_depth.clear()
            self.offered.clear()
            self.dirty.clear()
            self.seen_new.clear()
            self.seen.clear()
            if self.store is not None:
                self.store.clear()
            self._status()
        resp.success, resp.message = True, "map reset: the next keyframes start a new map"
        return resp

    def _srv_render(self, req, resp):
        from .convert import image_to_msg, msg_to_pose
        try:
            with self.worker.lock:
                if self.mapper is None:
                    resp.success, resp.message = False, "the map is empty"
                    return resp
                rgb, depth = self._render(msg_to_pose(req.pose), req.width, req.height,
                                          list(req.intrinsics))
            stamp = self.now()
            resp.rgb = image_to_msg(rgb, "rgb8", stamp, self.frame_id)
            resp.depth = image_to_msg(depth.astype(np.float32), "32FC1", stamp, self.frame_id)
            resp.success, resp.message = True, f"rendered {rgb.shape[1]}x{rgb.shape[0]}"
        except Exception as e:
            resp.success, resp.message = False, f"{type(e).__name__}: {e}"
        return resp

    # ------------------------------------------------------------ finalisation
    def _event(self, d: dict) -> None:
        if d.get("node") == "depth" and d.get("event") == "finalized":
            self.digest = d.get("digest") or {}
            self._check_final()

    def _check_final(self) -> None:
        if self.digest is None or self.saved:
            return
        if not all(self._handled(h) for h in self.digest.values()):
            return
        self.saved = True
        metrics = {}
        t0 = time.perf_counter()
        if self.mapper is not None:
            ref = self.mapper.final_refine(self.cfg.mapping.final_refine_iters)
            self.log.info(f"final refinement: {ref}")
            self._snapshot()
            if self.output_dir is not None:
                metrics = self.save(self.output_dir, final=True)
                metrics["refine_s"] = ref.get("refine_s")
            last = max(self.mapper.keyframes) if self.mapper.keyframes else None
            if last is not None:
                kf = self.mapper.keyframes[last]
                self._publish_renders(last, kf.pose, kf.timestamp)
                self._publish_points(kf.timestamp)
            self._status()
        self.log.info(f"saved outputs ({time.perf_counter() - t0:.1f} s)")
        self.publish_event("saved", metrics=metrics)


def main(argv=None) -> int:
    return run_node(MapperNode, argv)


if __name__ == "__main__":
    sys.exit(main())
