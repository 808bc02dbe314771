"""Frame sources shared by every dataset layout: the :class:`Dataset` interface, file- and
video-backed datasets, image/depth readers, timestamp association and pose interpolation.
The layouts themselves are in :mod:`splat_slam_ros.io.dataset_formats`; the entry point is
:func:`splat_slam_ros.io.datasets.open_dataset`."""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Iterable, Iterator, List, Optional, Sequence, Tuple

import cv2
import numpy as np
import torch
import yaml

from splat_slam_ros.geometry import interpolate_pose
from splat_slam_ros.io.sensor_codec import to_8bit, to_rgb
from splat_slam_ros.io.trajectory_io import TrajectoryFormatError, read_trajectory
from splat_slam_ros.types import DatasetError, Frame, Intrinsics, IntrinsicsError


FORMATS = ("tum", "replica", "scannet", "euroc", "folder", "video", "posefolder", "bag")
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")
VIDEO_EXTS = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv")

ASSOC_TOL = 0.02       # s, nearest-timestamp association (TUM associate.py default)
INTERP_MAX_GAP = 0.1   # s, widest bracket of ground-truth samples we interpolate across
DEFAULT_FPS = 30.0

# Published TUM RGB-D calibrations (ROS default 640x480 streams).
TUM_DEFAULTS = {
    "fr1": Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480, "plumb_bob",
                      [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
    "fr2": Intrinsics(520.9, 521.0, 325.1, 249.7, 640, 480, "plumb_bob",
                      [0.2312, -0.7849, -0.0033, -0.0001, 0.9172]),
    "fr3": Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480, "plumb_bob", []),
}
REPLICA_DEFAULT = Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)


# ---------------------------------------------------------------- small helpers
def stamp_to_ns(t: float) -> int:
    """Seconds (float) -> integer nanoseconds, exactly rounded (ns_to_stamp() inverts it for
    any stamp already on the nanosecond grid)."""
    return int(round(Fraction(float(t)) * 10**9))


def ns_to_stamp(ns: int) -> float:
    """Integer nanoseconds -> seconds, correctly rounded (int / int)."""
    return int(ns) / 10**9


def quantize_stamp(t: float) -> float:
    """Snap a time in seconds to the nanosecond grid of a ROS stamp (bag round trips exact)."""
    return ns_to_stamp(stamp_to_ns(t))


def stamp_key(t: float) -> float:
    """A timestamp rounded to 0.1 ms: how a frame is matched to its line of a trajectory
    file (written to the microsecond)."""
    return round(float(t), 4)


def natural_key(name: str):
    """Sort key that orders 'img2' before 'img10'."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def copy_intrinsics(k: Intrinsics) -> Intrinsics:
    return Intrinsics(k.fx, k.fy, k.cx, k.cy, k.width, k.height, k.distortion_model,
                      list(k.distortion))


def load_intrinsics(path) -> Tuple[Intrinsics, dict]:
    """Read an intrinsics file; returns (Intrinsics, extra keys such as ``depth_scale``).

    Accepts our YAML (fx fy cx cy width height [distortion_model distortion depth_scale]),
    a ROS camera_info YAML, or Replica's ``cam_params.json``.
    """
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"intrinsics file not found: {p}")
    if p.suffix.lower() == ".json":
        return _replica_cam_params(p)
    try:
        K = Intrinsics.from_yaml(p)
    except IntrinsicsError as e:
        raise DatasetError(str(e)) from None
    d = yaml.safe_load(p.read_text()) or {}
    extra = {}
    if "depth_scale" in d:
        try:
            extra["depth_scale"] = float(d["depth_scale"])
        except (TypeError, ValueError):
            raise DatasetError(f"{p}: depth_scale must be a number, got {d['depth_scale']!r}") \
                from None
    return K, extra


def _replica_cam_params(p: Path) -> Tuple[Intrinsics, dict]:
    try:
        c = json.loads(p.read_text())["camera"]
        K = Intrinsics(float(c["fx"]), float(c["fy"]), float(c["cx"]), float(c["cy"]),
                       int(c["w"]), int(c["h"]))
    except (ValueError, KeyError, TypeError) as e:
        raise DatasetError(f"{p}: expected Replica camera params "
                           f'{{"camera": {{"w","h","fx","fy","cx","cy","scale"}}}} ({e})') from None
    extra = {"depth_scale": float(c["scale"])} if "scale" in c else {}
    return K, extra


def as_intrinsics(intrinsics) -> Tuple[Optional[Intrinsics], dict]:
    if intrinsics is None:
        return None, {}
    if isinstance(intrinsics, Intrinsics):
        return copy_intrinsics(intrinsics), {}
    return load_intrinsics(intrinsics)


def read_image(path: Path, keep_mono: bool = False) -> np.ndarray:
    """Image file -> uint8 RGB HxWx3 (or HxW mono8 when ``keep_mono`` and the file is mono)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"cannot read image {path}")
    return _to_rgb8(img, path, keep_mono)


