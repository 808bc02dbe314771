"""rosbag2 (MCAP storage, CDR) writing and reading with ``rosbags`` — no ROS install needed.

Bag layout written by :func:`write_bag` (one message of each per frame, all with
the frame's timestamp as header stamp *and* log time):

=====================  ============================  =========================================
topic                  type                          content
=====================  ============================  =========================================
/camera/camera_info    sensor_msgs/msg/CameraInfo    K, P, distortion model + coefficients
/camera/image_raw      sensor_msgs/msg/Image         original encoding: rgb8 (colour) / mono8
                                                     (``jpeg_quality``: CompressedImage JPEG on
                                                     /camera/image_raw/compressed instead)
/camera/depth          sensor_msgs/msg/Image         32FC1 metres, 0 = unknown (REP-118);
                                                     only when the dataset has depth (eval only)
/ground_truth/pose     geometry_msgs/msg/PoseStamped camera-to-world, frame_id "world";
                                                     only for frames with ground truth
=====================  ============================  =========================================

Image/camera_info/depth frame_id is ``camera`` (OpenCV axes). Dataset name, format,
source and notes are stored in the bag's ``custom_data`` (keys ``splat_slam.*``) and
in ``splat_slam_info.yaml`` beside ``metadata.yaml``.

:class:`BagDataset` reads such a bag back as :class:`~splat_slam_ros.types.Frame`
objects (``open_dataset(path, fmt="bag")``), with the rosbags reader or, for a bare
``.mcap`` file (or ``backend="mcap"``), with ``mcap`` + ``mcap_ros2`` — both through
:class:`~splat_slam_ros.io.bag_reader.BagFile`, the one bag reader.
"""
from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

import numpy as np
import yaml
from tqdm import tqdm

from splat_slam_ros.io.dataset_base import (ASSOC_TOL, Dataset, DatasetError, check_selection, copy_intrinsics,
                       select_frames, associate, ns_to_stamp, stamp_to_ns)
from splat_slam_ros.geometry import pose_from_tq, pose_to_tq
from splat_slam_ros.io import mcap_recover
from splat_slam_ros.io.bag_reader import INFO_FILE, BagFile, is_bag_dir, make_typestore
from splat_slam_ros.io.bag_reader import register_project_types  # noqa: F401 (public re-export)
from splat_slam_ros.io.sensor_codec import (ConversionError, camera_info_to_intrinsics,
                                           compressed_topic, decode_depth, decode_rgb,
                                           encode_image, encode_jpeg, is_compressed_topic)
from splat_slam_ros.types import Frame, Intrinsics

DEFAULT_TOPICS: Dict[str, Optional[str]] = {
    "image": "/camera/image_raw",
    "camera_info": "/camera/camera_info",
    "depth": "/camera/depth",
    "gt_pose": "/ground_truth/pose",
}
CAMERA_FRAME = "camera"
WORLD_FRAME = "world"

T_IMAGE = "sensor_msgs/msg/Image"
T_COMPRESSED = "sensor_msgs/msg/CompressedImage"
T_INFO = "sensor_msgs/msg/CameraInfo"
T_POSE = "geometry_msgs/msg/PoseStamped"
IMAGE_TYPES = (T_IMAGE, T_COMPRESSED)


def _listing(topics: Dict[str, Tuple[str, int]]) -> str:
    return ", ".join(sorted(topics)) or "none"


