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

from pathlib import Path
from typing import Optional, Union

import cv2

from splat_slam_ros.io.dataset_base import (ASSOC_TOL, DEFAULT_FPS, FORMATS, IMAGE_EXTS,
                                            INTERP_MAX_GAP, REPLICA_DEFAULT, TUM_DEFAULTS,
                                            VIDEO_EXTS, Dataset, DatasetError, FileDataset,
                                            VideoDataset, as_intrinsics, list_images,
                                            associate, interpolate_poses, load_intrinsics,
                                            ns_to_stamp, read_depth, read_image, stamp_to_ns)
from splat_slam_ros.io.dataset_formats import (_open_euroc, _open_folder, _open_posefolder,
                                               _open_replica, _open_scannet, _open_tum)
from splat_slam_ros.types import Intrinsics

__all__ = ["ASSOC_TOL", "DEFAULT_FPS", "FORMATS", "IMAGE_EXTS", "INTERP_MAX_GAP", "REPLICA_DEFAULT",
           "TUM_DEFAULTS", "VIDEO_EXTS", "Dataset", "DatasetError", "FileDataset",
           "VideoDataset", "associate", "interpolate_poses", "load_intrinsics", "ns_to_stamp",
           "read_depth", "read_image", "stamp_to_ns", "LAYOUTS", "detect_format", "open_dataset"]


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
    if list_images(p):
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
    ``options``: format-specific (``camera="cam1"`` for EuRoC, ``topics={"image": ...,
    "camera_info": ...}`` for bags: see ``bagio.camera_topics``).
    """
    p = Path(path)
    if not p.exists():
        raise DatasetError(f"dataset path not found: {p}")
    if fmt == "auto":
        fmt = detect_format(p)
    if fmt not in FORMATS:
        raise DatasetError(f"unknown format {fmt!r}; use one of auto, {', '.join(FORMATS)}")
    K, extra = as_intrinsics(intrinsics)
    if fmt == "bag":      # imported here: the mcap/zstd/lz4 readers cost 0.7 MB of RSS
        from splat_slam_ros.io.bagio import BagDataset
        return BagDataset(p, max_frames=max_frames, stride=stride, keep_mono=keep_mono,
                          intrinsics=K, **options)
    if options.get("topics"):
        raise DatasetError(f"{p}: --image-topic / --camera-info-topic apply to bags only "
                           f"(this input is '{fmt}')")
    options.pop("topics", None)
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


class FromFrame:
    """A dataset without its first ``start`` frames (``splat-slam-run --start-frame``): one
    sequence split into sessions. Frames keep their indices and stamps; the ground truth is
    that of the remaining frames. Anything else is the wrapped dataset's."""

    def __init__(self, dataset, start: int):
        n = len(dataset)
        if not 0 <= int(start) < n:
            raise DatasetError(f"--start-frame {start} is outside the input's frames "
                               f"(0 <= N < {n})")
        self._ds, self.start = dataset, int(start)
        self._first_stamp: Optional[float] = None

    def __getattr__(self, name):
        return getattr(self._ds, name)

    def __len__(self) -> int:
        return len(self._ds) - self.start

    def iter_frames(self, keep_mono: Optional[bool] = None, depth: bool = True):
        for i, f in enumerate(self._ds.iter_frames(keep_mono, depth)):
            if i >= self.start:
                if self._first_stamp is None:
                    self._first_stamp = float(f.timestamp)
                yield f

    def __iter__(self):
        return self.iter_frames()

    def info(self) -> dict:
        return dict(self._ds.info(), frames=len(self))

    def gt_trajectory(self):
        gt = self._ds.gt_trajectory()
        if gt is None:
            return None
        if self._first_stamp is None:
            for _ in self.iter_frames(depth=False):
                break
        keep = gt[0] >= self._first_stamp - 1e-6
        return gt[0][keep], gt[1][keep]