def _to_rgb8(img: np.ndarray, src, keep_mono: bool) -> np.ndarray:
    """A decoded file or video frame (OpenCV's BGR(A) or mono, 8 or 16 bit) -> RGB uint8."""
    if img.dtype == np.uint16:
        img = to_8bit(img)
    elif img.dtype != np.uint8:
        raise DatasetError(f"unsupported image pixel type {img.dtype} in {src} (need 8/16-bit)")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim == 2:
        return np.ascontiguousarray(img) if keep_mono else np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise DatasetError(f"unsupported image shape {img.shape} in {src}")
    return to_rgb(img, "bgra8" if img.shape[2] == 4 else "bgr8")


def read_depth(path: Path, scale: float, size: Optional[Tuple[int, int]] = None,
               resize: bool = False) -> np.ndarray:
    """Depth image -> float32 metres (raw / scale; float images are taken as metres).

    ``size`` = (width, height) expected; a different size is an error unless
    ``resize`` (nearest neighbour, so no depth values are invented at edges).
    """
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None:
        raise DatasetError(f"cannot read depth image {path}")
    if d.ndim == 3:
        raise DatasetError(f"depth image {path} has {d.shape[2]} channels; expected one")
    if np.issubdtype(d.dtype, np.integer):
        d = d.astype(np.float32) / np.float32(scale)
    else:
        d = d.astype(np.float32)
    d[~np.isfinite(d)] = 0
    if size is not None and (d.shape[1], d.shape[0]) != tuple(size):
        if not resize:
            raise DatasetError(f"depth image {path} is {d.shape[1]}x{d.shape[0]} but the colour "
                               f"images are {size[0]}x{size[1]}")
        d = cv2.resize(d, tuple(size), interpolation=cv2.INTER_NEAREST)
    return d


def read_stamp_list(path: Path) -> List[Tuple[float, str]]:
    """TUM rgb.txt / depth.txt: ``timestamp filename`` rows, '#' comments."""
    rows = []
    for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        try:
            rows.append((float(parts[0]), parts[1]))
        except (ValueError, IndexError):
            raise DatasetError(f"{path}:{n}: expected 'timestamp filename', got {s[:80]!r}") \
                from None
    if not rows:
        raise DatasetError(f"{path}: no 'timestamp filename' rows")
    return rows


def associate(t_query: Sequence[float], t_ref: Sequence[float],
              tol: float = ASSOC_TOL) -> List[Optional[int]]:
    """Index of the nearest ``t_ref`` for each ``t_query`` within ``tol`` seconds, else None."""
    tr = np.asarray(t_ref, dtype=np.float64)
    order = np.argsort(tr, kind="stable")
    trs = tr[order]
    out: List[Optional[int]] = []
    for t in np.asarray(t_query, dtype=np.float64):
        i = int(np.searchsorted(trs, t))
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(trs) and abs(trs[j] - t) <= tol:
                if best is None or abs(trs[j] - t) < abs(trs[best] - t):
                    best = j
        out.append(None if best is None else int(order[best]))
    return out


def interpolate_poses(t_src, poses_src, t_query, tol: float = ASSOC_TOL,
                      max_gap: float = INTERP_MAX_GAP) -> List[Optional[np.ndarray]]:
    """Poses at ``t_query``: linear translation + SLERP rotation between the two bracketing
    samples when they are at most ``max_gap`` apart, else the nearest sample within ``tol``,
    else None."""
    ts = np.asarray(t_src, dtype=np.float64)
    P = np.asarray(poses_src, dtype=np.float64)
    order = np.argsort(ts, kind="stable")
    ts, P = ts[order], P[order]
    out: List[Optional[np.ndarray]] = []
    for t in np.asarray(t_query, dtype=np.float64):
        i = int(np.searchsorted(ts, t))   # ts[i-1] < t <= ts[i]
        if i < len(ts) and abs(ts[i] - t) < 1e-9:
            out.append(P[i].copy())
            continue
        if 0 < i < len(ts) and ts[i] - ts[i - 1] <= max_gap:
            a = (t - ts[i - 1]) / (ts[i] - ts[i - 1])
            out.append(interpolate_pose(torch.from_numpy(P[i - 1]), torch.from_numpy(P[i]),
                                        a).numpy())
            continue
        j = associate([t], ts, tol)[0]
        out.append(None if j is None else P[j].copy())
    return out


