"""Dataset readers: every supported layout yields :class:`~splat_slam_ros.types.Frame`.

``open_dataset(path)`` detects the layout (or takes ``fmt``) and returns a
:class:`Dataset`: iterable of frames, ``len()``, ``.intrinsics``, ``.name``,
``.format``, ``.has_gt_pose``, ``.has_gt_depth`` and ``.gt_trajectory()``.

Formats (see bags/README.md for the full table):

``tum``        rgb.txt / depth.txt / groundtruth.txt (TUM RGB-D)
``replica``    results/frame%06d.jpg, results/depth%06d.png, traj.txt (NICE-SLAM layout)
``scannet``    color/N.jpg, depth/N.png, pose/N.txt, intrinsic/intrinsic_color.txt
``euroc``      mav0/cam0/data.csv + data/*.png, sensor.yaml, ground truth CSV or TUM file
``posefolder`` color/N.png, depth/N.png|pgm, pose.txt rows ``tx ty tz qx qy qz qw``
               (ICL-NUIM / slambook style)
``folder``     a folder of images + intrinsics YAML
``video``      a video file cv2 can open + intrinsics YAML
``bag``        a rosbag2 folder (or .mcap file) written by ``splat-slam-convert``

Conventions (types.py): RGB uint8 images, depth float32 metres (0 = missing),
camera-to-world float64 poses with OpenCV camera axes. Frames are numbered
0..len-1 after ``stride`` / ``max_frames`` are applied.

Intrinsics precedence (all formats): an explicit ``intrinsics`` argument (an
:class:`Intrinsics` or a YAML/JSON file) wins; then a file shipped with the
data (``intrinsics.yaml``, ``cam_params.json``, ``sensor.yaml``,
``intrinsic_color.txt``); then format defaults (TUM fr1/fr2/fr3 by folder name,
Replica by image size). Distortion is carried in ``Intrinsics`` (not applied).

Negative focal lengths (ICL-NUIM's ``fy = -480``): such a camera has its y axis
pointing up while image rows go down. The reader makes ``fy`` positive and
returns ground-truth poses as ``F @ T @ F`` with ``F = diag(1, -1, 1, 1)``
(``diag(-1, 1, 1, 1)`` for a negative ``fx``): the same motion seen through a
right-handed OpenCV camera (x right, y down, z forward) in a world mirrored
across its y axis. Images are unchanged, so depth, intrinsics and poses stay
mutually consistent (tests/test_datasets.py checks the reprojection).
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Iterator, List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np
import torch
import yaml

from splat_slam_ros.geometry import interpolate_pose, pose_from_tq
from splat_slam_ros.io.trajectory_io import TrajectoryFormatError, read_trajectory
from splat_slam_ros.types import Frame, Intrinsics, IntrinsicsError


class DatasetError(ValueError):
    """A dataset is missing, malformed or inconsistent (one-line, user-facing message)."""


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


def natural_key(name: str):
    """Sort key that orders 'img2' before 'img10'."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _copy_intrinsics(k: Intrinsics) -> Intrinsics:
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


def _as_intrinsics(intrinsics) -> Tuple[Optional[Intrinsics], dict]:
    if intrinsics is None:
        return None, {}
    if isinstance(intrinsics, Intrinsics):
        return _copy_intrinsics(intrinsics), {}
    return load_intrinsics(intrinsics)


