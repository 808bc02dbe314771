"""splat-slam-camera: a camera driver node — a V4L2 device, a video file or an image folder
published as ``sensor_msgs/Image`` (rgb8) + ``sensor_msgs/CameraInfo``, or with ``--jpeg Q`` as
``sensor_msgs/CompressedImage`` on ``IMAGE_TOPIC/compressed`` (image_transport's compressed
transport: a tenth of the bandwidth or less, for a camera on another host).

    splat-slam-camera SOURCE [--camera-info CAM.yaml] [--rate HZ] [--loop] [--max-frames N]
                      [--jpeg Q] [--image-topic /camera/image_raw]
                      [--camera-info-topic /camera/camera_info]

SOURCE: a device index (``0``) or path (``/dev/video0``), a video file (anything OpenCV's
FFmpeg back end reads) or a folder of images (png/jpg/jpeg/bmp/tif, sorted by name).
Intrinsics come from ``--camera-info``: a ROS camera_info YAML (``camera_matrix: data:``,
what camera_calibration writes), an OpenCV FileStorage YAML (``%YAML:1.0``, ``!!opencv-matrix``
``camera_matrix`` / ``distortion_coefficients``) or the project's intrinsics YAML. Distortion
coefficients go out in CameraInfo unchanged; undistortion is left to the tracker
(``camera.undistort``). Without a file the intrinsics are a guess from ``--fov`` (a warning
says so). QoS is SensorData (BEST_EFFORT, keep last 5), as every ROS camera driver. Files and
folders end after the last frame (``--loop`` restarts them); the node then announces
``end_of_stream`` on the graph-event channel when ``--end-of-stream`` is given (the launcher
finalises the graph at that point). Stamps are the node clock at capture.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Iterator, List, Optional

import cv2
import numpy as np

from splat_slam_ros.io.sensor_codec import compressed_topic, encode_jpeg, is_compressed_topic
from splat_slam_ros.types import Intrinsics, IntrinsicsError

from ..node_common import TOPICS, events_qos, graph_event, init_process
from ..tool_runner import is_shutdown_race

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class CameraError(Exception):
    """User-facing error: ``error: ...``, exit 2."""


# --------------------------------------------------------------------------- sources
@contextlib.contextmanager
def _quiet_stderr():
    """Silence C-level stderr (FFmpeg logs) while probing a file; our own error follows."""
    sys.stderr.flush()
    saved = os.dup(2)
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(null)


class FrameSource:
    """Frames (RGB uint8) from a device, a video file or an image folder; ``fps`` is the
    source's own rate when it has one (0 otherwise)."""

    def __init__(self, spec: str, loop: bool = False):
        self.spec = spec
        self.loop = loop
        self.fps = 0.0
        self.files: List[Path] = []
        self.cap = None
        self.kind = self._open(spec)

    def _open(self, spec: str) -> str:
        p = Path(spec)
        if spec.isdigit() or spec.startswith("/dev/video"):
            dev = int(spec) if spec.isdigit() else spec
            if not spec.isdigit() and not p.exists():
                raise CameraError(f"camera device {spec} does not exist")
            self.cap = cv2.VideoCapture(dev, cv2.CAP_V4L2)
            if not self.cap.isOpened():
                raise CameraError(f"cannot open camera device {spec} (V4L2); is it in use, or "
                                  "does this user lack access to /dev/video*?")
            self.fps = float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)
            return "device"
        if p.is_dir():
            self.files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_EXTS)
            if not self.files:
                raise CameraError(f"image folder {p} holds no images "
                                  f"({', '.join(IMAGE_EXTS)})")
            return "folder"
        if p.is_file():
            with _quiet_stderr():          # FFmpeg's own complaints about a bad file
                self.cap = cv2.VideoCapture(str(p))
            if not self.cap.isOpened():
                raise CameraError(f"cannot read video file {p} (not a video OpenCV can decode)")
            self.fps = float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)
            return "video"
        raise CameraError(f"camera source {spec!r} not found: give a device index (0), "
                          "/dev/videoN, a video file or an image folder")

    def frames(self) -> Iterator[np.ndarray]:
        while True:
            n = 0
            for img in (self._folder() if self.kind == "folder" else self._capture()):
                n += 1
                yield img
            if not self.loop or self.kind == "device" or n == 0:
                return
            if self.cap is not None:
                self.cap.set(cv2.CAP_PROP_POS_FRAMES, 0)

    def _folder(self) -> Iterator[np.ndarray]:
        for f in self.files:
            img = cv2.imread(str(f), cv2.IMREAD_COLOR)
            if img is None:
                raise CameraError(f"cannot decode image {f}")
            yield cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def _capture(self) -> Iterator[np.ndarray]:
        while True:
            ok, img = self.cap.read()
            if not ok or img is None:
                if self.kind == "device":
                    raise CameraError(f"camera device {self.spec} stopped delivering frames")
                return
            if img.ndim == 2:
                img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
            yield cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()


