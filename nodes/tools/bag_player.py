"""splat-slam-bag-player: play a rosbag2 (MCAP, CDR) into the graph — ``ros2 bag play`` is
not on PyPI.

Messages are republished as the raw CDR bytes stored in the bag (no decoding). A *frame* is
one message of the image topic together with the other selected messages of the same log
time (camera_info; depth / ground truth with ``--topics all``); before each frame the bag
time is published on ``/clock`` (rosgraph_msgs/Clock) for nodes with ``use_sim_time``.

Modes
- ``lockstep`` (default): frame N+1 is published only after frame N was consumed: the
  tracker's FrameAck with the image's stamp, and — when that frame made keyframe K — the
  acks of the ``--wait-acks`` consumers (default loop_closure, mapper) for a keyframe id
  >= K. Nothing is dropped however slow the machine; results match the in-process pipeline.
- ``realtime``: frames at bag time / ``--rate``; no waiting (a slow tracker drops frames).

Before the first message the player waits until the image and camera_info topics have
subscribers and the ``--wait-nodes`` have announced ``ready`` on /splat/graph_events.
After the last frame it publishes ``end_of_stream`` there (the launcher's finalisation
starts from it) and exits 0.
"""
from __future__ import annotations

import argparse
import json
import struct
import sys
import time
from typing import Dict, List, Optional, Tuple

from splat_slam_ros.io.bag_reader import BagFile
from splat_slam_ros.types import DatasetError

from ..node_common import TOPICS, events_qos, graph_event, init_process
from ..tool_runner import run_rclpy_tool, usage_error
from .msg_types import UnknownMessageType, message_class

ROLE_TOPICS = ("image", "camera_info", "depth", "gt_pose")


class PlayerError(Exception):
    """User-facing error: printed as ``error: ...``, exit status 2."""


def cdr_stamp_ns(raw: bytes) -> Optional[int]:
    """header.stamp of a serialized message whose first field is std_msgs/Header."""
    if len(raw) < 12:
        return None
    little = raw[1] in (0x01, 0x03)
    sec, nsec = struct.unpack("<iI" if little else ">iI", raw[4:12])
    return sec * 1_000_000_000 + nsec


