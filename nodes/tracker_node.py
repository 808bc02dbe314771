"""tracker_node: camera frames -> splat_slam_ros.tracking.tracker.Tracker -> keyframes, poses, updates.

Subscribes  ros.image_topic (sensor_msgs/Image: rgb8, bgr8, mono8, rgba8, bgra8) and
            ros.camera_info_topic (sensor_msgs/CameraInfo) — remap with ``--set`` / ``-p``;
            /splat/pose_graph_updates (loop closure / global BA updates -> Tracker.apply_update);
            /splat/graph_events (end_of_stream -> Tracker.finalize()).
Publishes   /splat/keyframes (Keyframe), /splat/pose_graph_updates (its local-BA updates),
            /splat/camera_pose (PoseStamped), /splat/trajectory (Path), /tf map->odom->camera
            + /tf_static camera->camera_optical, /splat/keyframe_markers (MarkerArray; see
            nodes/tf_frames.py), /splat/frame_ack (FrameAck per consumed frame).
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

from .node_common import TOPICS, TRACKER_REASONS, SplatNode, run_node


class TrackerNode(SplatNode):
    def __init__(self):
        super().__init__("tracker", {"input_qos": "sensor", "max_queue": 2,
                                     "camera_info_timeout": 2.0, "intrinsics_file": "",
                                     "loop_closure": True, "mapping": True, "path_every": 10})
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Path as PathMsg
        from sensor_msgs.msg import CameraInfo, Image
        from splat_slam_msgs.msg import FrameAck, Keyframe, PoseGraphUpdate

        from . import qos as Q
        from .tf_frames import TrackerFrames
        n = self.node
        self.pub_kf = n.create_publisher(Keyframe, TOPICS["keyframes"], Q.keyframe_qos())
        self.pub_upd = n.create_publisher(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos())
        self.pub_ack = n.create_publisher(FrameAck, TOPICS["ack"], Q.ack_qos())
        self.pub_pose = n.create_publisher(PoseStamped, TOPICS["camera_pose"], Q.pose_qos())
        self.pub_path = n.create_publisher(PathMsg, TOPICS["trajectory"], Q.status_qos())
        self.frames = TrackerFrames(self, TRACKER_REASONS)     # /tf, /tf_static, markers
        in_qos = Q.image_qos() if self.opts["input_qos"] == "reliable" else Q.sensor_qos()
        # updates first: when an update and a frame are both ready, the update runs first
        self.subscribe(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos(), self._on_update,
                       "PoseGraphUpdate")
        self.subscribe(CameraInfo, self.cfg.ros.camera_info_topic, in_qos, self._on_info,
                       "CameraInfo")
        self.subscribe(Image, self.cfg.ros.image_topic, in_qos, self._on_image, "Image")
        self.on_events(self._on_event)
        self.tracker = None
        self.size = None
        self.intr = None
        self.cam_info = None
        self.info_lock = threading.Condition()
        self.n_frames = 0
        self.n_dropped = 0
        self.queued = 0
        self.last_seq = 0
        self.loop_seq = 0
        self.loop_final: Optional[dict] = None
        self.finalized = False
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
            if self.cam_info is not None and self.tracker is not None and \
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

    def _on_update(self, msg, raw) -> None:
        from .convert import msg_to_update
        ev = msg_to_update(msg)
        if ev.reason in TRACKER_REASONS:          # our own local-BA updates
            return
        self.worker.submit(self._apply_update, ev)

    def _on_event(self, d: dict) -> None:
        if d.get("event") == "end_of_stream" and d.get("node") in ("player", "launch",
                                                                   "camera"):
            self.worker.submit(self._finalize)
        elif d.get("node") == "loop_closure" and d.get("event") == "finalized":
            self.worker.submit(self._loop_finalized, d)

    # ------------------------------------------------------------ work (worker thread)
    def _ack(self, index: int, stamp, kf_id: Optional[int]) -> None:
        from .convert import frame_ack_msg
        m = frame_ack_msg(index, "tracker", 0.0, kf_id)
        m.header.stamp = stamp
        self.pub_ack.publish(m)

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

        from .convert import (ConversionError, from_stamp, keyframe_to_msg, msg_to_rgb,
                              update_to_msg)
        from .node_common import pose_stamped
        try:
            rgb = msg_to_rgb(msg)
        except ConversionError as e:
            self._drop(index, f"{e}")
            return None
        h, w = rgb.shape[:2]
        if self.tracker is not None and (w, h) != self.size:
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
        if self.tracker is None:
            from splat_slam_ros.tracking.tracker import Tracker
            try:
                self.tracker = Tracker(self.cfg, intr, seq_start=1)
            except (TrackingError, ValueError) as e:
                self.log.fatal(f"cannot start the tracker: {e}")
                raise SystemExit(2)
            self.size = (w, h)
            self.log.info(f"tracker started on {w}x{h} frames (tracking at "
                          f"{self.tracker.intrinsics.width}x{self.tracker.intrinsics.height})")
        stamp = from_stamp(msg.header.stamp)
        try:
            step = self.tracker.track(Frame(index=index, timestamp=stamp, image=rgb,
                                            intrinsics=intr))
        except TrackingError as e:
            self._drop(index, f"{e}")
            return None
        now = self.now()
        for ev in step.events:                    # local BA first, then the new keyframe(s)
            self.pub_upd.publish(update_to_msg(ev, now, self.frame_id))
            self.last_seq = max(self.last_seq, int(ev.seq))
        for kd in step.keyframes:
            self.pub_kf.publish(keyframe_to_msg(kd, self.frame_id))
        if step.keyframes:
            self.frames.on_keyframes(self.tracker, stamp)
        if self.tracker.initialized and not step.lost:
            self.pub_pose.publish(pose_stamped(step.pose, stamp, self.frame_id))
            self.frames.on_pose(step.pose, stamp)
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

    def _apply_update(self, ev) -> None:
        if self.tracker is not None:
            self.frames.around_update(self.tracker, ev, self.tracker.apply_update)
            self.frames.on_keyframes(self.tracker, self.frames.last_stamp or 0.0)
        self.loop_seq = max(self.loop_seq, int(ev.seq))
        self._maybe_save()

    def _finalize(self) -> None:
        from .convert import update_to_msg
        if self.finalized:
            return
        evs = self.tracker.finalize() if self.tracker is not None else []
        for ev in evs:
            self.pub_upd.publish(update_to_msg(ev, self.now(), self.frame_id))
            self.last_seq = max(self.last_seq, int(ev.seq))
        self.finalized = True
        kfs = len(self.tracker.published) if self.tracker is not None else 0
        self.log.info(f"finalized: {self.n_frames} frames, {kfs} keyframes, "
                      f"{self.n_dropped} dropped")
        self.publish_event("finalized", last_seq=self.last_seq, keyframes=kfs,
                           frames=self.n_frames, dropped=self.n_dropped)
        self._maybe_save()

    def _loop_finalized(self, d: dict) -> None:
        self.loop_final = d
        self._maybe_save()

    def _maybe_save(self) -> None:
        if not self.finalized or self.saved:
            return
        if self.opts["loop_closure"]:
            if self.loop_final is None:
                return
            if self.loop_seq < int(self.loop_final.get("last_seq", -1)):
                return
        self.saved = True
        files = []
        if self.output_dir is not None and self.tracker is not None:
            from splat_slam_ros.io.trajectory_io import write_tum
            self.output_dir.mkdir(parents=True, exist_ok=True)
            ts, P = self.tracker.trajectory_full()
            write_tum(self.output_dir / "trajectory_full.txt", ts, P)
            kts, kP = self.tracker.trajectory_keyframes()
            write_tum(self.output_dir / "trajectory_keyframes.txt", kts, kP)
            files = ["trajectory_full.txt", "trajectory_keyframes.txt"]
            if len(kts):
                self.stamps, self.poses = list(ts), list(P)
                self._publish_path(float(ts[-1]) if len(ts) else 0.0)
        kfs = len(self.tracker.published) if self.tracker is not None else 0
        self.publish_event("saved", files=files, keyframes=kfs, frames=self.n_frames,
                           dropped=self.n_dropped,
                           timings={k: round(float(v), 3) for k, v in
                                    (self.tracker.timings.items() if self.tracker else [])})


def main(argv=None) -> int:
    return run_node(TrackerNode, argv)


if __name__ == "__main__":
    sys.exit(main())
