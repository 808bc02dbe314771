"""tracker_node: camera frames -> splat_slam_ros.tracking.tracker.Tracker -> keyframes, poses, updates.

Subscribes  ros.image_topic (sensor_msgs/Image: rgb8, bgr8, mono8, rgba8, bgra8) and
            ros.camera_info_topic (sensor_msgs/CameraInfo) — remap with ``--set`` / ``-p``;
            /splat/pose_graph_updates (loop closure / global BA updates -> Tracker.apply_update);
            /splat/graph_events (end_of_stream -> Tracker.finalize()).
Publishes   /splat/keyframes (Keyframe), /splat/pose_graph_updates (its local-BA updates),
            /splat/camera_pose (PoseStamped), /splat/trajectory (Path), /tf map->camera
            (when tf2_msgs is installed), /splat/frame_ack (FrameAck per consumed frame).
Bad input (unsupported encoding, no camera_info, a size change, undecodable bytes) is a
logged error; the frame is acknowledged as consumed and dropped, the node keeps running.
Resize / crop / undistort follow ``camera.*`` (done by the Tracker's preprocessor).
Node options: node.input_qos (sensor = BEST_EFFORT, matches any camera driver; reliable for
the bag player), node.max_queue (frames waiting for the tracker; 2 by default so a live camera
stays current, older frames are dropped and counted; the launcher sets 0 = never drop in
lockstep), node.camera_info_timeout, node.intrinsics_file (when no camera_info is published).
"""
from __future__ import annotations

import sys
import threading
from typing import List, Optional

from .node_common import TOPICS, SplatNode, run_node