def read_image(path: Path, keep_mono: bool = False) -> np.ndarray:
    """Image file -> uint8 RGB HxWx3 (or HxW mono8 when ``keep_mono`` and the file is mono)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"cannot read image {path}")
    return _to_rgb8(img, path, keep_mono)


def _to_rgb8(img: np.ndarray, src, keep_mono: bool, bgr: bool = True) -> np.ndarray:
    if img.dtype == np.uint16:
        img = ((img.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise DatasetError(f"unsupported image pixel type {img.dtype} in {src} (need 8/16-bit)")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim == 2:
        return np.ascontiguousarray(img) if keep_mono else np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise DatasetError(f"unsupported image shape {img.shape} in {src}")
    img = img[..., :3]
    return np.ascontiguousarray(img[..., ::-1] if bgr else img)


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


def _read_stamp_list(path: Path) -> List[Tuple[float, str]]:
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


def _read_gt(path: Path, fmt: str = "auto") -> Tuple[np.ndarray, np.ndarray]:
    try:
        return read_trajectory(path, fmt)
    except TrajectoryFormatError as e:
        raise DatasetError(str(e)) from None


def _tum_default_for(path: Path) -> Optional[Tuple[str, Intrinsics]]:
    for part in reversed(path.resolve().parts):
        m = re.search(r"(?:freiburg|fr)([123])(?![0-9])", part.lower())
        if m:
            key = f"fr{m.group(1)}"
            return key, _copy_intrinsics(TUM_DEFAULTS[key])
    return None


def _listdir_images(folder: Path) -> List[Path]:
    return sorted((p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in IMAGE_EXTS and not p.name.startswith(".")),
                  key=lambda p: natural_key(p.name))


def _numeric_stem(p: Path) -> Optional[float]:
    try:
        v = float(p.stem)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


# --------------------------------------------------------------------- datasets
@dataclass
class _Entry:
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

    def iter_frames(self, keep_mono: Optional[bool] = None) -> Iterator[Frame]:
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


def _select(n: int, stride: int, max_frames: Optional[int]) -> range:
    sel = range(0, n, stride)
    return sel if max_frames is None else sel[:max_frames]


def _check_selection(stride, max_frames):
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
    K2 = _copy_intrinsics(K)
    K2.fx, K2.fy = abs(K.fx), abs(K.fy)
    axes = "".join(a for a, f in (("x", K.fx), ("y", K.fy)) if f < 0)
    note = (f"negative focal length on {axes} (fx={K.fx}, fy={K.fy}): made positive; "
            f"ground-truth poses returned as F @ T @ F with F = diag({', '.join(str(int(v)) for v in F.diagonal()[:3])})")
    return K2, F, note


class FileDataset(Dataset):
    """Datasets made of image files (all formats except video and bag)."""

    def __init__(self, name: str, fmt: str, source: Path, intrinsics: Intrinsics,
                 entries: List[_Entry], depth_scale: Optional[float] = None,
                 resize_depth: bool = False, keep_mono: bool = False,
                 max_frames: Optional[int] = None, stride: int = 1,
                 notes: Optional[List[str]] = None):
        _check_selection(stride, max_frames)
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
        self._entries = [entries[i] for i in _select(len(entries), int(stride), max_frames)]
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

    def iter_frames(self, keep_mono: Optional[bool] = None) -> Iterator[Frame]:
        keep = self.keep_mono if keep_mono is None else keep_mono
        K = self.intrinsics
        for i, e in enumerate(self._entries):
            img = read_image(e.image, keep)
            self._check_size(img, e.image)
            depth = None
            if e.depth is not None:
                depth = read_depth(e.depth, self.depth_scale, (K.width, K.height),
                                   self._resize_depth)
            yield Frame(index=i, timestamp=float(e.timestamp), image=img,
                        intrinsics=_copy_intrinsics(K),
                        gt_pose=None if e.gt_pose is None else e.gt_pose.copy(),
                        gt_depth=depth)


class VideoDataset(Dataset):
    """A video file; timestamps from the decoder's frame position (or index / fps)."""
    format = "video"

    def __init__(self, path: Path, intrinsics: Intrinsics, fps: Optional[float] = None,
                 keep_mono: bool = False, max_frames: Optional[int] = None, stride: int = 1):
        _check_selection(stride, max_frames)
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
        return len(_select(self._n_total, self._stride, self._max))

    has_gt_pose = property(lambda self: False)
    has_gt_depth = property(lambda self: False)

    def gt_trajectory(self):
        return None

    def iter_frames(self, keep_mono: Optional[bool] = None) -> Iterator[Frame]:
        keep = self.keep_mono if keep_mono is None else keep_mono
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
                            intrinsics=_copy_intrinsics(self.intrinsics))
                src += 1
                out += 1
        finally:
            cap.release()