# --------------------------------------------------------------------------- intrinsics
def load_camera_info(path: str) -> Intrinsics:
    """ROS camera_info / project intrinsics YAML, or an OpenCV FileStorage YAML."""
    p = Path(path)
    if not p.is_file():
        raise CameraError(f"camera info file not found: {p}")
    try:
        head = p.read_bytes()[:65536].decode("utf-8")
    except UnicodeDecodeError:
        raise CameraError(f"camera info file {p} is not a YAML text file") from None
    if head.lstrip().startswith("%YAML:1.0") or "!!opencv-matrix" in head:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        try:
            K = fs.getNode("camera_matrix").mat()
            D = fs.getNode("distortion_coefficients").mat()
            w = fs.getNode("image_width").real()
            h = fs.getNode("image_height").real()
        finally:
            fs.release()
        if K is None or K.shape != (3, 3) or not (w > 0 and h > 0):
            raise CameraError(f"OpenCV camera file {p} needs camera_matrix (3x3), image_width "
                              "and image_height")
        dist = [] if D is None else [float(x) for x in D.ravel()]
        model = "equidistant" if len(dist) == 4 and "fisheye" in head.lower() else "plumb_bob"
        return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                          int(w), int(h), model, dist)
    try:
        return Intrinsics.from_yaml(p)
    except IntrinsicsError as e:
        raise CameraError(str(e)) from None


def guess_intrinsics(width: int, height: int, fov_deg: float) -> Intrinsics:
    """Pinhole intrinsics from a horizontal field of view (no calibration file)."""
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