def shift_stamp(raw: bytes, delta_ns: int) -> bytes:
    """A serialized message (std_msgs/Header first) with header.stamp moved by ``delta_ns``."""
    ns = cdr_stamp_ns(raw)
    if ns is None:
        return raw
    ns += int(delta_ns)
    little = raw[1] in (0x01, 0x03)
    return raw[:4] + struct.pack("<iI" if little else ">iI", ns // 10**9, ns % 10**9) + raw[12:]


def _import_type(name: str):
    try:
        return message_class(name)
    except UnknownMessageType as e:
        raise PlayerError(str(e)) from None


class BagReader(BagFile):
    """The core bag reader (``io.bag_reader.BagFile``) with the player's views: ``types``
    {topic: type name} and ``counts`` {topic: messages}; a bad bag is a PlayerError."""

    def __init__(self, path):
        try:
            super().__init__(path)
            topics = self.topics()
        except DatasetError as e:
            raise PlayerError(str(e)) from None
        self.types: Dict[str, str] = {t: ty for t, (ty, _n) in topics.items()}
        self.counts: Dict[str, int] = {t: n for t, (_ty, n) in topics.items()}


def graph_topics(reader: BagReader, path, overrides: Dict, calibrated: bool = False
                 ) -> Dict[str, Optional[str]]:
    """For ``splat-slam-launch --bag``: the bag's camera topics ({role: topic in the bag}) and
    the graph's (``image_out``, ``info_out``; ``ros.*_topic`` in ``overrides`` win): this
    project's layout, or a bag recorded elsewhere (its one image topic and that camera's
    camera_info, ``bagio.camera_topics``; none needed when ``calibrated``: the tracker has a
    calibration file). Compressed images go out on a ``.../compressed`` name, where the
    tracker takes CompressedImage."""
    from splat_slam_ros.io.bagio import DEFAULT_TOPICS, T_COMPRESSED, camera_topics
    from splat_slam_ros.io.sensor_codec import compressed_topic, is_compressed_topic
    roles = dict(DEFAULT_TOPICS)
    roles.update(reader.info.get("topics") or {})
    try:
        image, info = camera_topics(path, reader.topics(), roles, {}, calibrated)
    except DatasetError as e:
        raise PlayerError(f"{e} (options of splat-slam-convert and splat-slam-run; the graph "
                          "takes a calibration with --camera-info FILE, and the topic choice "
                          "from a converted bag: splat-slam-convert BAG --out NEW "
                          "[--image-topic T] [--camera-info-topic T] [--intrinsics FILE])") from None
    compressed = reader.types[image] == T_COMPRESSED
    out = str(overrides.get("ros.image_topic") or image)
    if compressed and not is_compressed_topic(out):
        if "ros.image_topic" in overrides:
            raise PlayerError(f"the bag's images ({image}) are CompressedImage: "
                              "ros.image_topic must end in /compressed")
        out = compressed_topic(out)
    elif not compressed and is_compressed_topic(out):
        raise PlayerError(f"{out} ends in /compressed, but the bag's images ({image}) are raw "
                          "sensor_msgs/Image")
    return {"image": image, "camera_info": info, "image_out": out,
            "info_out": overrides.get("ros.camera_info_topic") or info}


def launch_args(a, bag_topics: Dict, nodes: List[str], wait_nodes: List[str], out_dir
                ) -> List[str]:
    """Command line of the player child of splat-slam-launch ``--bag`` (``bag_topics``:
    :func:`graph_topics`; ``nodes``: the graph's, whose acks lockstep waits for)."""
    from pathlib import Path
    acks = [n for n in ("loop_closure", "mapper") if n in nodes]
    args = [sys.executable, "-m", "splat_slam_nodes.tools.bag_player", str(Path(a.bag).resolve()),
            "--mode", a.mode, "--rate", str(a.rate), "--wait-nodes", ",".join(wait_nodes),
            "--wait-acks", ",".join(acks), "--start-timeout", str(a.start_timeout)]
    if a.max_frames:
        args += ["--max-frames", str(a.max_frames)]
    if out_dir is not None:
        args += ["--state", str(Path(out_dir) / "state" / "player")]
    if a.loop_bag > 1:
        args += ["--loop", str(a.loop_bag)]
    bt = bag_topics
    args += ["--image-topic", bt["image"], "--out-image", bt["image_out"]]
    if bt["camera_info"]:
        args += ["--camera-info-topic", bt["camera_info"], "--out-camera-info", bt["info_out"]]
    return args


def frames(reader: BagReader, topics: List[str], image_topic: str):
    """Groups of (topic, raw) with one image each, in log-time order. A message without a
    header stamp (0: a camera driver that never set it) gets its log time, as the bag's
    frames do when read (``bagio.BagDataset``): the tracker and the acks go by stamps."""
    group: List[Tuple[str, bytes]] = []
    group_t = None
    for topic, t, raw in reader.raw_messages(topics):
        if group_t is not None and t != group_t and any(tp == image_topic for tp, _ in group):
            yield group_t, group
            group = []
        group_t = t
        group.append((topic, shift_stamp(raw, t) if cdr_stamp_ns(raw) == 0 else raw))
    if any(tp == image_topic for tp, _ in group):
        yield group_t, group


class Player:
    def __init__(self, args, reader: BagReader):
        import rclpy
        from rosgraph_msgs.msg import Clock
        from splat_slam_msgs.msg import FrameAck
        from std_msgs.msg import String

        from .. import qos as Q
        self.args = args
        self.reader = reader
        self.node = rclpy.create_node(args.name)
        self.log = self.node.get_logger()
        bag_topics = dict(reader.info.get("topics") or {})
        self.roles = {r: (getattr(args, f"{r}_topic") or bag_topics.get(r) or
                          {"image": "/camera/image_raw", "camera_info": "/camera/camera_info",
                           "depth": "/camera/depth", "gt_pose": "/ground_truth/pose"}[r])
                      for r in ROLE_TOPICS}
        if self.roles["image"] not in reader.types:
            raise PlayerError(f"bag has no image topic {self.roles['image']!r} "
                              f"(topics: {', '.join(sorted(reader.types))}); pass "
                              "--image-topic, or convert a bag recorded elsewhere first: "
                              "splat-slam-convert BAG --out NEW [--image-topic TOPIC]")
        roles = ("image", "camera_info") if args.topics == "camera" else ROLE_TOPICS
        self.topics = [self.roles[r] for r in roles if self.roles[r] in reader.types]
        self.remap = {self.roles["image"]: args.out_image or self.roles["image"],
                      self.roles["camera_info"]: args.out_camera_info or self.roles["camera_info"]}
        self.pubs = {}
        for t in self.topics:
            self.pubs[t] = self.node.create_publisher(_import_type(reader.types[t]),
                                                      self.remap.get(t, t), Q.image_qos())
        self.clock_pub = self.node.create_publisher(Clock, "/clock", 10) if args.clock else None
        self.events_pub = self.node.create_publisher(String, TOPICS["events"], events_qos())
        self.String = String
        self.ready_nodes = set()
        self.progress = PlayerProgress(args.state) if args.state else None
        self.rewind: Optional[int] = None       # a restarted tracker's resume stamp (ns)
        self.acks: Dict[str, Dict] = {}
        self.tracker_acks: Dict[int, Tuple[bool, int]] = {}
        self.node.create_subscription(FrameAck, TOPICS["ack"], self._on_ack, Q.ack_qos())
        self.node.create_subscription(String, TOPICS["events"], self._on_event, events_qos())

    # ---------------------------------------------------------------- callbacks
    def _on_ack(self, m) -> None:
        ns = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        if m.consumer == "tracker":
            self.tracker_acks[ns] = (bool(m.is_keyframe), int(m.kf_id))
        elif m.is_keyframe:
            a = self.acks.setdefault(m.consumer, {"kf": -1})
            a["kf"] = max(a["kf"], int(m.kf_id))

    def _on_event(self, m) -> None:
        d = graph_event(m)
        if d is not None and d.get("event") == "ready":
            self.ready_nodes.add(d.get("node"))
        if d is not None and d.get("event") == "resumed" and d.get("node") == "tracker" and \
                self.args.mode == "lockstep":
            inc = str(d.get("incarnation"))
            if self.progress is None or inc not in self.progress.handled:
                st = d.get("stamp")
                ns = -1 if not isinstance(st, (int, float)) else int(round(st * 1e9))
                self.rewind = ns if self.rewind is None else min(self.rewind, ns)
                if self.progress is not None:
                    self.progress.handled.append(inc)
                self.log.info(f"the tracker resumed from its checkpoint: playing again from "
                              f"the first frame after {st}")

    def spin_until(self, cond, timeout: float, what: str) -> bool:
        import rclpy
        t0 = time.monotonic()
        last_note = t0
        while not cond():
            if not rclpy.ok():
                raise KeyboardInterrupt
            rclpy.spin_once(self.node, timeout_sec=0.2)
            now = time.monotonic()
            if now - t0 > timeout:
                return False
            if now - last_note > 30:
                last_note = now
                self.log.info(f"still waiting for {what} ({now - t0:.0f} s)")
        return True

    # ---------------------------------------------------------------- play
    def event(self, event: str, **kw) -> None:
        d = {"node": "player", "event": event, "t": time.time(), **kw}
        self.events_pub.publish(self.String(data=json.dumps(d)))

    def wait_for_graph(self) -> None:
        a = self.args
        want = [n for n in (a.wait_nodes.split(",") if a.wait_nodes else []) if n]
        need = [self.pubs[t] for t in self.topics if t in (self.roles["image"],
                                                           self.roles["camera_info"])]
        ok = self.spin_until(lambda: all(p.get_subscription_count() >= a.min_subscribers
                                         for p in need) and
                             all(n in self.ready_nodes for n in want),
                             a.start_timeout, "subscribers / ready nodes")
        if not ok:
            missing = [n for n in want if n not in self.ready_nodes]
            subs = {p.topic_name: p.get_subscription_count() for p in need}
            raise PlayerError(f"graph not ready after {a.start_timeout:g} s: nodes not ready "
                              f"{missing or 'none'}, subscribers {subs}")
        # let the matched subscribers' reliable channels settle (first-message loss)
        self.spin_until(lambda: False, 0.3, "")

    def _loop_period_ns(self) -> int:
        """Time shift between two passes of ``--loop``: the image stream's span + one frame."""
        ts = [t for _topic, t, _raw in self.reader.raw_messages([self.roles["camera_info"]])] \
            if self.roles["camera_info"] in self.reader.types else []
        if len(ts) < 2:
            ts = [t for t, _g in frames(self.reader, [self.roles["image"]], self.roles["image"])]
        if len(ts) < 2:
            return 10**9
        return int(ts[-1] - ts[0] + (ts[-1] - ts[0]) // (len(ts) - 1))

    def _frames_after(self, after_ns: Optional[int]):
        """(position, log time, group, image stamp ns) of the frames whose image stamp is
        newer than ``after_ns`` (None: all), in bag order; ``--loop N``: N passes, each one
        shifted in time (log time and header stamps) after the previous."""
        pos = 0
        period = self._loop_period_ns() if self.args.loop > 1 else 0
        for rep in range(max(1, self.args.loop)):
            shift = rep * period
            for t_ns, group in frames(self.reader, self.topics, self.roles["image"]):
                if shift:
                    t_ns, group = t_ns + shift, [(tp, shift_stamp(raw, shift)) for tp, raw in group]
                img = next(raw for topic, raw in group if topic == self.roles["image"])
                stamp = cdr_stamp_ns(img)
                if after_ns is None or stamp is None or stamp > after_ns + 1000:
                    yield pos, t_ns, group, stamp
                pos += 1

    def _publish(self, t_ns: int, group) -> None:
        from builtin_interfaces.msg import Time
        from rosgraph_msgs.msg import Clock
        if self.clock_pub is not None:
            self.clock_pub.publish(Clock(clock=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9)))
        img_raw = None
        for topic, raw in group:              # the image last: camera_info first
            if topic == self.roles["image"]:
                img_raw = raw
                continue
            self.pubs[topic].publish(raw)
        self.pubs[self.roles["image"]].publish(img_raw)

    def _wait_consumed(self, n: int, stamp, wait_kf: List[str], resend=None) -> int:
        """Lockstep: the tracker's ack of the frame (and the consumers' acks of the keyframe it
        made); a resumed tracker (``self.rewind``) ends the wait. Returns acks missing.
        ``resend`` (the frame's log time and messages): the first frame after a restart of
        the player or of the tracker, sent again when no ack came within ``--resend-after``
        seconds: a message published before the other side's connection has settled can be
        lost, and the frame would otherwise wait out ``--ack-timeout`` and never be tracked
        (a frame the tracker did get is acknowledged as a replay, not tracked twice)."""
        a, lost = self.args, 0
        acked = lambda: stamp in self.tracker_acks or self.rewind is not None  # noqa: E731
        what = f"the tracker's ack of frame {n - 1}"
        if resend is not None and 0 < a.resend_after < a.ack_timeout and \
                not self.spin_until(acked, a.resend_after, what):
            self.log.warning(f"no ack of frame {n - 1} within {a.resend_after:g} s of a restart: "
                             "sending it again")
            self._publish(*resend)
        ok = self.spin_until(acked, a.ack_timeout, what)
        if not ok:
            self.log.error(f"no ack of frame {n - 1} from the tracker within "
                           f"{a.ack_timeout:g} s; going on")
            return 1
        if self.rewind is not None:
            return 0
        is_kf, kf = self.tracker_acks.pop(stamp)
        if is_kf:
            for c in wait_kf:
                if not self.spin_until(
                        lambda c=c: self.acks.get(c, {"kf": -1})["kf"] >= kf or
                        self.rewind is not None, a.ack_timeout, f"{c}'s ack of keyframe {kf}"):
                    lost += 1
                    self.log.error(f"no ack of keyframe {kf} from {c} within "
                                   f"{a.ack_timeout:g} s; going on")
        return lost

    def play(self) -> int:
        import rclpy
        a = self.args
        self.wait_for_graph()
        total = self.reader.counts.get(self.roles["image"], 0) * max(1, a.loop)
        if a.max_frames:
            total = min(total, a.max_frames)
        start = self.progress.stamp_ns if self.progress is not None else None
        if self.rewind is not None:            # the tracker resumed before the player did
            start = self.rewind if start is None else min(start, self.rewind)
            self.rewind = None
        self.log.info(f"playing {total} frames ({a.mode}"
                      f"{'' if a.mode == 'lockstep' else f', rate {a.rate:g}'}) on "
                      f"{', '.join(self.remap.get(t, t) for t in self.topics)}"
                      + ("" if start is None else f", resuming after stamp {start * 1e-9:.6f}"))
        wait_kf = [c for c in (a.wait_acks.split(",") if a.wait_acks else []) if c]
        t_wall0 = t_bag0 = None
        n = 0
        t_start = time.monotonic()
        last_report = t_start
        lost_acks = 0
        self.event("start", frames=total, mode=a.mode)
        it = self._frames_after(start)
        restarted = start is not None          # resumed: its first frame may be resent
        while True:
            item = next(it, None)
            if item is None:
                break
            pos, t_ns, group, stamp = item
            if a.max_frames and pos >= a.max_frames:
                break
            if a.mode == "realtime":
                if t_wall0 is None:
                    t_wall0, t_bag0 = time.monotonic(), t_ns
                due = t_wall0 + (t_ns - t_bag0) * 1e-9 / a.rate
                while time.monotonic() < due:
                    rclpy.spin_once(self.node, timeout_sec=min(0.02, max(0.0, due - time.monotonic())))
            self._publish(t_ns, group)
            n = pos + 1
            if a.mode == "lockstep":
                lost_acks += self._wait_consumed(n, stamp, wait_kf,
                                                 (t_ns, group) if restarted else None)
                restarted = False
                if self.rewind is not None:     # a restarted tracker: from its checkpoint on
                    it, self.rewind = self._frames_after(self.rewind), None
                    self.tracker_acks.clear()
                    restarted = True
                    continue
            else:
                rclpy.spin_once(self.node, timeout_sec=0)
            if self.progress is not None and stamp is not None:
                self.progress.save(stamp, n)
            now = time.monotonic()
            if now - last_report >= a.report_every:
                last_report = now
                self.log.info(f"frame {n}/{total}  {n / (now - t_start):.2f} frames/s")
        wall = time.monotonic() - t_start
        self.log.info(f"end of stream: {n} frames in {wall:.1f} s ({n / max(wall, 1e-9):.2f} "
                      f"frames/s){f', {lost_acks} acks missing' if lost_acks else ''}")
        if not a.end_of_stream:
            return 0
        self.event("end_of_stream", frames=n, wall_s=wall, mode=a.mode, lost_acks=lost_acks)
        try:
            self.events_pub.wait_for_all_acked(timeout=rclpy.duration.Duration(seconds=5))
        except Exception:
            pass
        self.spin_until(lambda: False, 0.2, "")
        return 0


class PlayerProgress:
    """The player's position (stamp of the newest frame consumed) in ``DIR/progress.json``,
    replaced atomically after every frame: a restarted player continues after it."""

    def __init__(self, directory):
        from pathlib import Path
        self.path = Path(directory) / "progress.json"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        d = {}
        if self.path.is_file():
            try:
                d = json.loads(self.path.read_text())
            except ValueError:
                d = {}
        self.stamp_ns: Optional[int] = d.get("stamp_ns")
        self.frames = int(d.get("frames", 0))
        self.handled: List[str] = list(d.get("handled", []))   # tracker resumes followed

    def save(self, stamp_ns: int, frames: int) -> None:
        import os
        self.stamp_ns, self.frames = int(stamp_ns), int(frames)
        tmp = self.path.with_name(f".progress.{os.getpid()}.tmp")
        tmp.write_text(json.dumps({"stamp_ns": self.stamp_ns, "frames": self.frames,
                                   "handled": self.handled}))
        os.replace(tmp, self.path)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="splat-slam-bag-player", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bag", help="rosbag2 folder (MCAP storage) or a .mcap file")
    ap.add_argument("--mode", choices=["lockstep", "realtime"], default="lockstep")
    ap.add_argument("--rate", type=float, default=1.0, help="realtime mode: speed factor")
    ap.add_argument("--topics", choices=["camera", "all"], default="camera",
                    help="camera: image + camera_info (default); all: also depth / ground truth")
    ap.add_argument("--image-topic", help="image topic in the bag (default from the bag info)")
    ap.add_argument("--camera-info-topic", help="camera_info topic in the bag")
    ap.add_argument("--depth-topic", help=argparse.SUPPRESS)
    ap.add_argument("--gt-pose-topic", help=argparse.SUPPRESS)
    ap.add_argument("--out-image", help="publish the image on this topic instead")
    ap.add_argument("--out-camera-info", help="publish camera_info on this topic instead")
    ap.add_argument("--wait-nodes", default="",
                    help="comma list of graph nodes that must announce 'ready' first")
    ap.add_argument("--wait-acks", default="loop_closure,mapper",
                    help="lockstep: consumers whose keyframe acks are awaited after a keyframe")
    ap.add_argument("--min-subscribers", type=int, default=1)
    ap.add_argument("--start-timeout", type=float, default=120.0)
    ap.add_argument("--ack-timeout", type=float, default=300.0)
    ap.add_argument("--resend-after", type=float, default=15.0,
                    help="lockstep: the first frame after a restart of the player or the "
                         "tracker is sent again when not acknowledged within this many "
                         "seconds (0 = never)")
    ap.add_argument("--max-frames", type=int, default=0)
    ap.add_argument("--no-clock", dest="clock", action="store_false", help="do not publish /clock")
    ap.add_argument("--no-end-of-stream", dest="end_of_stream", action="store_false",
                    help="do not announce the end (act like a live camera that just stops)")
    ap.add_argument("--report-every", type=float, default=10.0, help="progress line period (s)")
    ap.add_argument("--name", default="bag_player", help="node name")
    ap.add_argument("--loop", type=int, default=1, metavar="N",
                    help="play the bag N times, each pass shifted in time after the previous "
                         "(long runs from a short bag: soak tests)")
    ap.add_argument("--state", metavar="DIR", help="keep the position in DIR/progress.json and "
                    "resume after it when started again (the launcher passes OUT/state/player)")
    return ap


def main(argv: Optional[List[str]] = None) -> int:
    init_process()
    from rclpy.utilities import remove_ros_args
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(remove_ros_args(["x"] + argv)[1:])
    if usage_error((args.rate <= 0, "--rate must be positive"),
                   (args.loop < 1, "--loop must be at least 1")):
        return 2
    try:
        reader = BagReader(args.bag)
    except PlayerError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return run_rclpy_tool(lambda: Player(args, reader).play(), (PlayerError,), ["x"] + argv)


if __name__ == "__main__":
    sys.exit(main())