def camera_topics(path, avail: Dict[str, Tuple[str, int]], tp: Dict[str, Optional[str]],
                  given: Dict[str, Optional[str]], intrinsics_given: bool
                  ) -> Tuple[str, Optional[str]]:
    """(image topic, camera_info topic or None) of a bag. ``given``: the user's choice
    (``--image-topic`` / ``--camera-info-topic``); ``tp``: the bag info's or the defaults. A bag
    not written by ``splat-slam-convert`` has its own names: its one image topic
    (sensor_msgs/Image or CompressedImage; topics named "depth" aside) and that camera's
    camera_info (image_transport's sibling ``.../camera_info``, else the bag's only one). No
    camera_info is needed when intrinsics are given."""
    def check(role, topic, types):
        if topic not in avail:
            raise DatasetError(f"{path}: bag has no {role} topic {topic!r} "
                               f"(topics: {_listing(avail)})")
        if avail[topic][0] not in types:
            raise DatasetError(f"{path}: topic {topic} is a {avail[topic][0]}, not a "
                               f"{' or '.join(types)}")
        return topic

    if given.get("image"):
        image = check("image", given["image"], IMAGE_TYPES)
    elif tp.get("image") in avail:
        image = check("image", tp["image"], IMAGE_TYPES)
    else:
        cands = sorted(t for t, (ty, n) in avail.items()
                       if ty in IMAGE_TYPES and n > 0 and "depth" not in t.lower())
        if len(cands) != 1:
            raise DatasetError(
                f"{path}: " + (f"bag has {len(cands)} image topics ({', '.join(cands)}): choose "
                               "one with --image-topic TOPIC" if cands else
                               f"bag has no image topic (sensor_msgs/Image or CompressedImage; "
                               f"topics: {_listing(avail)})"))
        image = cands[0]
    if given.get("camera_info"):
        return image, check("camera_info", given["camera_info"], (T_INFO,))
    base = image.rstrip("/").rsplit("/", 1)[0] if is_compressed_topic(image) else image
    infos = sorted(t for t, (ty, n) in avail.items() if ty == T_INFO and n > 0)
    for t in (base.rsplit("/", 1)[0] + "/camera_info", tp.get("camera_info")):
        if t in infos:
            return image, t
    if len(infos) == 1:
        return image, infos[0]
    if intrinsics_given:
        return image, None
    raise DatasetError(f"{path}: no camera_info topic for {image} (camera_info topics: "
                       f"{', '.join(infos) or 'none'}): choose one with --camera-info-topic "
                       "TOPIC, or give the calibration with --intrinsics FILE")


# ------------------------------------------------------------ message builders
def _header(ts, ns: int, frame_id: str):
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame_id)


def _image(ts, img: np.ndarray, ns: int, frame_id: str, encoding: str):
    f = encode_image(img, encoding)
    return ts.types[T_IMAGE](header=_header(ts, ns, frame_id), height=f.height, width=f.width,
                             encoding=f.encoding, is_bigendian=0, step=f.step, data=f.data)


def image_msg(ts, img: np.ndarray, ns: int, frame_id: str = CAMERA_FRAME):
    """uint8 HxW (mono8) or HxWx3 (rgb8) -> sensor_msgs/Image."""
    img = np.ascontiguousarray(img)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise DatasetError(f"image_msg needs uint8 HxW or HxWx3, got {img.dtype} {img.shape}")
    return _image(ts, img, ns, frame_id, "mono8" if img.ndim == 2 else "rgb8")


def jpeg_msg(ts, img: np.ndarray, ns: int, quality: int, frame_id: str = CAMERA_FRAME):
    """uint8 HxW or HxWx3 RGB -> sensor_msgs/CompressedImage (JPEG, image_transport's format)."""
    fmt, data = encode_jpeg(np.asarray(img), quality)
    return ts.types[T_COMPRESSED](header=_header(ts, ns, frame_id), format=fmt, data=data)


def depth_msg(ts, depth: np.ndarray, ns: int, frame_id: str = CAMERA_FRAME):
    """float32 metres HxW -> sensor_msgs/Image 32FC1 (little endian)."""
    return _image(ts, np.asarray(depth, dtype=np.float32), ns, frame_id, "32FC1")


def camera_info_msg(ts, K: Intrinsics, ns: int, frame_id: str = CAMERA_FRAME):
    d = list(K.distortion)
    if K.distortion_model == "plumb_bob" and 0 < len(d) < 5:
        d = d + [0.0] * (5 - len(d))
    Roi = ts.types["sensor_msgs/msg/RegionOfInterest"]
    return ts.types[T_INFO](
        header=_header(ts, ns, frame_id), height=int(K.height), width=int(K.width),
        distortion_model=K.distortion_model, d=np.asarray(d, dtype=np.float64),
        k=np.array([K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1], dtype=np.float64),
        r=np.eye(3).reshape(-1),
        p=np.array([K.fx, 0, K.cx, 0, 0, K.fy, K.cy, 0, 0, 0, 1, 0], dtype=np.float64),
        binning_x=0, binning_y=0,
        roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def pose_msg(ts, T: np.ndarray, ns: int, frame_id: str = WORLD_FRAME):
    tq = pose_to_tq(np.asarray(T, dtype=np.float64)).numpy()
    P = ts.types
    pose = P["geometry_msgs/msg/Pose"](
        position=P["geometry_msgs/msg/Point"](x=float(tq[0]), y=float(tq[1]), z=float(tq[2])),
        orientation=P["geometry_msgs/msg/Quaternion"](x=float(tq[3]), y=float(tq[4]),
                                                       z=float(tq[5]), w=float(tq[6])))
    return P[T_POSE](header=_header(ts, ns, frame_id), pose=pose)


# -------------------------------------------- decoders (rosbags or mcap_ros2 objects)
def msg_stamp_ns(msg) -> int:
    return int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)


