"""The tracker node's camera intake: sensor_msgs/Image (or CompressedImage on a topic ending in
``/compressed``, image_transport's name, or wherever the camera publishes that type:
``SplatNode.subscribe_image``) + CameraInfo -> core Frames.

Decodes every image on the executor-independent worker, checks it against the calibration
(camera_info, or ``node.intrinsics_file`` when no camera_info is published) and the size the
tracker started with, and drops what it cannot use with a logged reason; every frame, used
or dropped, is acknowledged on /splat/frame_ack (lockstep). ``node.max_queue`` bounds the
frames in flight (waiting or being tracked; 1 = a frame is tracked only when the tracker is
free, so a live camera stays current; 0 = never skip): a frame that arrives while that many
are in flight is *skipped*, not dropped: its constant-velocity pose is published at once and
the final trajectory places it between its tracked neighbours (``Tracker.skip``); when the
stream ends, its last frame, if skipped, is tracked (``track_last``), so no skipped frame lies
after the last tracked one. Only when ``node.max_backlog`` jobs already wait for the worker
is a frame dropped. Pose latency (arrival at this node -> pose published) is kept per frame,
and the arrival (epoch s) of the newest ARRIVALS_KEPT frames: the map lag of a keyframe
counts from its frame's arrival (``spread``, the launcher's ``map_lag_s``).
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict
from typing import Callable, Dict, List, Optional, Sequence, Tuple

ARRIVALS_KEPT = 1024        # frames whose arrival a keyframe made later still looks up


def spread(values: Sequence[float], ndigits: int = 2) -> Dict[str, float]:
    """p50 / p95 / max of ``values`` and their count (``frames``; {} when there are none)."""
    import numpy as np
    if not len(values):
        return {}
    a = np.asarray(values, dtype=float)
    return {"p50": round(float(np.percentile(a, 50)), ndigits),
            "p95": round(float(np.percentile(a, 95)), ndigits),
            "max": round(float(a.max()), ndigits), "frames": int(a.size)}


class CameraInput:
    def __init__(self, owner, on_frame: Callable, on_skip: Callable):
        """``on_frame(frame)`` runs on the owner's worker; it returns the kf_id made or None.
        ``on_skip(index, stamp, now, frame=None)``: a skipped frame, once on the executor at
        arrival (``now``: publish its predicted pose) and once on the worker (record it, with
        its decoded ``frame`` when ``tracking.bridge_frames`` keeps skipped frames)."""
        from sensor_msgs.msg import CameraInfo

        from . import qos as Q
        self.owner, self.on_frame, self.on_skip = owner, on_frame, on_skip
        o, self.opts, self.cfg = owner, owner.opts, owner.cfg
        self.size: Optional[Tuple[int, int]] = None
        self.intr = None
        self.cam_info = None
        self.info_lock = threading.Condition()
        self.n_frames = self.n_dropped = self.n_skipped = self.queued = 0
        self.count_lock = threading.Lock()        # queued: executor += / worker -=
        self.arrived: Dict[int, float] = {}       # frame index -> arrival (monotonic s)
        self.latency_ms: List[float] = []         # arrival -> pose published, per posed frame
        self.arrival_epoch: "OrderedDict[int, float]" = OrderedDict()  # newest ARRIVALS_KEPT
        self.last_ns: Optional[int] = None        # newest frame stamp taken (replays: older)
        self.last_skipped = None                  # (message, index) of the newest skipped frame
        # a replayed frame is recognised by its stamp on the player's reliable input (a live
        # camera's clock may jump back: its frames are never dropped for that)
        self.dedup = self.opts["input_qos"] == "reliable"
        if self.opts["intrinsics_file"]:
            from splat_slam_ros.types import Intrinsics, IntrinsicsError
            try:
                self.intr = Intrinsics.from_yaml(self.opts["intrinsics_file"])
            except IntrinsicsError as e:
                o.log.fatal(str(e))
                raise SystemExit(2)
        in_qos = Q.image_qos() if self.opts["input_qos"] == "reliable" else Q.sensor_qos()
        o.subscribe(CameraInfo, self.cfg.ros.camera_info_topic, in_qos, self._on_info,
                    "CameraInfo")
        o.subscribe_image(self.cfg.ros.image_topic, in_qos, self._on_image,
                          lambda: self.n_frames > 0)

    # ------------------------------------------------------------ callbacks (executor)
    def _on_info(self, msg, raw) -> None:
        from .convert import ConversionError, camera_info_to_intrinsics
        try:
            intr = camera_info_to_intrinsics(msg)
        except ConversionError as e:
            self.owner.warn_throttled("info", f"ignoring camera_info: {e}")
            return
        key = lambda i: (i.fx, i.fy, i.cx, i.cy, i.width, i.height)  # noqa: E731
        with self.info_lock:
            if self.cam_info is not None and self.size is not None and \
                    key(intr) != key(self.cam_info):
                self.owner.warn_throttled("info-change", "camera_info changed while tracking; "
                                          "the tracker keeps its initial calibration",
                                          error=False)
                return
            self.cam_info = intr
            self.info_lock.notify_all()

    def resume(self, intr, stamp: Optional[float], n_frames: int) -> None:
        """A tracker restored from its checkpoint: frames up to ``stamp`` are replays."""
        self.cam_info = self.cam_info or intr
        self.size = (intr.width, intr.height)
        self.n_frames = int(n_frames)
        self.last_ns = None if stamp is None else int(round(stamp * 1e9))
        self.dedup = True

    def _on_image(self, msg, raw) -> None:
        if msg.header.stamp.sec == 0 and msg.header.stamp.nanosec == 0:
            # a driver that never sets the stamp: the arrival time
            msg.header.stamp = self.owner.node.get_clock().now().to_msg()
            self.owner.warn_throttled("unstamped", f"frames on {self.cfg.ros.image_topic} have "
                                      "no header stamp: stamped at arrival (set the stamp in "
                                      "the camera driver: the trajectory and the keyframe rate "
                                      "go by camera time)", error=False)
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if self.last_ns is not None and ns <= self.last_ns + 1000:
            # a replay (the player resumed from its last acknowledged frame, or the tracker
            # from a checkpoint after it): acknowledged, not tracked twice
            self._ack(max(self.n_frames - 1, 0), msg.header.stamp, None)
            return
        if self.dedup:
            self.last_ns = ns
        mq = int(self.opts["max_queue"])
        index = self.n_frames
        self.n_frames += 1
        self.arrived[index] = time.monotonic()
        self.arrival_epoch[index] = time.time()
        if len(self.arrival_epoch) > ARRIVALS_KEPT:
            self.arrival_epoch.popitem(last=False)
        with self.count_lock:
            busy = mq > 0 and self.queued >= mq   # realtime: mq frames in flight already
            if not busy:
                self.queued += 1
        if busy:
            if self.owner.worker.pending() >= int(self.opts["max_backlog"]):
                self.n_dropped += 1               # the worker is behind by the whole bound
                self.arrived.pop(index, None)
                self._ack(index, msg.header.stamp, None)
                self.owner.warn_throttled("drop", f"tracker backlog full: dropped frame {index} "
                                          f"({self.n_dropped} so far)", error=False)
                return
            self.n_skipped += 1
            self.last_skipped = (msg, index)
            from .convert import from_stamp
            stamp = from_stamp(msg.header.stamp)
            self.on_skip(index, stamp, now=True)      # the predicted pose, at once
            self.owner.worker.submit(self._skip, index, stamp, msg.header.stamp, msg)
            return
        self.owner.worker.submit(self._process, msg, index)

    def posed(self, index: int) -> None:
        """The pose of frame ``index`` was published: its latency is recorded."""
        t = self.arrived.pop(index, None)
        if t is not None:
            self.latency_ms.append(1000.0 * (time.monotonic() - t))

    def latency_stats(self) -> Dict[str, float]:
        """Pose latency (arrival -> pose published) over the posed frames, in ms."""
        return spread(self.latency_ms)

    # ------------------------------------------------------------ worker thread
    def _ack(self, index: int, stamp, kf_id: Optional[int]) -> None:
        from .convert import frame_ack_msg
        m = frame_ack_msg(index, "tracker", 0.0, kf_id)
        m.header.stamp = stamp
        self.owner.pubs["ack"].publish(m)

    def _intrinsics(self):
        if self.intr is not None and self.cam_info is None:
            return self.intr
        with self.info_lock:
            if self.cam_info is None:
                self.info_lock.wait(timeout=float(self.opts["camera_info_timeout"]))
            return self.cam_info

    def _skip(self, index: int, stamp: float, ros_stamp, msg) -> None:
        # the record, in frame order, with the image: the next tracked frame may track it
        # after all to bridge a large motion (tracking.bridge_frames)
        frame = self._frame(msg, index, quiet=True) if self.cfg.tracking.bridge_frames else None
        self.on_skip(index, stamp, now=False, frame=frame)
        self._ack(index, ros_stamp, None)

    def _process(self, msg, index: int) -> None:
        kf_id = None
        try:
            frame = self._frame(msg, index)
            if frame is not None:
                kf_id = self.on_frame(frame)
        finally:
            with self.count_lock:
                self.queued -= 1                   # in flight until tracked
            self.arrived.pop(index, None)          # not posed (warm-up, lost, dropped)
            self._ack(index, msg.header.stamp, kf_id)

    def track_last(self, unskip: Callable[[int], bool]) -> bool:
        """End of input (worker): the stream's last frame, when it was skipped, is tracked now
        that the tracker is free, so the skipped frames before it lie between tracked frames
        (interpolated) instead of after the last one (extrapolated: up to 11 cm off on the
        fr2/desk render's last 0.7 s). ``unskip(index)`` takes back its skipped record."""
        last, self.last_skipped = self.last_skipped, None
        if last is None or last[1] != self.n_frames - 1 or not unskip(last[1]):
            return False
        self.n_skipped -= 1                        # tracked now (or dropped, and counted so)
        frame = self._frame(*last)
        if frame is not None:
            self.on_frame(frame)
        return frame is not None

    def drop(self, index: int, why: str) -> None:
        self.n_dropped += 1
        self.owner.warn_throttled(why.split(":")[0], f"frame {index} dropped: {why}")

    def _frame(self, msg, index: int, quiet: bool = False):
        """The core Frame of an Image message, or None: dropped with a logged reason (``quiet``:
        None, nothing counted: a skipped frame's image that cannot serve as a bridge)."""
        from splat_slam_ros.types import Frame

        from .convert import ConversionError, from_stamp, msg_to_rgb
        try:
            rgb = msg_to_rgb(msg)
        except ConversionError as e:
            return None if quiet else self.drop(index, f"{e}")
        h, w = rgb.shape[:2]
        if quiet and (self.size is None or (w, h) != self.size or self.intr is None and
                      self.cam_info is None):
            return None
        if self.size is not None and (w, h) != self.size:
            return self.drop(index, f"image size changed: {w}x{h}, the tracker runs on "
                                    f"{self.size[0]}x{self.size[1]} (restart the graph for a "
                                    "new size)")
        intr = self._intrinsics()
        if intr is None:
            return self.drop(index, f"no camera_info received on {self.cfg.ros.camera_info_topic}"
                                    f" within {float(self.opts['camera_info_timeout']):g} s "
                                    "(publish it, or set node.intrinsics_file)")
        if (w, h) != (intr.width, intr.height):
            return self.drop(index, f"image size: the image is {w}x{h} but camera_info says "
                                    f"{intr.width}x{intr.height}")
        self.size = (w, h)
        return Frame(index=index, timestamp=from_stamp(msg.header.stamp), image=rgb,
                     intrinsics=intr)
