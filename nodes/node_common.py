"""What every splat_slam_ros node shares: topic names, config <-> ROS parameters, robust raw
subscriptions, a worker thread, the graph-event channel and process start/stop.

A node is a thin adapter: callbacks turn messages into core types (nodes/convert.py) and hand
them to a core stage (splat_slam_ros.*) on the node's worker thread; results go back out as
messages. Extra conversions that convert.py does not have (PoseStamped, Path, PointCloud2)
live here (TF: nodes/tf_frames.py).

Graph events (``/splat/graph_events``, std_msgs/String with one JSON object, RELIABLE +
TRANSIENT_LOCAL) carry the control protocol: ``ready``, ``end_of_stream``, ``finalized``,
``saved`` (see nodes/tools/launch.py for the end-of-stream / finalisation sequence).
"""
from __future__ import annotations

import array
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

from splat_slam_ros.config import ConfigError
from splat_slam_ros.heap import bound_heap, release_free_memory
from splat_slam_ros.ros_env import RosEnvError, apply_ros_environment

from .node_options import COMMON_OPTIONS
from .tool_runner import is_shutdown_race
from .worker import NewestWaiting, Worker  # noqa: F401  (re-exported)

# --------------------------------------------------------------------------- names
NS = "/splat"
TOPICS = {
    "keyframes": f"{NS}/keyframes",                  # splat_slam_msgs/Keyframe
    "updates": f"{NS}/pose_graph_updates",           # splat_slam_msgs/PoseGraphUpdate
    "proxy_depth": f"{NS}/proxy_depth",              # splat_slam_msgs/ProxyDepth
    "ack": f"{NS}/frame_ack",                        # splat_slam_msgs/FrameAck
    "events": f"{NS}/graph_events",                  # std_msgs/String (JSON)
    "camera_pose": f"{NS}/camera_pose",              # geometry_msgs/PoseStamped
    "odometry": f"{NS}/odometry",                    # nav_msgs/Odometry (odom -> camera)
    "trajectory": f"{NS}/trajectory",                # nav_msgs/Path
    "keyframe_markers": f"{NS}/keyframe_markers",    # visualization_msgs/MarkerArray
    "rendered_rgb": f"{NS}/map/rendered_rgb",        # sensor_msgs/Image rgb8 (latest keyframe)
    "rendered_depth": f"{NS}/map/rendered_depth",    # sensor_msgs/Image 32FC1
    "rendered_info": f"{NS}/map/rendered_camera_info",  # sensor_msgs/CameraInfo of the renders
    "render_request": f"{NS}/map/render_request",    # geometry_msgs/PoseStamped
    "view_rgb": f"{NS}/map/view_rgb",                # sensor_msgs/Image rgb8 (requested pose)
    "view_depth": f"{NS}/map/view_depth",            # sensor_msgs/Image 32FC1
    "view_info": f"{NS}/map/view_camera_info",       # sensor_msgs/CameraInfo of the views
    "points": f"{NS}/map/points",                    # sensor_msgs/PointCloud2
    "status": f"{NS}/map/status",                    # splat_slam_msgs/MapperStatus
}
SERVICES = {
    "save_map": f"{NS}/map/save",                    # splat_slam_msgs/SaveMap
    "reset_map": f"{NS}/map/reset",                  # std_srvs/Trigger
    "render": f"{NS}/map/render",                    # splat_slam_msgs/RenderPose
    "graph_save_map": f"{NS}/save_map",              # splat_slam_msgs/SaveMap (launcher)
    "graph_load_map": f"{NS}/load_map",              # splat_slam_msgs/LoadMap (launcher)
}
NODE_NAMES = ("tracker", "depth", "loop_closure", "mapper")
TRIM_EVERY_S = 1.0        # free heap pages go back to the OS at most this often (after work)
IMAGE_TYPE_CHECK_S = 5.0  # a camera topic's type is checked this often until its first image



