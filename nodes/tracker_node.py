"""tracker_node: camera frames -> TrackerRole (flow + dense BA, §3.1) -> keyframes, poses, updates.

Subscribes  ros.image_topic (sensor_msgs/Image: rgb8, bgr8, mono8, rgba8, bgra8, 16-bit
            colour, Bayer, YUV 4:2:2; CompressedImage when it ends in /compressed) and
            ros.camera_info_topic (sensor_msgs/CameraInfo) — remap with ``--set`` / ``-p``;
            /splat/pose_graph_updates (loop closure / global BA updates);
            /splat/graph_events (end_of_stream -> finalize; the loop closer's ``finalized``).
Publishes   /splat/keyframes (Keyframe), /splat/pose_graph_updates (its local-BA updates),
            /splat/camera_pose (PoseStamped), /splat/trajectory (Path), /tf map->odom->camera
            + /tf_static camera->camera_optical, /splat/keyframe_markers (MarkerArray; see
            nodes/tf_frames.py), /splat/frame_ack (FrameAck per consumed frame).
Bad input (unsupported encoding, no camera_info, a size change, undecodable bytes) is a
logged error; the frame is acknowledged as consumed and dropped, the node keeps running
(nodes/camera_input.py). Resize / crop / undistort follow ``camera.*`` (the Tracker's
preprocessor). Node options: node.input_qos (sensor = BEST_EFFORT, matches any camera
driver; reliable for the bag player), node.max_queue (frames in flight, waiting or being
tracked; 1: a frame is tracked only when the tracker is free, so a live camera stays current;
the others are skipped: posed at once by constant velocity and placed between their tracked
neighbours in the final trajectory, the stream's last frame tracked at its end when it was
skipped; the launcher sets 0 = track every frame in lockstep), node.max_backlog (worker jobs waiting beyond which a frame is dropped),
node.camera_info_timeout, node.intrinsics_file (when no camera_info is published),
node.path_every (the trajectory Path is published at every keyframe and every N frames),
node.loop_closure / node.mapping (which stages the graph runs; set by the launcher).
"""
from __future__ import annotations

import sys
from typing import List, Optional

import numpy as np

from splat_slam_ros.types import TRACKER_REASONS

from .map_requests import answer_save, load_request, reply
from .node_common import TOPICS, SplatNode, run_node, takes_update
from .node_options import NODE_OPTIONS