def read_gt_trajectory(path: Path, fmt: str = "auto") -> Tuple[np.ndarray, np.ndarray]:
    try:
        return read_trajectory(path, fmt)
    except TrajectoryFormatError as e:
        raise DatasetError(str(e)) from None


def tum_default_for(path: Path) -> Optional[Tuple[str, Intrinsics]]:
    for part in reversed(path.resolve().parts):
        m = re.search(r"(?:freiburg|fr)([123])(?![0-9])", part.lower())
        if m:
            key = f"fr{m.group(1)}"
            return key, copy_intrinsics(TUM_DEFAULTS[key])
    return None


def list_images(folder: Path) -> List[Path]:
    return sorted((p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in IMAGE_EXTS and not p.name.startswith(".")),
                  key=lambda p: natural_key(p.name))


def numeric_stem(p: Path) -> Optional[float]:
    try:
        v = float(p.stem)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


# --------------------------------------------------------------------- datasets
@dataclass
class FrameEntry:
    timestamp: float
    image: Path
    depth: Optional[Path] = None
    gt_pose: Optional[np.ndarray] = None


class Dataset:
    """A sequence of frames. Iterate for :class:`Frame` objects (lazy: one image in memory).

    Attributes: ``name``, ``format``, ``source`` (path), ``intrinsics``, ``keep_mono``,
    ``depth_scale`` (raw units per metre, None without depth), ``notes`` (list of str
    describing conversions applied, e.g. the negative-fy flip).
    """
    format = "?"

    def __init__(self, name: str, source: Path, intrinsics: Intrinsics,
                 keep_mono: bool = False, notes: Optional[List[str]] = None):
        self.name = name
        self.source = Path(source)
        self.intrinsics = intrinsics
        self.keep_mono = keep_mono
        self.depth_scale: Optional[float] = None
        self.notes: List[str] = list(notes or [])

    # subclasses implement these
    def __len__(self) -> int:
        raise NotImplementedError

    def iter_frames(self, keep_mono: Optional[bool] = None, depth: bool = True) -> Iterator[Frame]:
        """The frames in order; ``depth`` False: without ``gt_depth`` (not read or decoded:
        tracking needs none)."""
        raise NotImplementedError

    @property
    def has_gt_pose(self) -> bool:
        raise NotImplementedError

    @property
    def has_gt_depth(self) -> bool:
        raise NotImplementedError

    def gt_trajectory(self) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """(timestamps (N,), camera-to-world poses (N,4,4)) at the frames that have ground
        truth (after stride/max_frames), or None when the dataset has none."""
        raise NotImplementedError

    def __iter__(self) -> Iterator[Frame]:
        return self.iter_frames()

    def frames_at(self, indices: Iterable[int], depth: bool = False) -> Iterator[Frame]:
        """The frames whose ``Frame.index`` is in ``indices``, in order (with ``gt_depth`` when
        ``depth``): a stream decodes its frames in turn up to the last one asked for; a folder
        of files (:class:`FileDataset`) reads just these."""
        want = sorted({int(i) for i in indices})
        if want:
            yield from self._frames_of(want, depth)

    def frames_at_stamps(self, stamps: Iterable[float], depth: bool = True) -> Iterator[Frame]:
        """The frames whose :func:`stamp_key` is one of ``stamps``' (the 0.1 ms they round
        to), in order: a folder of files reads just these, a stream decodes them in turn."""
        want = {stamp_key(t) for t in stamps}
        if not want:
            return
        known = self._stamps()
        if known is not None:
            yield from self.frames_at((i for i, t in enumerate(known) if stamp_key(t) in want),
                                      depth)
            return
        for f in self.iter_frames(depth=depth):
            if stamp_key(f.timestamp) in want:
                yield f

    def _stamps(self) -> Optional[List[float]]:
        """Every frame's timestamp without decoding any, or None when that needs decoding."""
        return None

    def _frames_of(self, want: List[int], depth: bool) -> Iterator[Frame]:
        """:meth:`frames_at`'s frames (``want``: sorted indices): decoded in turn."""
        for f in self.iter_frames(depth=depth):
            if f.index in want:
                yield f
            if f.index >= want[-1]:
                break

    def close(self) -> None:
        """Release open files (bags); file datasets hold none."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def info(self) -> dict:
        """Plain-data description (written beside converted bags)."""
        K = self.intrinsics
        return {"name": self.name, "format": self.format, "source": str(self.source),
                "frames": len(self), "has_gt_pose": bool(self.has_gt_pose),
                "has_gt_depth": bool(self.has_gt_depth),
                "depth_scale": None if self.depth_scale is None else float(self.depth_scale),
                "intrinsics": {"fx": float(K.fx), "fy": float(K.fy), "cx": float(K.cx),
                               "cy": float(K.cy), "width": int(K.width), "height": int(K.height),
                               "distortion_model": str(K.distortion_model),
                               "distortion": [float(x) for x in K.distortion]},
                "notes": list(self.notes)}

    def __repr__(self) -> str:
        K = self.intrinsics
        return (f"<{type(self).__name__} {self.format} '{self.name}': {len(self)} frames "
                f"{K.width}x{K.height}, gt_pose={self.has_gt_pose}, gt_depth={self.has_gt_depth}>")


def select_frames(n: int, stride: int, max_frames: Optional[int]) -> range:
    sel = range(0, n, stride)
    return sel if max_frames is None else sel[:max_frames]


def check_selection(stride, max_frames):
    if int(stride) < 1:
        raise DatasetError(f"stride must be >= 1, got {stride}")
    if max_frames is not None and int(max_frames) < 1:
        raise DatasetError(f"max_frames must be >= 1, got {max_frames}")


def _fix_focal_signs(K: Intrinsics) -> Tuple[Intrinsics, Optional[np.ndarray], Optional[str]]:
    """Negative fx/fy -> positive, plus the 4x4 mirror F to apply as F @ T @ F to poses."""
    if K.fx > 0 and K.fy > 0:
        return K, None, None
    if K.fx == 0 or K.fy == 0:
        raise DatasetError(f"intrinsics have a zero focal length (fx={K.fx}, fy={K.fy})")
    F = np.diag([np.sign(K.fx), np.sign(K.fy), 1.0, 1.0])
    K2 = copy_intrinsics(K)
    K2.fx, K2.fy = abs(K.fx), abs(K.fy)
    axes = "".join(a for a, f in (("x", K.fx), ("y", K.fy)) if f < 0)
    note = (f"negative focal length on {axes} (fx={K.fx}, fy={K.fy}): made positive; "
            f"ground-truth poses returned as F @ T @ F with F = diag({', '.join(str(int(v)) for v in F.diagonal()[:3])})")
    return K2, F, note


class FileDataset(Dataset):
    """Datasets made of image files (all formats except video and bag)."""

    def __init__(self, name: str, fmt: str, source: Path, intrinsics: Intrinsics,
                 entries: List[FrameEntry], depth_scale: Optional[float] = None,
                 resize_depth: bool = False, keep_mono: bool = False,
                 max_frames: Optional[int] = None, stride: int = 1,
                 notes: Optional[List[str]] = None):
        check_selection(stride, max_frames)
        if not entries:
            raise DatasetError(f"{source}: no frames found")
        K, F, note = _fix_focal_signs(intrinsics)
        super().__init__(name, source, K, keep_mono, notes)
        self.format = fmt
        if F is not None:
            self.notes.append(note)
            for e in entries:
                if e.gt_pose is not None:
                    e.gt_pose = F @ e.gt_pose @ F
        for e in entries:
            e.timestamp = quantize_stamp(e.timestamp)
        self._entries = [entries[i] for i in select_frames(len(entries), int(stride), max_frames)]
        self.depth_scale = depth_scale if any(e.depth is not None for e in self._entries) else None
        self._resize_depth = resize_depth
        # Validate the intrinsics against the first image now (clear error, not mid-run).
        first = read_image(self._entries[0].image, keep_mono=True)
        self._check_size(first, self._entries[0].image)

    def _check_size(self, img: np.ndarray, path: Path):
        K = self.intrinsics
        if (img.shape[1], img.shape[0]) != (K.width, K.height):
            raise DatasetError(f"image {path} is {img.shape[1]}x{img.shape[0]} but the intrinsics "
                               f"are for {K.width}x{K.height}")

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def has_gt_pose(self) -> bool:
        return any(e.gt_pose is not None for e in self._entries)

    @property
    def has_gt_depth(self) -> bool:
        return any(e.depth is not None for e in self._entries)

    def gt_trajectory(self):
        sel = [e for e in self._entries if e.gt_pose is not None]
        if not sel:
            return None
        return (np.array([e.timestamp for e in sel], dtype=np.float64),
                np.stack([e.gt_pose for e in sel]).astype(np.float64))

    def iter_frames(self, keep_mono: Optional[bool] = None, depth: bool = True) -> Iterator[Frame]:
        keep = self.keep_mono if keep_mono is None else keep_mono
        for i in range(len(self._entries)):
            yield self._read(i, keep, depth)

    def _stamps(self) -> List[float]:
        return [float(e.timestamp) for e in self._entries]

    def _frames_of(self, want: List[int], depth: bool) -> Iterator[Frame]:
        """Only the image files of ``want`` are read."""
        for i in want:
            if 0 <= i < len(self._entries):
                yield self._read(i, self.keep_mono, depth)

    def _read(self, i: int, keep_mono: bool, with_depth: bool = True) -> Frame:
        e = self._entries[i]
        K = self.intrinsics
        img = read_image(e.image, keep_mono)
        self._check_size(img, e.image)
        depth = None
        if e.depth is not None and with_depth:
            depth = read_depth(e.depth, self.depth_scale, (K.width, K.height),
                               self._resize_depth)
        return Frame(index=i, timestamp=float(e.timestamp), image=img,
                     intrinsics=copy_intrinsics(K),
                     gt_pose=None if e.gt_pose is None else e.gt_pose.copy(), gt_depth=depth)


class VideoDataset(Dataset):
    """A video file; timestamps from the decoder's frame position (or index / fps)."""
    format = "video"

    def __init__(self, path: Path, intrinsics: Intrinsics, fps: Optional[float] = None,
                 keep_mono: bool = False, max_frames: Optional[int] = None, stride: int = 1):
        check_selection(stride, max_frames)
        K, _, note = _fix_focal_signs(intrinsics)
        super().__init__(path.stem, path, K, keep_mono, [note] if note else None)
        cap = self._open()
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        vfps = cap.get(cv2.CAP_PROP_FPS)
        cap.release()
        if (w, h) != (K.width, K.height):
            raise DatasetError(f"video {path} is {w}x{h} but the intrinsics are for "
                               f"{K.width}x{K.height}")
        if fps is not None and fps <= 0:
            raise DatasetError(f"fps must be > 0, got {fps}")
        self.fps = fps
        self.video_fps = vfps if vfps and vfps > 0 else None
        self._stride, self._max = int(stride), max_frames
        self._n_total = max(n, 0)   # container's count (an estimate for some codecs)

    def _open(self):
        cap = cv2.VideoCapture(str(self.source))
        if not cap.isOpened():
            raise DatasetError(f"cannot open video {self.source}")
        return cap

    def __len__(self) -> int:
        return len(select_frames(self._n_total, self._stride, self._max))

    has_gt_pose = property(lambda self: False)
    has_gt_depth = property(lambda self: False)

    def gt_trajectory(self):
        return None

    def iter_frames(self, keep_mono: Optional[bool] = None, depth: bool = True) -> Iterator[Frame]:
        keep = self.keep_mono if keep_mono is None else keep_mono     # a video has no depth
        cap = self._open()
        fps = self.fps or self.video_fps or DEFAULT_FPS
        src, out, last_t = 0, 0, -1.0
        try:
            while self._max is None or out < self._max:
                if src % self._stride:
                    if not cap.grab():
                        break
                    src += 1
                    continue
                ok, img = cap.read()
                if not ok:
                    break
                t = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0   # after read(): this frame's time
                if self.fps is not None or not (t > last_t or (src == 0 and t >= 0)):
                    t = src / fps
                t = quantize_stamp(t)
                last_t = t
                yield Frame(index=out, timestamp=float(t),
                            image=_to_rgb8(img, self.source, keep),
                            intrinsics=copy_intrinsics(self.intrinsics))
                src += 1
                out += 1
        finally:
            cap.release()