def init_process() -> None:
    """Project DDS environment, before rclpy is imported (every node's first call); the
    allocator settings of a long-running process (:func:`splat_slam_ros.heap.bound_heap`)."""
    bound_heap()
    try:
        apply_ros_environment()
    except RosEnvError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)


def graph_event(msg) -> Optional[dict]:
    """The JSON object of a /splat/graph_events message, or None when it is not one."""
    try:
        d = json.loads(msg.data)
    except ValueError:
        return None
    return d if isinstance(d, dict) else None


def takes_update(msg, sources) -> bool:
    """Whether a PoseGraphUpdate message comes from one of ``sources`` (checked before any
    decoding: every node also receives its own updates back on the shared topic). A message
    with an unknown reason is taken, so that the message checks report it."""
    from splat_slam_ros.types import UpdateEvent, update_source
    r = int(msg.reason)
    return r >= len(UpdateEvent.REASONS) or update_source(UpdateEvent.REASONS[r]) in sources


class Throttle:
    """At most one log line per key every ``period`` seconds (plus a count of the rest)."""

    def __init__(self, period: float = 5.0):
        self.period = period
        self.last: Dict[str, float] = {}
        self.skipped: Dict[str, int] = {}

    def __call__(self, key: str) -> Optional[str]:
        now = time.monotonic()
        if now - self.last.get(key, -1e9) >= self.period:
            self.last[key] = now
            n = self.skipped.pop(key, 0)
            return f" ({n} similar suppressed)" if n else ""
        self.skipped[key] = self.skipped.get(key, 0) + 1
        return None


# --------------------------------------------------------------------------- node base
def _param_value(v):
    if isinstance(v, tuple):
        return list(v)
    return v