# ---------------------------------------------------------------- format readers
def _open_tum(root: Path, K, extra, **kw) -> FileDataset:
    rgb_txt = root / "rgb.txt"
    if not rgb_txt.is_file():
        raise DatasetError(f"{root}: TUM layout needs rgb.txt (timestamp filename rows)")
    notes = []
    local = root / "intrinsics.yaml"
    if K is None and local.is_file():
        K, extra = load_intrinsics(local)
    if K is None:
        d = _tum_default_for(root)
        if d is None:
            raise DatasetError(f"{root}: no intrinsics: add intrinsics.yaml, pass --intrinsics "
                               "FILE, or name the folder after the TUM camera (fr1/fr2/fr3)")
        key, K = d
        notes.append(f"intrinsics: TUM {key} defaults chosen from the folder name")
    rgb = _read_stamp_list(rgb_txt)
    entries = [_Entry(t, root / f) for t, f in rgb]
    depth_txt = root / "depth.txt"
    scale = None
    if depth_txt.is_file():
        scale = float(kw.pop("depth_scale", None) or extra.get("depth_scale", 5000.0))
        dep = _read_stamp_list(depth_txt)
        idx = associate([t for t, _ in rgb], [t for t, _ in dep])
        if all(i is None for i in idx):
            raise DatasetError(f"{root}: no depth.txt stamp within {ASSOC_TOL} s of any rgb.txt "
                               f"stamp (rgb {rgb[0][0]:.3f}..{rgb[-1][0]:.3f}, depth "
                               f"{dep[0][0]:.3f}..{dep[-1][0]:.3f})")
        for e, i in zip(entries, idx):
            e.depth = None if i is None else root / dep[i][1]
        miss = sum(i is None for i in idx)
        if miss:
            notes.append(f"{miss} rgb frames have no depth within {ASSOC_TOL} s")
    else:
        kw.pop("depth_scale", None)
    gt_txt = root / "groundtruth.txt"
    if gt_txt.is_file():
        ts, P = _read_gt(gt_txt, "tum")
        poses = interpolate_poses(ts, P, [e.timestamp for e in entries])
        if all(p is None for p in poses):
            raise DatasetError(f"{root}: no groundtruth.txt sample within {ASSOC_TOL} s of any "
                               f"rgb.txt stamp (rgb {rgb[0][0]:.3f}..{rgb[-1][0]:.3f}, "
                               f"groundtruth {ts[0]:.3f}..{ts[-1]:.3f})")
        for e, p in zip(entries, poses):
            e.gt_pose = p
    return FileDataset(root.name, "tum", root, K, entries, depth_scale=scale, notes=notes, **kw)


def _open_replica(root: Path, K, extra, fps=None, **kw) -> FileDataset:
    res = root / "results"
    if not res.is_dir():
        raise DatasetError(f"{root}: Replica layout needs results/frame%06d.jpg")
    imgs = sorted(res.glob("frame*.jpg"), key=lambda p: natural_key(p.name)) or \
        sorted(res.glob("frame*.png"), key=lambda p: natural_key(p.name))
    if not imgs:
        raise DatasetError(f"{res}: no frame*.jpg images")
    depths = sorted(res.glob("depth*.png"), key=lambda p: natural_key(p.name))
    if depths and len(depths) != len(imgs):
        raise DatasetError(f"{res}: {len(imgs)} colour frames but {len(depths)} depth images")
    notes = []
    if K is None:
        for cp in (root / "cam_params.json", root.parent / "cam_params.json"):
            if cp.is_file():
                K, extra = load_intrinsics(cp)
                break
    if K is None:
        h, w = read_image(imgs[0], keep_mono=True).shape[:2]
        if (w, h) != (REPLICA_DEFAULT.width, REPLICA_DEFAULT.height):
            raise DatasetError(f"{root}: no intrinsics (no cam_params.json here or in the parent, "
                               f"no --intrinsics) and the images are {w}x{h}, not Replica's "
                               "1200x680")
        K = _copy_intrinsics(REPLICA_DEFAULT)
        notes.append("intrinsics: Replica defaults (600, 600, 599.5, 339.5)")
    scale = float(kw.pop("depth_scale", None) or extra.get("depth_scale", 6553.5))
    fps = fps or DEFAULT_FPS
    entries = [_Entry(i / fps, p, depths[i] if depths else None) for i, p in enumerate(imgs)]
    traj = root / "traj.txt"
    if traj.is_file():
        rows = _numeric_matrix_rows(traj, 16)
        if len(rows) != len(imgs):
            raise DatasetError(f"{traj} has {len(rows)} poses but results/ has {len(imgs)} frames")
        for e, r in zip(entries, rows):
            e.gt_pose = r.reshape(4, 4)
    return FileDataset(root.name, "replica", root, K, entries,
                       depth_scale=scale if depths else None, notes=notes, **kw)