class TrackerNode(SplatNode):
    def __init__(self):
        super().__init__("tracker", {"input_qos": "sensor", "max_queue": 2,
                                     "camera_info_timeout": 2.0, "intrinsics_file": "",
                                     "loop_closure": True, "mapping": True, "path_every": 10})
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Path as PathMsg
        from sensor_msgs.msg import CameraInfo, Image
        from splat_slam_msgs.msg import PoseGraphUpdate

        from . import qos as Q
        from .node_common import tf_available
        n = self.node
        self.publishers("keyframes", "updates", "ack")
        self.pub_pose = n.create_publisher(PoseStamped, TOPICS["camera_pose"], Q.pose_qos())
        self.pub_path = n.create_publisher(PathMsg, TOPICS["trajectory"], Q.status_qos())
        self.pub_tf = None
        if tf_available():
            from tf2_msgs.msg import TFMessage
            self.pub_tf = n.create_publisher(TFMessage, "/tf", 100)
        else:
            self.log.info("tf2_msgs is not installed (not on PyPI): map->camera is published as "
                          f"{TOPICS['camera_pose']} (PoseStamped) only, not on /tf")
        in_qos = Q.image_qos() if self.opts["input_qos"] == "reliable" else Q.sensor_qos()
        # updates first: when an update and a frame are both ready, the update runs first
        self.subscribe(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos(),
                       lambda m, raw: self.worker.submit(self._apply_update, m),
                       "PoseGraphUpdate")
        self.subscribe(CameraInfo, self.cfg.ros.camera_info_topic, in_qos, self._on_info,
                       "CameraInfo")
        self.subscribe(Image, self.cfg.ros.image_topic, in_qos, self._on_image, "Image")
        self.on_events(self._on_event)
        self.role = None                    # splat_slam_ros.roles.TrackerRole, on the first frame
        self.size = None
        self.intr = None
        self.cam_info = None
        self.info_lock = threading.Condition()
        self.n_frames = 0
        self.n_dropped = 0
        self.queued = 0
        self.eos = False
        self.saved = False
        self.stamps: List[float] = []
        self.poses: List = []
        if self.opts["intrinsics_file"]:
            from splat_slam_ros.types import Intrinsics, IntrinsicsError
            try:
                self.intr = Intrinsics.from_yaml(self.opts["intrinsics_file"])
            except IntrinsicsError as e:
                self.log.fatal(str(e))
                raise SystemExit(2)
        import splat_slam_ros.tracking.tracker  # noqa: F401  (torch, OpenCV before 'ready')
        self.log.info(f"listening on {self.cfg.ros.image_topic} + {self.cfg.ros.camera_info_topic} "
                      f"({self.opts['input_qos']} QoS)")
        self.publish_event("ready")

    # ------------------------------------------------------------ callbacks (executor)
    def _on_info(self, msg, raw) -> None:
        from .convert import ConversionError, camera_info_to_intrinsics
        try:
            intr = camera_info_to_intrinsics(msg)
        except ConversionError as e:
            self.warn_throttled("info", f"ignoring camera_info: {e}")
            return
        with self.info_lock:
            if self.cam_info is not None and self.role is not None and \
                    (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height) != \
                    (self.cam_info.fx, self.cam_info.fy, self.cam_info.cx, self.cam_info.cy,
                     self.cam_info.width, self.cam_info.height):
                self.warn_throttled("info-change", "camera_info changed while tracking; the "
                                    "tracker keeps its initial calibration", error=False)
                return
            self.cam_info = intr
            self.info_lock.notify_all()

    def _on_image(self, msg, raw) -> None:
        mq = int(self.opts["max_queue"])
        if mq > 0 and self.queued >= mq:          # realtime: a slow tracker drops frames
            self.n_frames += 1
            self.n_dropped += 1
            self._ack(self.n_frames - 1, msg.header.stamp, None)
            self.warn_throttled("drop", f"tracker busy: dropped frame {self.n_frames - 1} "
                                f"({self.n_dropped} so far)", error=False)
            return
        index = self.n_frames
        self.n_frames += 1
        self.queued += 1
        self.worker.submit(self._process, msg, index)

    def _on_event(self, d: dict) -> None:
        if d.get("event") == "end_of_stream" and d.get("node") in ("player", "launch"):
            self.worker.submit(self._finalize)
        elif d.get("event") == "finalized":
            self.worker.submit(self._on_final, d)

    # ------------------------------------------------------------ work (worker thread)
    def _ack(self, index: int, stamp, kf_id: Optional[int]) -> None:
        from .convert import frame_ack_msg
        m = frame_ack_msg(index, "tracker", 0.0, kf_id)
        m.header.stamp = stamp
        self.pubs["ack"].publish(m)

    def _intrinsics(self, index: int):
        if self.intr is not None and self.cam_info is None:
            return self.intr
        with self.info_lock:
            if self.cam_info is None:
                self.info_lock.wait(timeout=float(self.opts["camera_info_timeout"]))
            return self.cam_info

    def _process(self, msg, index: int) -> None:
        self.queued -= 1
        kf_id = None
        try:
            kf_id = self._track(msg, index)
        finally:
            self._ack(index, msg.header.stamp, kf_id)

    def _drop(self, index: int, why: str) -> None:
        self.n_dropped += 1
        self.warn_throttled(why.split(":")[0], f"frame {index} dropped: {why}")

    def _track(self, msg, index: int) -> Optional[int]:
        from splat_slam_ros.tracking.tracker import TrackingError
        from splat_slam_ros.types import Frame

        from .convert import ConversionError, from_stamp, msg_to_rgb
        from .node_common import pose_stamped
        try:
            rgb = msg_to_rgb(msg)
        except ConversionError as e:
            self._drop(index, f"{e}")
            return None
        h, w = rgb.shape[:2]
        if self.role is not None and (w, h) != self.size:
            self._drop(index, f"image size changed: {w}x{h}, the tracker runs on "
                              f"{self.size[0]}x{self.size[1]} (restart the graph for a new size)")
            return None
        intr = self._intrinsics(index)
        if intr is None:
            self._drop(index, f"no camera_info received on {self.cfg.ros.camera_info_topic} "
                              f"within {float(self.opts['camera_info_timeout']):g} s (publish it, or "
                              "set node.intrinsics_file)")
            return None
        if (w, h) != (intr.width, intr.height):
            self._drop(index, f"image size: the image is {w}x{h} but camera_info says "
                              f"{intr.width}x{intr.height}")
            return None
        if self.role is None:
            from splat_slam_ros.roles import TrackerRole
            try:
                self.role = TrackerRole(self.cfg, intr, bool(self.opts["loop_closure"]))
            except (TrackingError, ValueError) as e:
                self.log.fatal(f"cannot start the tracker: {e}")
                raise SystemExit(2)
            self.size = (w, h)
            ti = self.role.tracker.intrinsics
            self.log.info(f"tracker started on {w}x{h} frames (tracking at "
                          f"{ti.width}x{ti.height})")
        stamp = from_stamp(msg.header.stamp)
        try:
            step, out = self.role.on_frame(Frame(index=index, timestamp=stamp, image=rgb,
                                                 intrinsics=intr))
        except TrackingError as e:
            self._drop(index, f"{e}")
            return None
        self.emit(out)                            # local BA first, then the new keyframe(s)
        if self.role.tracker.initialized and not step.lost:
            self.pub_pose.publish(pose_stamped(step.pose, stamp, self.frame_id))
            if self.pub_tf is not None:
                from .node_common import tf_message
                self.pub_tf.publish(tf_message(step.pose, stamp, self.frame_id,
                                               self.cfg.ros.camera_frame))
            self.stamps.append(stamp)
            self.poses.append(step.pose)
            if step.is_keyframe or len(self.stamps) % max(1, int(self.opts["path_every"])) == 0:
                self._publish_path(stamp)
        return step.kf_id if step.is_keyframe else None

    def _publish_path(self, stamp: float) -> None:
        import numpy as np

        from .node_common import path_msg
        if self.stamps:
            self.pub_path.publish(path_msg(self.stamps, np.stack(self.poses), self.frame_id, stamp))

    def _apply_update(self, msg) -> None:
        from .convert import msg_to_update
        if self.role is not None:
            self.emit(self.role.on_update(msg_to_update(msg)))
        self._maybe_save()

    def _on_final(self, d: dict) -> None:
        if self.role is not None:
            self.role.on_final(str(d.get("node")), d)
        self._maybe_save()

    def _finalize(self) -> None:
        if self.eos:
            return
        self.eos = True
        from splat_slam_ros.roles import Outbox
        out = self.role.finalize() if self.role is not None else \
            Outbox(final={"last_seq": 0, "keyframes": 0})
        kfs = out.final.get("keyframes", 0) if out.final else 0
        self.log.info(f"finalized: {self.n_frames} frames, {kfs} keyframes, "
                      f"{self.n_dropped} dropped")
        out.final = dict(out.final or {}, frames=self.n_frames, dropped=self.n_dropped)
        self.emit(out)
        self._maybe_save()

    def _maybe_save(self) -> None:
        if not self.eos or self.saved or (self.role is not None and not self.role.complete):
            return
        self.saved = True
        files, trk = [], (self.role.tracker if self.role is not None else None)
        if self.output_dir is not None and trk is not None:
            from splat_slam_ros.io.trajectory_io import write_tum
            self.output_dir.mkdir(parents=True, exist_ok=True)
            ts, P = trk.trajectory_full()
            write_tum(self.output_dir / "trajectory_full.txt", ts, P)
            kts, kP = trk.trajectory_keyframes()
            write_tum(self.output_dir / "trajectory_keyframes.txt", kts, kP)
            files = ["trajectory_full.txt", "trajectory_keyframes.txt"]
            if len(kts):
                self.stamps, self.poses = list(ts), list(P)
                self._publish_path(float(ts[-1]) if len(ts) else 0.0)
        self.publish_event("saved", files=files, frames=self.n_frames, dropped=self.n_dropped,
                           keyframes=len(trk.published) if trk is not None else 0,
                           timings={k: round(float(v), 3) for k, v in
                                    (trk.timings.items() if trk is not None else [])})


def main(argv=None) -> int:
    return run_node(TrackerNode, argv)


if __name__ == "__main__":
    sys.exit(main())