class SplatNode:
    """Mixin-style helper wrapped around an rclpy Node (composition keeps rclpy imports lazy).

    Declares ``config_file`` + every SlamConfig key (dotted names, dynamic typing so that
    ``-p tracking.keyframe_thresh:=3`` works) + node options; builds ``self.cfg``.
    """

    def __init__(self, name: str, options: Dict[str, Any]):
        import rclpy
        from rclpy.node import Node
        from rcl_interfaces.msg import ParameterDescriptor
        from std_msgs.msg import String

        from splat_slam_ros.config import ConfigError, load_config

        self.name = name
        self.started = time.time()          # graph requests older than this are not ours
        self.node: Node = rclpy.create_node(name)
        self.log = self.node.get_logger()
        self.throttle = Throttle()
        dyn = ParameterDescriptor(dynamic_typing=True)
        cfg_file = self.node.declare_parameter("config_file", "", dyn).value or None
        try:
            cfg = load_config(cfg_file)
        except ConfigError as e:
            self.log.fatal(str(e))
            raise SystemExit(2)
        for key, default in cfg.flat().items():
            val = self.node.declare_parameter(key, _param_value(default), dyn).value
            if val != _param_value(default):
                try:
                    cfg.set(key, val)
                except ConfigError as e:
                    self.log.fatal(f"parameter {key}: {e}")
                    raise SystemExit(2)
        sections = {k.split(".")[0] for k in cfg.flat()}
        for key in getattr(self.node, "_parameter_overrides", {}):   # -p of an unknown key
            if key.split(".")[0] in sections and not self.node.has_parameter(key):
                self.log.fatal(f"parameter {key}: unknown config key (see config/*.yaml)")
                raise SystemExit(2)
        self.cfg = cfg
        self.opts: Dict[str, Any] = {}
        for key, default in {**COMMON_OPTIONS, **options}.items():
            self.opts[key] = self.node.declare_parameter(f"node.{key}", default, dyn).value
        self.frame_id = cfg.ros.map_frame
        self._events_pub = self.node.create_publisher(String, TOPICS["events"], events_qos())
        self._event_handlers: List[Callable[[dict], None]] = []
        self._events_sub = None
        self._trimmed = 0.0
        self.worker = Worker(self)
        self.pubs: Dict[str, Any] = {}
        # protocol messages queued on the worker, per channel (route)
        self.waiting: Dict[str, int] = {"updates": 0, "keyframes": 0, "proxy_depth": 0}
        self._waiting_lock = threading.Lock()
        self.depth_waiting = NewestWaiting()       # route(newest_depth=True): by kf_id

    # ------------------------------------------------------------ helpers
    @property
    def output_dir(self) -> Optional[Path]:
        d = self.opts.get("output_dir") or ""
        return Path(d) if d else None

    @property
    def state_dir(self) -> Optional[Path]:
        d = self.opts.get("state_dir") or ""
        return Path(d) if d else None

    def store(self):
        """The node's crash-safe KeyframeStore (``node.state_dir``), or None."""
        from splat_slam_ros.io.keyframe_store import KeyframeStore
        return KeyframeStore(self.state_dir) if self.state_dir is not None else None

    def now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def warn_throttled(self, key: str, text: str, error: bool = True) -> None:
        suffix = self.throttle(key)
        if suffix is None:
            return
        if error:
            self.log.error(text + suffix)
        else:
            self.log.warning(text + suffix)

    def subscribe(self, msg_type, topic: str, qos_profile, callback: Callable, what: str):
        """Raw subscription: deserialise here so that garbage bytes are a logged error, not a
        crash of the executor. ``callback(msg, raw)``; exceptions are logged, never raised."""
        from rclpy.serialization import deserialize_message

        def cb(raw: bytes):
            try:
                msg = deserialize_message(raw, msg_type)
            except Exception as e:            # Fast CDR raises RMWError on garbage
                self.worker.count_drop()
                self.warn_throttled(f"deser:{topic}", f"dropping a {what} message on {topic} "
                                    f"that cannot be deserialised ({len(raw)} bytes): "
                                    f"{str(e).splitlines()[0][:120]}")
                return
            try:
                callback(msg, raw)
            except Exception as e:
                self.worker.count_drop()
                self.warn_throttled(f"cb:{topic}", f"error handling a {what} message on {topic}: "
                                    f"{type(e).__name__}: {e}")
        return self.node.create_subscription(msg_type, topic, cb, qos_profile, raw=True)

    def subscribe_image(self, topic: str, qos_profile, callback: Callable,
                        received: Callable[[], bool]) -> None:
        """A camera image subscription that follows the camera: CompressedImage on a topic
        ending in ``/compressed`` (image_transport's name), Image elsewhere; until
        ``received()``, every ``IMAGE_TYPE_CHECK_S`` the topic's type in the graph. Published
        as the other image type only (which would never connect), the subscription is made
        again with that type, and said; a topic with several types is an error in the log."""
        from sensor_msgs.msg import CompressedImage, Image

        from splat_slam_ros.io.sensor_codec import is_compressed_topic
        kinds = {"sensor_msgs/msg/Image": Image, "sensor_msgs/msg/CompressedImage": CompressedImage}
        first = CompressedImage if is_compressed_topic(topic) else Image
        state = {"sub": self.subscribe(first, topic, qos_profile, callback, first.__name__)}

        def check():
            if received():
                timer.cancel()
                return
            types = sorted({i.topic_type for i in self.node.get_publishers_info_by_topic(topic)})
            mine = f"sensor_msgs/msg/{state['sub'].msg_type.__name__}"
            if not [t for t in types if t != mine]:
                return
            if len(types) == 1 and types[0] in kinds:
                self.node.destroy_subscription(state["sub"])
                new = kinds[types[0]]
                state["sub"] = self.subscribe(new, topic, qos_profile, callback, new.__name__)
                self.log.warning(f"{topic} is published as {types[0]}, not {mine}: subscribed "
                                 "as that")
                return
            self.warn_throttled("image-type", f"{topic} is published as {', '.join(types)}; "
                                f"this node takes {mine} there: some cameras never connect")
        timer = self.node.create_timer(IMAGE_TYPE_CHECK_S, check)

    # ------------------------------------------------------------ stage roles
    def publishers(self, *kinds: str) -> None:
        """Publishers for the protocol channels an Outbox may fill (see :meth:`emit`)."""
        from splat_slam_msgs.msg import FrameAck, Keyframe, PoseGraphUpdate, ProxyDepth

        from . import qos as Q
        spec = {"updates": (PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos()),
                "keyframes": (Keyframe, TOPICS["keyframes"], Q.keyframe_qos()),
                "proxy_depth": (ProxyDepth, TOPICS["proxy_depth"], Q.proxy_depth_qos()),
                "ack": (FrameAck, TOPICS["ack"], Q.ack_qos())}
        for k in kinds:
            self.pubs[k] = self.node.create_publisher(*spec[k])

    def emit(self, out) -> None:
        """Publish a role's Outbox: updates, keyframes, proxy depths, acks, ``finalized``."""
        from .convert import (frame_ack_msg, keyframe_to_msg, proxy_depth_to_msg, to_stamp,
                              update_to_msg)
        for ev in out.updates:
            self.pubs["updates"].publish(update_to_msg(ev, self.now(), self.frame_id))
        for kf in out.keyframes:
            self.pubs["keyframes"].publish(keyframe_to_msg(kf, self.frame_id))
        for pd in out.proxy_depths:
            self.pubs["proxy_depth"].publish(proxy_depth_to_msg(pd, self.frame_id))
        for frame_index, kf_id, stamp in out.acks:
            m = frame_ack_msg(frame_index, self.name, 0.0, kf_id)
            m.header.stamp = to_stamp(stamp)
            self.pubs["ack"].publish(m)
        if out.final is not None:
            self.publish_event("finalized", **out.final)

    def route(self, role, keyframes: bool = False, updates: bool = False,
              proxy_depth: bool = False, after: Optional[Callable] = None,
              on_update: Optional[Callable] = None,
              on_keyframe: Optional[Callable] = None, newest_depth: bool = False) -> None:
        """Subscribe the protocol channels to ``role``'s handlers (on the worker thread) and
        the ``finalized`` graph events to ``role.on_final``; each Outbox is emitted, then
        ``after(out)`` runs (node-specific outputs). ``on_update`` / ``on_keyframe`` replace
        ``role.on_update`` (``self.waiting["updates"]``: updates queued behind this one) /
        ``role.on_keyframe``. ``newest_depth``: a ProxyDepth that arrives while an older
        revision of its keyframe still waits replaces that one in its place in the queue
        (``self.depth_waiting``, :class:`NewestWaiting`), so a consumer behind the stream
        applies each keyframe's newest depth once, not every revision in turn."""
        from splat_slam_msgs.msg import Keyframe, PoseGraphUpdate, ProxyDepth

        from splat_slam_ros.config import ConfigError

        from . import qos as Q
        from .convert import msg_to_keyframe, msg_to_proxy_depth, msg_to_update

        def handle(fn, convert, msg):
            try:
                out = fn(convert(msg))
            except ConfigError as e:      # e.g. a bad tracking.flow_model: the stage cannot run
                self.log.fatal(f"cannot run the {self.name} stage: {e}")
                raise SystemExit(2)
            self.emit(out)
            if after is not None:
                after(out)
            now = time.monotonic()
            if now - self._trimmed > TRIM_EVERY_S:     # keep RSS at what is in use (soak)
                release_free_memory()
                self._trimmed = now

        def handle_queued(topic, fn, convert, msg):
            with self._waiting_lock:
                self.waiting[topic] -= 1
            handle(fn, convert, msg)

        def sub(kind, topic, qos, fn, convert, take=lambda m: True):
            def enqueue(m, raw):
                if take(m):
                    with self._waiting_lock:
                        self.waiting[topic] += 1
                    self.worker.submit(handle_queued, topic, fn, convert, m)
            self.subscribe(kind, TOPICS[topic], qos, enqueue, kind.__name__)
        from .msg_checks import check_keyframe, check_proxy_depth, check_update  # fuzz-proof
        if updates:        # first: an update and a keyframe both waiting -> the update first
            sub(PoseGraphUpdate, "updates", Q.pose_graph_qos(), on_update or role.on_update,
                lambda m: msg_to_update(check_update(m)),
                lambda m: takes_update(m, role.update_sources))
        if keyframes:
            sub(Keyframe, "keyframes", Q.keyframe_qos(), on_keyframe or role.on_keyframe,
                lambda m: msg_to_keyframe(check_keyframe(m)))
        depth_in = lambda m: msg_to_proxy_depth(check_proxy_depth(m))  # noqa: E731
        if proxy_depth and newest_depth:
            def enqueue_newest(m, raw):
                with self._waiting_lock:
                    if not self.depth_waiting.offer(int(m.kf_id), m, int(m.revision)):
                        return                  # queued already: the newer one in its place
                    self.waiting["proxy_depth"] += 1
                self.worker.submit(handle_newest, int(m.kf_id))

            def handle_newest(k):
                with self._waiting_lock:
                    m = self.depth_waiting.take(k)
                    self.waiting["proxy_depth"] -= 1
                handle(role.on_proxy_depth, depth_in, m)
            self.subscribe(ProxyDepth, TOPICS["proxy_depth"], Q.proxy_depth_qos(),
                           enqueue_newest, "ProxyDepth")
        elif proxy_depth:
            sub(ProxyDepth, "proxy_depth", Q.proxy_depth_qos(), role.on_proxy_depth, depth_in)
        self.on_events(lambda d: d.get("event") == "finalized" and self.worker.submit_final(
            handle, lambda info: role.on_final(str(info.get("node")), info), lambda d: d, d))

    # ------------------------------------------------------------ graph events
    def publish_event(self, event: str, **fields) -> None:
        from std_msgs.msg import String
        d = {"node": self.name, "event": event, "t": time.time(),
             "dropped_inputs": self.worker.dropped, **fields}     # malformed messages so far
        try:
            self._events_pub.publish(String(data=json.dumps(d, default=str)))
        except Exception as e:                 # context shut down meanwhile
            self.log.debug(f"event {event} not published: {e}")

    def on_events(self, handler: Callable[[dict], None]) -> None:
        from std_msgs.msg import String
        self._event_handlers.append(handler)
        if self._events_sub is None:
            prof = events_qos()

            def cb(msg, raw):
                d = graph_event(msg)
                if d is None or d.get("node") == self.name:
                    return
                for h in self._event_handlers:
                    h(d)
            self._events_sub = self.subscribe(String, TOPICS["events"], prof, cb, "graph event")

    def spin(self) -> int:
        """Spin until shutdown (SIGINT / SIGTERM); returns the exit status."""
        import rclpy
        from rclpy.executors import ExternalShutdownException
        self.worker.start()
        rc = 0
        try:
            rclpy.spin(self.node)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except RuntimeError as e:
            if not is_shutdown_race(e):
                raise
        finally:
            self.worker.stop()
            rc = self.worker.fatal_rc
            try:
                self.node.destroy_node()
            except Exception:
                pass
            rclpy.try_shutdown()
        return rc