def _numeric_matrix_rows(path: Path, ncol: int) -> np.ndarray:
    try:
        a = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except ValueError as e:
        raise DatasetError(f"{path}: not a numeric table ({e})") from None
    if a.size == 0 or a.shape[1] != ncol:
        raise DatasetError(f"{path}: expected {ncol} numbers per row, found "
                           f"{a.shape[1] if a.size else 0}")
    return a


def _open_scannet(root: Path, K, extra, fps=None, **kw) -> FileDataset:
    cdir = root / "color"
    if not cdir.is_dir():
        raise DatasetError(f"{root}: ScanNet layout needs color/N.jpg")
    imgs = [p for p in _listdir_images(cdir) if p.stem.isdigit()]
    imgs.sort(key=lambda p: int(p.stem))
    if not imgs:
        raise DatasetError(f"{cdir}: no N.jpg colour images")
    notes = []
    if K is None:
        kf = root / "intrinsic" / "intrinsic_color.txt"
        if not kf.is_file():
            raise DatasetError(f"{root}: no intrinsics: expected intrinsic/intrinsic_color.txt "
                               "or --intrinsics FILE")
        M = _numeric_matrix_rows(kf, 4)
        h, w = read_image(imgs[0], keep_mono=True).shape[:2]
        K = Intrinsics(float(M[0, 0]), float(M[1, 1]), float(M[0, 2]), float(M[1, 2]), w, h)
    ddir = root / "depth"
    depths = None
    if ddir.is_dir():
        depths = {p.stem: p for p in ddir.glob("*.png")}
        missing = [p.stem for p in imgs if p.stem not in depths]
        if missing:
            raise DatasetError(f"{root}: {len(imgs)} colour frames but {len(depths)} depth images "
                               f"(no depth/{missing[0]}.png)")
        notes.append("depth resized to the colour size (nearest neighbour)")
    scale = float(kw.pop("depth_scale", None) or extra.get("depth_scale", 1000.0))
    fps = fps or DEFAULT_FPS
    entries = [_Entry(i / fps, p, depths[p.stem] if depths else None) for i, p in enumerate(imgs)]
    pdir = root / "pose"
    if pdir.is_dir():
        bad = 0
        for e, p in zip(entries, imgs):
            f = pdir / f"{p.stem}.txt"
            if not f.is_file():
                raise DatasetError(f"{pdir}: missing pose file {f.name}")
            try:
                T = np.loadtxt(f, dtype=np.float64)
            except ValueError as err:
                raise DatasetError(f"{f}: not a 4x4 matrix ({err})") from None
            if T.shape != (4, 4):
                raise DatasetError(f"{f}: expected a 4x4 matrix, got shape {T.shape}")
            if np.all(np.isfinite(T)):
                e.gt_pose = T
            else:
                bad += 1
        if bad:
            notes.append(f"{bad} frames have invalid (inf/nan) ground-truth poses: gt_pose=None")
    return FileDataset(root.name, "scannet", root, K, entries,
                       depth_scale=scale if depths else None, resize_depth=True,
                       notes=notes, **kw)