# --------------------------------------------------------------------------- node
class CameraNode:
    def __init__(self, args, source: FrameSource, intr: Optional[Intrinsics]):
        import rclpy
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image
        from std_msgs.msg import String
        self.args = args
        self.source = source
        self.intr = intr
        self.node = rclpy.create_node(args.name)
        self.log = self.node.get_logger()
        # (with --jpeg, main() made args.image_topic the compressed transport's name)
        img_type = CompressedImage if args.jpeg else Image
        self.pub_img = self.node.create_publisher(img_type, args.image_topic,
                                                  qos_profile_sensor_data)
        self.CompressedImage = CompressedImage
        self.pub_info = self.node.create_publisher(CameraInfo, args.camera_info_topic,
                                                   qos_profile_sensor_data)
        self.pub_ev = self.node.create_publisher(String, TOPICS["events"], events_qos())
        self.String = String
        self.ready = set()
        self.node.create_subscription(String, TOPICS["events"], self._on_event, events_qos())

    def _on_event(self, m) -> None:
        d = graph_event(m)
        if d is not None and d.get("event") == "ready":
            self.ready.add(d.get("node"))

    def event(self, event: str, **kw) -> None:
        d = {"node": "camera", "event": event, "t": time.time(), **kw}
        self.pub_ev.publish(self.String(data=json.dumps(d)))

    def _spin(self, seconds: float) -> None:
        import rclpy
        t_end = time.monotonic() + seconds
        while True:
            if not rclpy.ok():
                raise KeyboardInterrupt
            left = t_end - time.monotonic()
            if left <= 0:
                return
            rclpy.spin_once(self.node, timeout_sec=min(left, 0.05))

    def wait_for_graph(self) -> None:
        want = [n for n in self.args.wait_nodes.split(",") if n]
        t0 = time.monotonic()
        while not (all(n in self.ready for n in want) and
                   self.pub_img.get_subscription_count() >= self.args.min_subscribers):
            if time.monotonic() - t0 > self.args.start_timeout:
                raise CameraError(f"graph not ready after {self.args.start_timeout:g} s "
                                  f"(nodes not ready: "
                                  f"{[n for n in want if n not in self.ready] or 'none'}, "
                                  f"subscribers {self.pub_img.get_subscription_count()})")
            self._spin(0.1)
        if want or self.args.min_subscribers:
            self._spin(0.3)                # let fresh matches settle

    def run(self) -> int:
        from tqdm import tqdm

        from ..convert import image_to_msg, intrinsics_to_camera_info
        a = self.args
        self.wait_for_graph()
        rate = a.rate or self.source.fps or 30.0
        period = 1.0 / rate
        self.log.info(f"publishing {self.source.kind} {self.source.spec} on {a.image_topic} "
                      f"({f'JPEG quality {a.jpeg}' if a.jpeg else 'rgb8'}) + "
                      f"{a.camera_info_topic} at {rate:g} Hz (SensorData QoS)")
        n = 0
        t_next = time.monotonic()
        bar = tqdm(total=a.max_frames or (len(self.source.files) or None), unit="frame",
                   desc="camera", disable=not a.progress)
        for rgb in self.source.frames():
            if self.intr is None:
                self.intr = guess_intrinsics(rgb.shape[1], rgb.shape[0], a.fov)
                self.log.warning(f"no --camera-info: guessing intrinsics from a {a.fov:g} deg "
                                 f"field of view (fx = {self.intr.fx:.1f} px); calibrate the "
                                 "camera for real use")
            if (rgb.shape[1], rgb.shape[0]) != (self.intr.width, self.intr.height):
                raise CameraError(f"frame size {rgb.shape[1]}x{rgb.shape[0]} does not match the "
                                  f"camera info ({self.intr.width}x{self.intr.height})")
            self._spin(max(0.0, t_next - time.monotonic()))
            t_next = max(t_next + period, time.monotonic() - period)   # no burst after a stall
            stamp = self.node.get_clock().now().nanoseconds * 1e-9
            self.pub_info.publish(intrinsics_to_camera_info(self.intr, stamp, a.frame_id))
            self.pub_img.publish(self._jpeg_msg(rgb, stamp) if a.jpeg else
                                 image_to_msg(rgb, "rgb8", stamp, a.frame_id))
            n += 1
            bar.update(1)
            if a.max_frames and n >= a.max_frames:
                break
        bar.close()
        self.log.info(f"published {n} frames")
        if a.end_of_stream:
            self.event("end_of_stream", frames=n)
            self._spin(0.5)                 # deliver the event before the process exits
        return 0

    def _jpeg_msg(self, rgb: np.ndarray, stamp: float):
        """sensor_msgs/CompressedImage of ``rgb`` as image_transport's compressed transport
        writes it (JPEG at ``--jpeg``)."""
        from ..convert import to_stamp
        fmt, data = encode_jpeg(rgb, self.args.jpeg)
        m = self.CompressedImage(format=fmt, data=data.tobytes())
        m.header.stamp, m.header.frame_id = to_stamp(stamp), self.args.frame_id
        return m


# --------------------------------------------------------------------------- launcher side
def camera_topic(jpeg: int, cfg, overrides: dict) -> None:
    """splat-slam-launch --camera: with ``--camera-jpeg`` the camera publishes on the compressed
    name of ``ros.image_topic``, which the tracker (and rerun logger) then subscribe to (set in
    ``cfg`` and ``overrides``); a ``/compressed`` image topic without it is an error."""
    topic = cfg.ros.image_topic
    if jpeg:
        if not 1 <= jpeg <= 100:
            raise CameraError(f"--camera-jpeg takes a quality from 1 to 100, got {jpeg}")
        cfg.ros.image_topic = overrides["ros.image_topic"] = compressed_topic(topic)
    elif is_compressed_topic(topic):
        raise CameraError(f"ros.image_topic {topic} is a compressed transport's name: add "
                          "--camera-jpeg Q for the camera to publish JPEG there")


def calibration_yaml(path: str) -> str:
    """A camera calibration file in any format :func:`load_camera_info` reads, as the
    project's intrinsics YAML in a new temporary file (the tracker's ``node.intrinsics_file``
    reads that format): its path."""
    import tempfile
    K = load_camera_info(path)
    fd, name = tempfile.mkstemp(prefix="splat_camera_", suffix=".yaml")
    os.close(fd)
    K.to_yaml(name)
    return name