NODE_HELP = """
Run it through splat-slam-launch (which starts the whole graph), or alone with ROS arguments:
  {prog} --ros-args -r __node:=NAME -p config_file:=CONFIG.yaml -p KEY:=VALUE ...
KEY is any configuration key (e.g. tracking.keyframe_thresh, mapping.iters_per_keyframe; see
config/*.yaml) or a node option (node.*, listed above). -h/--help prints this and exits
without starting ROS."""


def node_help(make, argv: Optional[List[str]] = None) -> Optional[str]:
    """The help text of a node executable when its arguments (before ``--ros-args``) ask for
    it, else None: the module's description (topics, services, options) and how to run it."""
    args = list(sys.argv[1:] if argv is None else argv)
    if "--ros-args" in args:
        args = args[:args.index("--ros-args")]
    if not ({"-h", "--help"} & set(args)):
        return None
    doc = (sys.modules[make.__module__].__doc__ or "").strip()
    prog = Path(sys.argv[0]).name if argv is None else make.__module__
    return doc + "\n" + NODE_HELP.format(prog=prog)


def run_node(make: Callable[[], SplatNode], argv: Optional[List[str]] = None) -> int:
    """Entry point body of every node executable: env, rclpy.init, build, spin (``--help``:
    the node's description, without starting ROS)."""
    text = node_help(make, argv)
    if text is not None:
        print(text)
        return 0
    init_process()
    import rclpy
    rclpy.init(args=sys.argv if argv is None else argv)
    try:
        n = make()
    except SystemExit as e:
        rclpy.try_shutdown()
        return int(e.code or 0)
    except ConfigError as e:                 # checked at start: one line, no traceback
        print(f"error: configuration error: {e}", file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return 2
    try:
        import torch
        torch.set_num_threads(int(os.environ.get("SPLAT_SLAM_THREADS", "0")) or
                              max(1, os.cpu_count() or 1))
    except ImportError:
        pass
    return n.spin()


# --------------------------------------------------------------------------- conversions
def pose_stamped(T, stamp: float, frame_id: str):
    from geometry_msgs.msg import PoseStamped

    from .convert import pose_to_msg, to_stamp
    m = PoseStamped()
    m.header.stamp = to_stamp(stamp)
    m.header.frame_id = frame_id
    m.pose = pose_to_msg(T)
    return m


def path_msg(stamps, poses, frame_id: str, stamp: float):
    from nav_msgs.msg import Path as PathMsg

    from .convert import poses_to_msgs, to_stamp
    m = PathMsg()
    m.header.stamp = to_stamp(stamp)
    m.header.frame_id = frame_id
    out = []
    if len(poses):
        from geometry_msgs.msg import PoseStamped
        for t, p in zip(stamps, poses_to_msgs(poses)):
            ps = PoseStamped()
            ps.header.stamp = to_stamp(t)
            ps.header.frame_id = frame_id
            ps.pose = p
            out.append(ps)
    m.poses = out
    return m


def pointcloud2(points, colors_u8, stamp: float, frame_id: str):
    """N x 3 float points + N x 3 uint8 RGB -> sensor_msgs/PointCloud2 (x y z rgb, PCL's
    packed-float rgb convention)."""
    import numpy as np
    from sensor_msgs.msg import PointCloud2, PointField

    from .convert import to_stamp
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    col = np.asarray(colors_u8, np.uint8).reshape(-1, 3)
    n = len(pts)
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["rgb"] = (col[:, 0].astype(np.uint32) << 16) | (col[:, 1].astype(np.uint32) << 8) | col[:, 2]
    m = PointCloud2()
    m.header.stamp = to_stamp(stamp)
    m.header.frame_id = frame_id
    m.height, m.width = 1, n
    m.fields = [PointField(name=nm, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                for i, nm in enumerate(("x", "y", "z", "rgb"))]
    m.is_bigendian = False
    m.point_step = 16
    m.row_step = 16 * n
    buf = array.array("B")
    buf.frombytes(rec.tobytes())
    m.data = buf
    m.is_dense = True
    return m


def pointcloud2_to_arrays(m):
    """Inverse of :func:`pointcloud2` (tests, viewers)."""
    import numpy as np
    rec = np.frombuffer(bytes(m.data), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                               ("rgb", "<u4")])
    pts = np.stack([rec["x"], rec["y"], rec["z"]], -1)
    rgb = np.stack([(rec["rgb"] >> 16) & 255, (rec["rgb"] >> 8) & 255, rec["rgb"] & 255], -1)
    return pts, rgb.astype(np.uint8)


def events_qos():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