def _euroc_root(path: Path) -> Tuple[Path, Path]:
    """(sequence folder, mav0 folder) from either of them."""
    if (path / "mav0").is_dir():
        return path, path / "mav0"
    if path.name == "mav0" or (path / "cam0" / "data.csv").is_file():
        return path.parent, path
    raise DatasetError(f"{path}: EuRoC layout needs mav0/cam0/data.csv")


def _read_euroc_sensor(p: Path) -> Tuple[Intrinsics, np.ndarray]:
    if not p.is_file():
        raise DatasetError(f"EuRoC camera calibration not found: {p}")
    text = "\n".join(l for l in p.read_text().splitlines() if not l.startswith("%"))
    try:
        d = yaml.safe_load(text)
        fu, fv, cu, cv = [float(x) for x in d["intrinsics"]]
        w, h = [int(x) for x in d["resolution"]]
        model = str(d.get("distortion_model", "")).lower()
        coeffs = [float(x) for x in d.get("distortion_coefficients") or []]
        T_BS = np.asarray(d["T_BS"]["data"], dtype=np.float64).reshape(4, 4)
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{p}: not a EuRoC sensor.yaml (need intrinsics [fu fv cu cv], "
                           f"resolution, T_BS) ({e})") from None
    if model in ("radial-tangential", "radtan", "plumb_bob", ""):
        dm, coeffs = "plumb_bob", (coeffs + [0.0] * 5)[:5] if coeffs else []
    elif model in ("equidistant", "fisheye"):
        dm = "equidistant"
    else:
        raise DatasetError(f"{p}: unsupported distortion_model {model!r} "
                           "(radial-tangential or equidistant)")
    return Intrinsics(fu, fv, cu, cv, w, h, dm, coeffs), T_BS