def pose_from_msg(msg) -> np.ndarray:
    p, q = msg.pose.position, msg.pose.orientation
    return pose_from_tq(np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w])).numpy()


# -------------------------------------------------------------------- writing
def _prepare_out(out: Path, overwrite: bool) -> None:
    if not out.exists():
        return
    if out.is_dir() and not any(out.iterdir()):
        out.rmdir()
        return
    if not overwrite:
        raise DatasetError(f"output {out} already exists (use --overwrite to replace it)")
    if not is_bag_dir(out):
        raise DatasetError(f"output {out} exists and is not a rosbag2 folder; not deleting it")
    shutil.rmtree(out)


def write_bag(dataset: Dataset, out_dir, progress: bool = True,
              topics: Optional[Dict[str, Optional[str]]] = None,
              overwrite: bool = False, compress: bool = False,
              jpeg_quality: Optional[int] = None) -> dict:
    """Write ``dataset`` as a rosbag2 folder (MCAP, CDR). Returns a summary dict
    (path, frames, topics {name: count}, duration_s, size_bytes).

    ``topics`` overrides DEFAULT_TOPICS per role (image, camera_info, depth, gt_pose); a
    role mapped to None is not written. ``compress``: zstd-compressed MCAP chunks (about
    2x smaller for raw images, slower to write; every MCAP reader decodes them).
    ``jpeg_quality``: the images as JPEG CompressedImage at that quality (lossy, about 15x
    smaller) on image_transport's ``/camera/image_raw/compressed``. A failure removes the
    partial bag.
    """
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    tp = dict(DEFAULT_TOPICS)
    if jpeg_quality is not None:
        if not 1 <= int(jpeg_quality) <= 100:
            raise DatasetError(f"JPEG quality {jpeg_quality} is outside 1..100")
        tp["image"] = compressed_topic(tp["image"])
    tp.update(topics or {})
    if not tp.get("image"):
        raise DatasetError("write_bag needs an image topic")
    out = Path(out_dir)
    _prepare_out(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    ts = make_typestore(project_types=False)
    info = dataset.info()
    counts: Dict[str, int] = {}
    first_ns = last_ns = None
    writer = Writer(out, version=8, storage_plugin=StoragePlugin.MCAP)
    if compress:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    for key in ("name", "format", "source"):
        writer.set_custom_data(f"splat_slam.{key}", str(info[key]))
    writer.set_custom_data("splat_slam.frames", str(info["frames"]))
    try:
        writer.open()
        conns = {}

        def conn(role, msgtype):
            if tp.get(role) and role not in conns:
                conns[role] = writer.add_connection(tp[role], msgtype, typestore=ts)
                counts[tp[role]] = 0
            return conns.get(role)

        conn("camera_info", T_INFO)
        conn("image", T_IMAGE if jpeg_quality is None else T_COMPRESSED)
        if dataset.has_gt_depth:
            conn("depth", T_IMAGE)
        if dataset.has_gt_pose:
            conn("gt_pose", T_POSE)

        def put(role, msg):
            c = conns.get(role)
            if c is not None:
                writer.write(c, ns, ts.serialize_cdr(msg, msg.__msgtype__))
                counts[tp[role]] += 1

        bar = tqdm(total=len(dataset), disable=not progress, unit="frame",
                   desc=f"bag {out.name}")
        n = 0
        for f in dataset.iter_frames(keep_mono=True):
            ns = stamp_to_ns(f.timestamp)
            if last_ns is not None and ns <= last_ns:
                raise DatasetError(f"timestamps must increase: frame {f.index} at {f.timestamp:.9f}"
                                   f" s is not after the previous frame")
            first_ns = ns if first_ns is None else first_ns
            last_ns = ns
            put("camera_info", camera_info_msg(ts, f.intrinsics, ns))
            put("image", image_msg(ts, f.image, ns) if jpeg_quality is None else
                jpeg_msg(ts, f.image, ns, jpeg_quality))
            if f.gt_depth is not None:
                put("depth", depth_msg(ts, f.gt_depth, ns))
            if f.gt_pose is not None:
                put("gt_pose", pose_msg(ts, f.gt_pose, ns))
            n += 1
            bar.update(1)
        bar.close()
        if n == 0:
            raise DatasetError(f"{dataset.source}: the dataset yielded no frames")
        writer.close()
        info.update(frames=n, topics={k: v for k, v in tp.items() if v and v in counts},
                    message_counts=counts, bag_format="rosbag2 mcap cdr (metadata version 8)")
        (out / INFO_FILE).write_text(yaml.safe_dump(info, sort_keys=False))
    except BaseException:
        try:
            writer.close()
        except Exception:
            pass
        shutil.rmtree(out, ignore_errors=True)
        raise
    size = sum(p.stat().st_size for p in out.iterdir() if p.is_file())
    return {"path": str(out), "frames": n, "topics": counts,
            "duration_s": (last_ns - first_ns) / 1e9, "size_bytes": size}


# -------------------------------------------------------------------- reading
class BagDataset(Dataset):
    """Frames from a rosbag2 folder (or bare .mcap file) with the layout :func:`write_bag` makes.

    Frames are the messages of the image topic; ``intrinsics`` come from the first
    camera_info; ``gt_pose`` from the PoseStamped with the image's stamp (nearest within
    0.02 s otherwise); ``gt_depth`` from the depth image with the same log time.
    ``backend``: "auto" (rosbags for folders, mcap for a bare .mcap file), "rosbags", "mcap".
    """
    format = "bag"

    def __init__(self, path, max_frames: Optional[int] = None, stride: int = 1,
                 keep_mono: bool = False, topics: Optional[Dict[str, Optional[str]]] = None,
                 backend: str = "auto", intrinsics: Optional[Intrinsics] = None):
        check_selection(stride, max_frames)
        p = Path(path)
        self._bag = bag = BagFile(p, backend)
        self.backend = bag.backend
        info, custom, bag_dir = bag.info, bag.custom, bag.bag_dir
        tp = dict(DEFAULT_TOPICS)
        tp.update(info.get("topics") or {})
        tp.update({k: v for k, v in (topics or {}).items() if k not in ("image", "camera_info")})
        self.info_file = info
        name = info.get("name") or custom.get("splat_slam.name") or \
            (bag_dir.name if bag_dir is not None else p.stem)
        self.source_format = info.get("format") or custom.get("splat_slam.format")
        avail = bag.topics()
        tp["image"], tp["camera_info"] = camera_topics(p, avail, tp, topics or {},
                                                       intrinsics is not None)
        self.topics = tp
        # First pass: small topics decoded, image topic only counted (log times).
        K = copy_intrinsics(intrinsics) if intrinsics is not None else None
        img_ns: List[int] = []
        gt: Dict[int, np.ndarray] = {}
        want = [tp["image"]] + ([tp["camera_info"]] if K is None else []) + \
            ([tp["gt_pose"]] if tp.get("gt_pose") in avail else [])
        for topic, t, dec in bag.messages(want):
            if topic == tp["image"]:
                img_ns.append(t)
            elif topic == tp["camera_info"]:
                if K is None:
                    try:
                        K = camera_info_to_intrinsics(dec())
                    except ConversionError as e:
                        raise DatasetError(f"{p}: {topic}: {e} (give the calibration with "
                                           "--intrinsics FILE)") from None
            else:
                m = dec()
                gt[msg_stamp_ns(m)] = pose_from_msg(m)
        if K is None:
            raise DatasetError(f"{p}: bag has no {tp['camera_info']} messages")
        if not img_ns:
            raise DatasetError(f"{p}: bag has no {tp['image']} messages")
        super().__init__(name, p, K, keep_mono,
                         notes=[f"converted: {n}" for n in info.get("notes") or []])
        self._sel = select_frames(len(img_ns), int(stride), max_frames)
        self._img_ns = img_ns
        self._gt_ns = np.array(sorted(gt), dtype=np.int64)
        self._gt = gt
        self._has_depth = tp.get("depth") in avail and avail[tp["depth"]][1] > 0
        self._unstamped = False
        if self._has_depth:
            self.depth_scale = 1.0

    def close(self) -> None:
        self._bag.close()

    def health(self) -> List["mcap_recover.McapHealth"]:
        """Intact / damaged state of each MCAP file of the bag (``--info``)."""
        return [mcap_recover.scan_mcap(f) for f in self._bag.mcap_files
                if f.suffix.lower() == ".mcap" and f.is_file()]

    def topic_counts(self) -> Dict[str, Tuple[str, int]]:
        """{topic: (message type, message count)} of the whole bag."""
        return self._bag.topics()

    # ---------------------------------------------------------------- helpers
    def _gt_for(self, ns: int) -> Optional[np.ndarray]:
        if ns in self._gt:
            return self._gt[ns].copy()
        if not len(self._gt_ns):
            return None
        j = associate([ns / 1e9], self._gt_ns / 1e9, ASSOC_TOL)[0]
        return None if j is None else self._gt[int(self._gt_ns[j])].copy()

    def __len__(self) -> int:
        return len(self._sel)

    @property
    def has_gt_pose(self) -> bool:
        return any(self._gt_for(self._img_ns[i]) is not None for i in self._sel)

    @property
    def has_gt_depth(self) -> bool:
        return bool(self._has_depth)

    def gt_trajectory(self):
        rows = [(ns_to_stamp(self._img_ns[i]), self._gt_for(self._img_ns[i])) for i in self._sel]
        rows = [r for r in rows if r[1] is not None]
        if not rows:
            return None
        return (np.array([r[0] for r in rows]), np.stack([r[1] for r in rows]))

    def iter_frames(self, keep_mono: Optional[bool] = None, depth: bool = True) -> Iterator[Frame]:
        keep = self.keep_mono if keep_mono is None else keep_mono
        wanted = set(self._sel)
        last = self._sel[-1] if len(self._sel) else -1
        tp = self.topics
        topics = [tp["image"]] + ([tp["depth"]] if self._has_depth and depth else [])
        group_t, group = None, []
        k = -1        # ordinal of the image message
        out = 0

        def flush():
            nonlocal out
            imgs = [(o, dec) for top, o, dec in group if top == tp["image"]]
            depths = [dec for top, o, dec in group if top != tp["image"]]
            for ordinal, dec in imgs:
                m = dec()
                ns = msg_stamp_ns(m)
                if ns == 0:           # a driver that never stamped: the recorder's time
                    ns = group_t
                    if not self._unstamped:
                        self._unstamped = True
                        print(f"warning: {tp['image']}: images without a header stamp: "
                              "stamped with the bag's log time", file=sys.stderr, flush=True)
                depth = None
                for dd in depths:
                    dm = dd()
                    if msg_stamp_ns(dm) == ns:
                        depth = decode_depth(dm)
                        break
                try:
                    img = decode_rgb(m, keep)
                except ConversionError as e:
                    raise DatasetError(f"image {ordinal} on {tp['image']}: {e}") from None
                if (img.shape[1], img.shape[0]) != (self.intrinsics.width, self.intrinsics.height):
                    raise DatasetError(f"image {ordinal} in the bag is {img.shape[1]}x"
                                       f"{img.shape[0]} but the calibration says "
                                       f"{self.intrinsics.width}x{self.intrinsics.height}")
                yield Frame(index=out, timestamp=ns_to_stamp(ns), image=img,
                            intrinsics=copy_intrinsics(self.intrinsics),
                            gt_pose=self._gt_for(ns), gt_depth=depth)
                out += 1

        for topic, t, dec in self._bag.messages(topics):
            if t != group_t:
                yield from flush()
                group_t, group = t, []
                if k >= last:
                    return
            if topic == tp["image"]:
                k += 1
                if k in wanted:
                    group.append((topic, k, dec))
            else:
                group.append((topic, k, dec))
        yield from flush()