class TrackerNode(SplatNode):
    def __init__(self):
        super().__init__("tracker", NODE_OPTIONS["tracker"])
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Path as PathMsg
        from splat_slam_msgs.msg import PoseGraphUpdate

        from splat_slam_ros.roles import TrackerRole  # (torch, OpenCV before 'ready')

        from . import qos as Q
        from .camera_input import CameraInput
        from .tf_frames import TrackerFrames
        n = self.node
        self.publishers("keyframes", "updates", "ack")
        self.pub_pose = n.create_publisher(PoseStamped, TOPICS["camera_pose"], Q.pose_qos())
        self.pub_path = n.create_publisher(PathMsg, TOPICS["trajectory"], Q.status_qos())
        self.frames = TrackerFrames(self, TRACKER_REASONS)     # /tf, /tf_static, markers
        # updates first: when an update and a frame are both ready, the update runs first
        self.subscribe(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos(),
                       lambda m, raw: takes_update(m, TrackerRole.update_sources) and
                       self.worker.submit(self._apply_update, m), "PoseGraphUpdate")
        self.camera = CameraInput(self, self._track, self._skip)
        self.on_events(self._on_event)
        self.role = None                    # splat_slam_ros.roles.TrackerRole, on the first frame
        self.localize = bool(self.opts["localize"])
        self.kf_images: dict = {}           # kf id -> published image (the session's keyframes)
        self.kf_arrival: dict = {}          # kf id -> its frame's arrival here (epoch s)
        self.eos = self.saved = False
        self.stamps: List[float] = []
        self.poses: List = []
        self._store = self.store()          # node.state_dir: checkpoints, resume after a crash
        if TrackerRole.stored_intrinsics(self._store) is not None:
            self._resume()
        self.log.info(f"listening on {self.cfg.ros.image_topic} + {self.cfg.ros.camera_info_topic} "
                      f"({self.opts['input_qos']} QoS)")
        self.publish_event("ready")

    def _resume(self) -> None:
        """Rebuild the tracker from its checkpoint; the input continues after its newest frame
        (``resumed`` event: the bag player rewinds to it in lockstep)."""
        import os
        import time

        from splat_slam_ros.roles import TrackerRole
        from splat_slam_ros.tracking.tracker import TrackingError
        from splat_slam_ros.tracking.tracker_state import TrackerStateError
        intr = TrackerRole.stored_intrinsics(self._store)
        try:
            self.role = self._make_role(intr)
        except (TrackingError, TrackerStateError, ValueError) as e:
            self.log.fatal(f"cannot resume the tracker from {self.state_dir}: {e}")
            raise SystemExit(2)
        trk, stamp = self.role.tracker, self.role.resume_stamp
        trk.on_pose_estimate = self._early_pose
        self.camera.resume(intr, stamp, (trk.records[-1].index + 1) if trk.records else 0)
        if self.role.resumed:
            self.log.info(f"resumed from {self.state_dir}: {len(trk.published)} keyframes, "
                          f"{len(trk.records)} frames, next keyframe id {trk.next_kf}")
        else:
            self.log.info(f"restarted before its first checkpoint ({self.state_dir}): "
                          "tracking again from the first frame")
        self.emit(self.role.resume_outbox())      # consumers skip what they hold
        self.publish_event("resumed", stamp=stamp, keyframes=len(trk.published),
                           incarnation=f"{os.getpid()}-{time.time():.6f}")

    def _on_event(self, d: dict) -> None:
        if d.get("event") == "end_of_stream" and d.get("node") in ("player", "launch",
                                                                   "camera"):
            self.worker.submit_final(self._finalize)
        elif d.get("event") == "finalized":
            self.worker.submit_final(self._on_final, d)
        elif d.get("event") in ("save_map", "load_map") and load_request(d, self.started):
            self.worker.submit(self._save_map if d["event"] == "save_map" else self._load_map, d)

    # ------------------------------------------------------------ the launcher's map services
    def _save_map(self, d: dict) -> None:
        """/splat/save_map: the trajectories and the keyframes' part of DIR/session/ now."""
        trk = self.role.tracker if self.role is not None else None
        if trk is None or self.localize or not trk.keyframe_ids():
            return reply(self, "map_saved", d, False, "no keyframe yet: nothing to save" if
                         not self.localize else "localize-only: the map is read-only")
        answer_save(self, d, lambda out: self._write_outputs(trk, *trk.trajectory_full(), out))

    def _load_map(self, d: dict) -> None:
        """/splat/load_map: the session (checked by the launcher) becomes node.load_map, taken
        by the role the first frame makes; refused once a frame was tracked."""
        from pathlib import Path
        run = d.get("run")
        if self.role is not None or self.opts["load_map"]:
            why = (f"a map is loaded already ({self.opts['load_map']})" if self.opts["load_map"]
                   else "frames were tracked already: load a map before the first frame, or "
                   "start splat-slam-launch with --load-map")
            return reply(self, "map_loaded", d, False, why)
        if not isinstance(run, str) or not (Path(run) / "session").is_dir():
            return reply(self, "map_loaded", d, False, f"no saved session in {run!r}")
        self.opts["load_map"], self.localize = run, d.get("localize") is True
        self.log.info(f"loaded map {self.opts['load_map']} "
                      f"({'localize-only' if self.localize else 'extend'})")
        reply(self, "map_loaded", d, True, "the next frame relocalises in it",
              run=self.opts["load_map"], localize=self.localize, mapping=d.get("mapping") or {})

    def _make_role(self, intr):
        """TrackerRole; with node.load_map the session it continues (an ExtendTracker) or,
        with node.localize, a LocalizeRole in it (SessionError: a ValueError)."""
        from pathlib import Path

        from splat_slam_ros.roles import TrackerRole
        loop, path = bool(self.opts["loop_closure"]), str(self.opts["load_map"])
        if not path:
            return TrackerRole(self.cfg, intr, loop, store=self._store)
        from splat_slam_ros.io.session import load_session
        session = load_session(Path(path))
        if self.localize:
            from splat_slam_ros.localize import LocalizeRole
            return LocalizeRole(self.cfg, intr, session)
        from splat_slam_ros.tracking.relocalise import ExtendTracker
        return TrackerRole(self.cfg, intr, loop, store=self._store,
                           tracker=ExtendTracker(self.cfg, intr, session))

    # ------------------------------------------------------------ work (worker thread)
    def _track(self, frame) -> Optional[int]:
        from splat_slam_ros.tracking.tracker import TrackingError
        if self.role is None:
            try:
                self.role = self._make_role(frame.intrinsics)
            except (TrackingError, ValueError) as e:
                self.log.fatal(f"cannot start the tracker: {e}")
                raise SystemExit(2)
            ti = self.role.tracker.intrinsics
            self.role.tracker.on_pose_estimate = self._early_pose
            self.log.info(f"tracker started on {frame.intrinsics.width}x{frame.intrinsics.height} "
                          f"frames (tracking at {ti.width}x{ti.height})")
        trk = self.role.tracker
        relocs = getattr(trk, "n_relocalisations", 0)
        try:
            step, out = self.role.on_frame(frame)
        except TrackingError as e:
            return self.camera.drop(frame.index, f"{e}")
        self.emit(out)                            # local BA first, then the new keyframe(s)
        self._keep_keyframes(out)
        stamp = frame.timestamp
        if getattr(trk, "n_relocalisations", 0) > relocs:     # in a loaded map (node.load_map)
            self._relocalised(frame.index, trk, step.pose)
        if out.keyframes:
            self.frames.on_keyframes(self.role.tracker, stamp)
        if self.role.tracker.initialized and not step.lost:
            self._publish_pose(frame.index, stamp, step.pose)
            self.stamps.append(stamp)
            self.poses.append(step.pose)
            if step.is_keyframe or len(self.stamps) % max(1, int(self.opts["path_every"])) == 0:
                self._publish_path(stamp)
        return step.kf_id if step.is_keyframe else None

    def _relocalised(self, index: int, trk, T) -> None:
        """Located in the loaded map: the jump goes into map -> odom; a graph event says so."""
        self.frames.relocalised(T)
        first = trk.relocalised_frame == index
        self.log.info(f"frame {index}: {'relocalised' if first else 'relocalised again'} in the "
                      f"loaded map ({self.opts['load_map']})")
        self.publish_event("relocalised", frame=int(index), first=bool(first),
                           keyframe=trk.relocalised_keyframe, count=int(trk.n_relocalisations))

    def _publish_pose(self, index: int, stamp: float, T, tf: bool = True) -> None:
        """A frame's pose on /splat/camera_pose (and /tf), its latency recorded."""
        from .node_common import pose_stamped
        self.pub_pose.publish(pose_stamped(T, stamp, self.frame_id))
        if tf:
            self.frames.on_pose(T, stamp)
        self.camera.posed(index)

    def _early_pose(self, index: int, stamp: float, T) -> None:
        """A frame's pose before its step ends (the refined pose and its /tf follow), so the
        pose latency waits neither for a new keyframe's local BA (its pose from its alignment)
        nor for the skipped frames tracked to bridge a large motion (its predicted pose)."""
        self._publish_pose(index, stamp, T, tf=False)

    def _skip(self, index: int, stamp: float, now: bool, frame=None) -> None:
        """A frame the busy tracker skips (live input). ``now`` (executor thread, at arrival):
        publish its constant-velocity pose; else (worker, in frame order): record it, to be
        placed between its tracked neighbours in the final trajectory (``frame``: its image,
        a possible bridge for the next tracked frame)."""
        role = self.role
        if role is None:
            return
        if not now:
            role.tracker.skip(index, stamp, frame)
        elif role.tracker.initialized:
            self._publish_pose(index, stamp, role.tracker.predict())

    def _publish_path(self, stamp: float) -> None:
        from .node_common import path_msg
        if self.stamps:
            self.pub_path.publish(path_msg(self.stamps, np.stack(self.poses), self.frame_id, stamp))

    def _apply_update(self, msg) -> None:
        from .convert import msg_to_update
        from .msg_checks import check_update
        if self.role is not None:
            trk = self.role.tracker
            self.frames.around_update(trk, msg_to_update(check_update(msg)),
                                      lambda ev: self.emit(self.role.on_update(ev)))
            self.frames.on_keyframes(trk, self.frames.last_stamp or 0.0)
        self._maybe_save()

    def _on_final(self, d: dict) -> None:
        if self.role is not None:
            self.role.on_final(str(d.get("node")), d)
        self._maybe_save()

    def _finalize(self) -> None:
        from splat_slam_ros.roles import Outbox
        if self.eos:
            return
        self.eos = True
        unskip = getattr(self.role.tracker, "unskip", None) if self.role is not None else None
        if unskip is not None and self.camera.track_last(unskip):
            self.log.info("the last frame, skipped while the tracker was busy, tracked at the end")
        out = self.role.finalize() if self.role is not None else Outbox(final={"last_seq": 0})
        c = self.camera
        self.log.info(f"finalized: {c.n_frames} frames, {self._keyframes()} keyframes, "
                      f"{self._skipped()} skipped (posed by interpolation), {c.n_dropped} "
                      f"dropped")
        out.final = dict(out.final or {}, keyframes=self._keyframes(), frames=c.n_frames,
                         dropped=c.n_dropped)
        self.emit(out)
        self._keep_keyframes(out)
        self._maybe_save()

    def _keep_keyframes(self, out) -> None:
        """The published keyframes' images (the session's keyframes) and their frames'
        arrival (the launcher's map lag: arrival -> mapped)."""
        for kd in out.keyframes:
            self.kf_images[kd.kf_id] = kd.image
            t = self.camera.arrival_epoch.get(int(kd.frame_index))
            if t is not None:
                self.kf_arrival[int(kd.kf_id)] = t

    def _skipped(self) -> int:
        """Frames skipped and never tracked: those tracked after all as bridges count as
        tracked."""
        trk = self.role.tracker if self.role is not None else None
        return self.camera.n_skipped - int(getattr(trk, "n_bridged", 0))

    def _keyframes(self) -> int:
        return len(self.role.tracker.published) if self.role is not None else 0

    def _maybe_save(self) -> None:
        if not self.eos or self.saved or (self.role is not None and not self.role.complete):
            return
        self.saved = True
        files, trk = [], (self.role.tracker if self.role is not None else None)
        posed = 0
        if self.output_dir is not None and trk is not None:
            self.output_dir.mkdir(parents=True, exist_ok=True)
            ts, P = trk.trajectory_full()
            files = self._write_outputs(trk, ts, P)
            posed = len(ts)
            if len(ts):
                self.stamps, self.poses = list(ts), list(P)
                self._publish_path(float(ts[-1]))
        self.publish_event("saved", files=files, frames=self.camera.n_frames,
                           session=self._session_info(trk),
                           dropped=self.camera.n_dropped, skipped=self._skipped(),
                           lost=trk.n_lost if trk is not None else 0,
                           posed=posed, latency_ms=self.camera.latency_stats(),
                           keyframes=self._keyframes(),
                           **(trk.keyframe_summary() if trk is not None else {}),
                           keyframe_arrival={str(k): round(t, 4)
                                             for k, t in sorted(self.kf_arrival.items())},
                           timings={k: round(float(v), 3) for k, v in
                                    (trk.timings.items() if trk is not None else [])})

    def _write_outputs(self, trk, ts, P, out=None) -> List[str]:
        """trajectory_full.txt (the posed frames), and unless localizing
        trajectory_keyframes.txt, frames_skipped.txt (live input: the frames skipped on
        arrival) and the keyframes' part of session/ (the mapper node writes its map state
        there): a later run can load this one's map. Into node.output_dir or ``out``."""
        from splat_slam_ros.io.trajectory_io import write_tum
        out = out or self.output_dir
        if len(ts) or not self.localize:
            write_tum(out / "trajectory_full.txt", ts, P)
        if self.localize:
            return ["trajectory_full.txt"] if len(ts) else []
        write_tum(out / "trajectory_keyframes.txt", *trk.trajectory_keyframes())
        files = ["trajectory_full.txt", "trajectory_keyframes.txt", "session/"]
        if trk.skipped_at:          # splat-slam-run --skip-frames replays this tracker's work
            from splat_slam_ros.io.trajectory_io import SKIPPED_FRAMES, write_stamps
            write_stamps(out / SKIPPED_FRAMES, [t for _, t in trk.skipped_at],
                         "frames the live tracker skipped on arrival (timestamp, s); "
                         "splat-slam-run INPUT --skip-frames FILE replays them")
            files.append(SKIPPED_FRAMES)
        from splat_slam_ros.tracking.relocalise import (published_images, save_session,
                                                        session_ids)
        images = dict(self.kf_images)
        for k in session_ids(trk):          # published before a restart: the checkpoint's
            if k not in images and self._store is not None and self._store.has(f"timg{k}"):
                images[k] = self._store.get(f"timg{k}")["image"]
        save_session(trk, published_images(trk, images), self.cfg, self.role.intrinsics, out)
        return files

    def _session_info(self, trk) -> Optional[dict]:
        """The loaded session's part of the launcher's metrics (node.load_map)."""
        if trk is None or not self.opts["load_map"]:
            return None
        info = {"session": str(self.opts["load_map"]), "localize": self.localize,
                "relocalised_frame": trk.relocalised_frame,
                "relocalised_keyframe": trk.relocalised_keyframe,
                "relocalisations": int(trk.n_relocalisations)}
        if not self.localize:
            info.update(loaded_keyframes=len(trk.loaded_ids),
                        new_keyframes=len(trk.new_keyframe_ids()))
        return info


def main(argv=None) -> int:
    return run_node(TrackerNode, argv)


if __name__ == "__main__":
    sys.exit(main())