def _open_euroc(root: Path, K, extra, camera: str = "cam0", **kw) -> FileDataset:
    seq, mav0 = _euroc_root(root)
    cam = mav0 / camera
    csv = cam / "data.csv"
    if not csv.is_file():
        raise DatasetError(f"{mav0}: EuRoC layout needs {camera}/data.csv")
    K_file, T_BS = _read_euroc_sensor(cam / "sensor.yaml")
    K = K or K_file
    kw.pop("depth_scale", None)
    entries = []
    for n, line in enumerate(csv.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            ns_str, fname = [x.strip() for x in s.split(",")[:2]]
            ns = int(ns_str)
        except ValueError:
            raise DatasetError(f"{csv}:{n}: expected 'timestamp_ns,filename', got {s[:80]!r}") \
                from None
        entries.append(_Entry(ns / 10**9, cam / "data" / fname))   # exact int -> float
    notes = []
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    gt_tum = sorted(seq.glob("groundtruth*.txt"))
    gt_file = gt_csv if gt_csv.is_file() else (gt_tum[0] if gt_tum else None)
    if gt_file is not None:
        ts, P = _read_gt(gt_file)
        poses = interpolate_poses(ts, P, [e.timestamp for e in entries])
        if all(p is None for p in poses):
            raise DatasetError(f"{gt_file}: no ground-truth sample within {ASSOC_TOL} s of any "
                               f"image stamp (images {entries[0].timestamp:.3f}.."
                               f"{entries[-1].timestamp:.3f}, ground truth {ts[0]:.3f}.."
                               f"{ts[-1]:.3f})")
        for e, p in zip(entries, poses):
            e.gt_pose = None if p is None else p @ T_BS   # body->world @ camera->body
        notes.append(f"ground truth: {gt_file.name} body poses x T_BS -> camera poses")
    name = seq.name if seq.name else mav0.name
    return FileDataset(name, "euroc", seq, K, entries, notes=notes, **kw)


def _open_posefolder(root: Path, K, extra, fps=None, **kw) -> FileDataset:
    cdir, pose_txt = root / "color", root / "pose.txt"
    if not cdir.is_dir() or not pose_txt.is_file():
        raise DatasetError(f"{root}: posefolder layout needs color/N.png and pose.txt")
    imgs = [p for p in _listdir_images(cdir)]
    if not imgs:
        raise DatasetError(f"{cdir}: no images")
    if K is None and (root / "intrinsics.yaml").is_file():
        K, extra = load_intrinsics(root / "intrinsics.yaml")
    if K is None:
        raise DatasetError(f"{root}: no intrinsics: pass --intrinsics FILE (or put "
                           "intrinsics.yaml in the folder)")
    a = _numeric_matrix_rows_any(pose_txt, (7, 8))
    if len(a) != len(imgs):
        raise DatasetError(f"{pose_txt} has {len(a)} poses but color/ has {len(imgs)} images")
    ddir = root / "depth"
    depths = None
    if ddir.is_dir():
        dl = _listdir_images(ddir)
        by_stem = {p.stem: p for p in dl}
        missing = [p.stem for p in imgs if p.stem not in by_stem]
        if missing:
            raise DatasetError(f"{root}: {len(imgs)} colour images but {len(dl)} depth images "
                               f"(no depth image for {missing[0]})")
        depths = [by_stem[p.stem] for p in imgs]
    scale = float(kw.pop("depth_scale", None) or extra.get("depth_scale", 5000.0))
    fps = fps or DEFAULT_FPS
    stamps = a[:, 0] if a.shape[1] == 8 else np.arange(len(a)) / fps
    P = pose_from_tq(a[:, -7:]).numpy()
    entries = [_Entry(float(stamps[i]), p, depths[i] if depths else None, P[i])
               for i, p in enumerate(imgs)]
    return FileDataset(root.name, "posefolder", root, K, entries,
                       depth_scale=scale if depths else None, **kw)


def _numeric_matrix_rows_any(path: Path, ncols) -> np.ndarray:
    try:
        a = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except ValueError as e:
        raise DatasetError(f"{path}: not a numeric table ({e})") from None
    if a.size == 0 or a.shape[1] not in ncols:
        raise DatasetError(f"{path}: expected rows of 'tx ty tz qx qy qz qw' (7 numbers, or 8 "
                           f"with a leading timestamp), found {a.shape[1] if a.size else 0}")
    return a


def _open_folder(root: Path, K, extra, fps=None, **kw) -> FileDataset:
    imgs = _listdir_images(root)
    if not imgs:
        raise DatasetError(f"{root}: no images ({', '.join(IMAGE_EXTS)}) in the folder")
    if K is None and (root / "intrinsics.yaml").is_file():
        K, extra = load_intrinsics(root / "intrinsics.yaml")
    if K is None:
        raise DatasetError(f"{root}: no intrinsics: pass --intrinsics FILE (or put "
                           "intrinsics.yaml in the folder)")
    kw.pop("depth_scale", None)
    stamps = [_numeric_stem(p) for p in imgs]
    notes = []
    if fps is None and all(s is not None for s in stamps) and len(set(stamps)) == len(stamps):
        order = np.argsort(stamps, kind="stable")
        imgs, stamps = [imgs[i] for i in order], [stamps[i] for i in order]
        notes.append("timestamps from the file names")
    else:
        fps = fps or DEFAULT_FPS
        stamps = [i / fps for i in range(len(imgs))]
        notes.append(f"timestamps: index / {fps:g} fps")
    entries = [_Entry(t, p) for t, p in zip(stamps, imgs)]
    return FileDataset(root.name, "folder", root, K, entries, notes=notes, **kw)


# --------------------------------------------------------------------- entry point
LAYOUTS = ("tum: rgb.txt [depth.txt groundtruth.txt]; replica: results/frame*.jpg + traj.txt; "
           "scannet: color/ depth/ pose/ intrinsic/; euroc: mav0/cam0/data.csv; "
           "posefolder: color/ [depth/] pose.txt; bag: metadata.yaml + .mcap; "
           "folder: image files; video: a video file")


def detect_format(path) -> str:
    """Name of the layout at ``path`` (one of FORMATS), or DatasetError naming what was expected."""
    p = Path(path)
    if not p.exists():
        raise DatasetError(f"dataset path not found: {p}")
    if p.is_file():
        suf = p.suffix.lower()
        if suf == ".mcap":
            return "bag"
        if suf in VIDEO_EXTS:
            return "video"
        if suf in IMAGE_EXTS or suf in (".txt", ".yaml", ".yml", ".csv", ".json"):
            raise DatasetError(f"{p} is a single file; give the dataset folder ({LAYOUTS})")
        cap = cv2.VideoCapture(str(p))
        ok = cap.isOpened() and cap.read()[0]
        cap.release()
        if ok:
            return "video"
        raise DatasetError(f"{p}: not a video cv2 can open and not a .mcap bag")
    if (p / "metadata.yaml").is_file():
        return "bag"
    if (p / "rgb.txt").is_file():
        return "tum"
    if (p / "results").is_dir() and any((p / "results").glob("frame*")):
        return "replica"
    if (p / "color").is_dir() and (p / "pose").is_dir() or (p / "intrinsic").is_dir():
        return "scannet"
    if (p / "mav0").is_dir() or p.name == "mav0" or (p / "cam0" / "data.csv").is_file():
        return "euroc"
    if (p / "color").is_dir() and (p / "pose.txt").is_file():
        return "posefolder"
    if _listdir_images(p):
        return "folder"
    raise DatasetError(f"{p}: unknown dataset layout; expected one of: {LAYOUTS}")


def open_dataset(path, fmt: str = "auto", intrinsics: Union[None, str, Path, Intrinsics] = None,
                 max_frames: Optional[int] = None, stride: int = 1, keep_mono: bool = False,
                 fps: Optional[float] = None, depth_scale: Optional[float] = None,
                 **options) -> Dataset:
    """Open a dataset of any supported layout (``fmt="auto"`` detects it).

    ``intrinsics``: Intrinsics or a YAML/JSON file; overrides the dataset's own.
    ``fps``: frame rate for layouts without timestamps (folder, replica, scannet,
    posefolder; default 30) and to override a video's stamps. ``depth_scale``: raw depth
    units per metre (overrides the format default and ``depth_scale`` in intrinsics YAML).
    ``options``: format-specific (``camera="cam1"`` for EuRoC, ``topics={...}`` for bags).
    """
    p = Path(path)
    if not p.exists():
        raise DatasetError(f"dataset path not found: {p}")
    if fmt == "auto":
        fmt = detect_format(p)
    if fmt not in FORMATS:
        raise DatasetError(f"unknown format {fmt!r}; use one of auto, {', '.join(FORMATS)}")
    if fmt == "bag":
        from splat_slam_ros.io.bagio import BagDataset
        return BagDataset(p, max_frames=max_frames, stride=stride, keep_mono=keep_mono,
                          **options)
    K, extra = _as_intrinsics(intrinsics)
    if fmt == "video":
        if not p.is_file():
            raise DatasetError(f"{p}: format 'video' needs a video file")
        if K is None:
            raise DatasetError(f"{p}: a video needs --intrinsics FILE (fx fy cx cy width height)")
        return VideoDataset(p, K, fps=fps, keep_mono=keep_mono, max_frames=max_frames,
                            stride=stride)
    if not p.is_dir():
        raise DatasetError(f"{p}: format '{fmt}' needs a folder")
    kw = dict(max_frames=max_frames, stride=stride, keep_mono=keep_mono, depth_scale=depth_scale)
    if fmt in ("replica", "scannet", "posefolder", "folder"):
        kw["fps"] = fps
    opener = {"tum": _open_tum, "replica": _open_replica, "scannet": _open_scannet,
              "euroc": _open_euroc, "posefolder": _open_posefolder, "folder": _open_folder}[fmt]
    return opener(p, K, extra, **kw, **options)