def check_camera_args(source: str, camera_info: Optional[str]) -> None:
    """What splat-slam-launch checks before starting anything (devices are not opened)."""
    if camera_info:
        load_camera_info(camera_info)
    if not (source.isdigit() or Path(source).exists()):
        raise CameraError(f"camera source {source!r} not found: give a device index (0), "
                          "/dev/videoN, a video file or an image folder")


def launch_args(a, cfg, wait_nodes: List[str], end_of_stream: bool) -> List[str]:
    """Command line of the camera child of splat-slam-launch (topics from ``cfg.ros``)."""
    args = [sys.executable, "-m", "splat_slam_nodes.tools.camera_node", str(a.camera),
            "--image-topic", cfg.ros.image_topic, "--camera-info-topic",
            cfg.ros.camera_info_topic, "--frame-id", cfg.ros.optical_frame,
            "--wait-nodes", ",".join(wait_nodes), "--min-subscribers", "1", "--no-progress"]
    if a.camera_info:
        args += ["--camera-info", str(Path(a.camera_info).resolve())]
    if a.camera_rate:
        args += ["--rate", str(a.camera_rate)]
    if a.camera_jpeg:
        args += ["--jpeg", str(a.camera_jpeg)]
    if a.max_frames:
        args += ["--max-frames", str(a.max_frames)]
    if end_of_stream:
        args.append("--end-of-stream")
    return args


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="splat-slam-camera", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("source", help="device index / /dev/videoN, video file or image folder")
    ap.add_argument("--camera-info", metavar="YAML",
                    help="intrinsics: ROS camera_info YAML, OpenCV YAML or project intrinsics")
    ap.add_argument("--rate", type=float, default=0.0,
                    help="frames per second (default: the source's own rate, else 30)")
    ap.add_argument("--loop", action="store_true", help="restart files / folders at the end")
    ap.add_argument("--max-frames", type=int, default=0, help="stop after N frames")
    ap.add_argument("--fov", type=float, default=60.0,
                    help="horizontal field of view (deg) for guessed intrinsics without a file")
    ap.add_argument("--jpeg", type=int, default=0, metavar="Q",
                    help="publish JPEG sensor_msgs/CompressedImage at quality Q (1-100) on "
                         "IMAGE_TOPIC/compressed, image_transport's name (for a network link; "
                         "default: raw rgb8 Image)")
    ap.add_argument("--image-topic", default="/camera/image_raw")
    ap.add_argument("--camera-info-topic", default="/camera/camera_info")
    ap.add_argument("--frame-id", default="camera_optical", help="header frame_id")
    ap.add_argument("--wait-nodes", default="",
                    help="comma list of graph nodes that must announce 'ready' first")
    ap.add_argument("--min-subscribers", type=int, default=0,
                    help="wait for this many image subscribers before the first frame")
    ap.add_argument("--start-timeout", type=float, default=180.0)
    ap.add_argument("--end-of-stream", action="store_true",
                    help="announce end_of_stream on /splat/graph_events after the last frame")
    ap.add_argument("--no-progress", dest="progress", action="store_false")
    ap.add_argument("--name", default="camera", help="node name")
    return ap


def main(argv: Optional[List[str]] = None) -> int:
    init_process()
    import rclpy
    from rclpy.utilities import remove_ros_args
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(remove_ros_args(["x"] + argv)[1:])
    if args.rate < 0 or args.max_frames < 0 or not 1.0 <= args.fov < 180.0 or \
            not 0 <= args.jpeg <= 100:
        print("error: --rate and --max-frames must be >= 0, --fov in [1, 180), --jpeg in "
              "[1, 100] (0 = raw images)", file=sys.stderr)
        return 2
    if args.jpeg:
        args.image_topic = compressed_topic(args.image_topic)
    try:
        intr = load_camera_info(args.camera_info) if args.camera_info else None
        source = FrameSource(args.source, loop=args.loop)
    except CameraError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    rclpy.init(args=["x"] + argv)
    try:
        return CameraNode(args, source, intr).run()
    except CameraError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as e:
        if type(e).__name__ == "ExternalShutdownException" or is_shutdown_race(e):
            return 130
        raise
    finally:
        source.close()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
