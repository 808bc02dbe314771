"""Core data types shared by every stage, the readers and the ROS nodes.

Conventions (used everywhere in the project):
- Images are numpy ``uint8`` arrays, H x W x 3 in RGB order (mono inputs are
  expanded to 3 channels by the readers unless asked otherwise).
- Depth is metres, ``float32`` H x W, 0 (or non-finite) where missing.
- Poses are camera-to-world 4x4 matrices (float64 numpy or torch), camera
  frame x right, y down, z forward (OpenCV). TUM files store the same pose as
  ``tx ty tz qx qy qz qw``.
- Timestamps are seconds (float) in the dataset's clock.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import yaml


class DatasetError(ValueError):
    """A dataset or bag is missing, malformed or inconsistent (one-line, user-facing message)."""


class IntrinsicsError(ValueError):
    """An intrinsics file is missing, unreadable or incomplete."""


@dataclass
class Intrinsics:
    """Pinhole intrinsics (pixels) plus optional distortion.

    ``distortion_model`` follows sensor_msgs/CameraInfo: ``plumb_bob`` (OpenCV
    k1 k2 p1 p2 k3) or ``equidistant`` (k1..k4); empty ``distortion`` = none.
    """
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion_model: str = "plumb_bob"
    distortion: List[float] = field(default_factory=list)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.distortion)

    def as_vector(self) -> np.ndarray:
        return np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float64)

    # ------------------------------------------------------------ YAML I/O
    def to_dict(self) -> dict:
        """``fx fy cx cy width height distortion_model distortion`` as plain Python values."""
        return dict(fx=float(self.fx), fy=float(self.fy), cx=float(self.cx), cy=float(self.cy),
                    width=int(self.width), height=int(self.height),
                    distortion_model=self.distortion_model,
                    distortion=[float(x) for x in self.distortion])

    @staticmethod
    def from_dict(d: dict) -> "Intrinsics":
        """The inverse of :meth:`to_dict` (distortion optional); KeyError / TypeError /
        ValueError when a value is missing or not a number."""
        return Intrinsics(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                          int(d["width"]), int(d["height"]),
                          str(d.get("distortion_model", "plumb_bob")),
                          [float(x) for x in (d.get("distortion") or [])])

    def to_yaml(self, path, **extra) -> None:
        """Write :meth:`to_dict` (+ extra keys) as YAML."""
        Path(path).write_text(yaml.safe_dump({**self.to_dict(), **extra}, sort_keys=False))

    @staticmethod
    def from_yaml(path) -> "Intrinsics":
        """Read our intrinsics YAML, or a ROS camera_calibration YAML (camera_matrix: data:)."""
        p = Path(path)
        if not p.is_file():
            raise IntrinsicsError(f"intrinsics file not found: {p}")
        try:
            d = yaml.safe_load(p.read_text())
        except yaml.YAMLError as e:
            raise IntrinsicsError(f"intrinsics file {p} is not valid YAML: {e}") from None
        if not isinstance(d, dict):
            raise IntrinsicsError(f"intrinsics file {p} must hold a mapping")
        try:
            if "camera_matrix" in d:   # ROS camera_calibration format
                k = d["camera_matrix"]["data"]
                dist = d.get("distortion_coefficients", {}).get("data", []) or []
                return Intrinsics(float(k[0]), float(k[4]), float(k[2]), float(k[5]),
                                  int(d["image_width"]), int(d["image_height"]),
                                  d.get("distortion_model", "plumb_bob"),
                                  [float(x) for x in dist])
            return Intrinsics.from_dict(d)
        except (KeyError, TypeError, IndexError, ValueError) as e:
            raise IntrinsicsError(
                f"intrinsics file {p} lacks a valid entry ({e}); expected keys fx, fy, cx, cy, "
                "width, height [, distortion_model, distortion] or a ROS camera_info YAML") from None

    def scaled(self, sx: float, sy: Optional[float] = None) -> "Intrinsics":
        """Intrinsics of the image resized by (sx, sy) (pixel-centre convention)."""
        sy = sx if sy is None else sy
        return Intrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                          (self.cy + 0.5) * sy - 0.5, int(round(self.width * sx)),
                          int(round(self.height * sy)), self.distortion_model,
                          list(self.distortion))

    def resized(self, width: int, height: int) -> "Intrinsics":
        """Intrinsics of the image resized to ``width`` x ``height`` (see :meth:`scaled`)."""
        return self.scaled(width / self.width, height / self.height)


@dataclass
class Frame:
    """One input camera frame as yielded by every reader (dataset or bag)."""
    index: int
    timestamp: float
    image: np.ndarray                       # H x W x 3 uint8 RGB (or H x W mono8 when kept)
    intrinsics: Intrinsics
    gt_pose: Optional[np.ndarray] = None    # 4x4 camera-to-world, evaluation only
    gt_depth: Optional[np.ndarray] = None   # H x W float32 metres, evaluation only


@dataclass
class KeyframeData:
    """A keyframe as the tracker hands it on (what ``splat_slam_msgs/Keyframe`` carries).

    ``image``/``intrinsics`` are at the mapping size (``camera.*``); ``disparity`` and
    ``confidence`` at the tracker's BA grid (tracking image / ``tracking.ba_downsample``,
    the tracking image may be larger: ``tracking.max_pixels``).
    """
    kf_id: int
    frame_index: int
    timestamp: float
    pose: np.ndarray                          # 4x4 camera-to-world (map frame)
    image: np.ndarray                         # H x W x 3 uint8 RGB
    intrinsics: Intrinsics                    # of ``image``
    disparity: np.ndarray                     # h x w float32, 1/m (scale of the map)
    confidence: np.ndarray                    # h x w float32 in [0, 1]
    mono_depth: Optional[np.ndarray] = None   # H x W float32 relative depth, optional
    # Keyframes published together (the end of the tracker's warm-up) form one batch: the
    # same batch_id (the first one's kf_id), batch_size of them. Consumers process a batch
    # as a whole, so that each keyframe sees the others (Eq. 6 views, loop candidates).
    batch_id: int = -1                        # -1: a batch of its own
    batch_size: int = 1


@dataclass
class UpdateEvent:
    """A change of keyframe poses/disparities made by BA, loop closure or global BA.

    This is what ``splat_slam_msgs/PoseGraphUpdate`` carries between nodes. Each source
    numbers its updates in its own range (TRACKER_SEQ_START.., LOOP_SEQ_START..), strictly
    increasing, so a consumer recognises a replayed update by ``seq <= last seen``.
    """
    seq: int                                 # strictly increasing per source
    reason: str                              # one of REASONS
    kf_ids: Sequence[int]
    poses: np.ndarray                        # N x 4 x 4 camera-to-world
    disparities: Optional[np.ndarray] = None  # N x h x w (BA resolution) or None = poses only

    REASONS = ("local_ba", "loop_closure", "global_ba", "final")

    @property
    def source(self) -> str:
        return update_source(self.reason)


def update_source(reason: str) -> str:
    """Who makes updates of ``reason``: ``"tracker"`` (local BA) or ``"loop"`` (loop closure,
    global BA, final)."""
    return "tracker" if reason in TRACKER_REASONS else "loop"


# Update sequence numbers: the tracker's from 1, the loop closer's from 1e9 (0 = none).
TRACKER_SEQ_START = 1
LOOP_SEQ_START = 1_000_000_000
TRACKER_REASONS = ("local_ba",)
LOOP_REASONS = ("loop_closure", "global_ba", "final")


@dataclass
class ProxyDepth:
    """Proxy depth of one keyframe as the depth stage hands it on (``splat_slam_msgs/ProxyDepth``).

    ``revision`` counts the depths sent for this keyframe (0 = the first); a consumer applies
    a ProxyDepth only if its revision is newer than the last one it took for that keyframe.
    """
    kf_id: int
    depth: np.ndarray           # H x W float32 metres, 0 = none
    source: np.ndarray          # H x W uint8: SOURCE_* below
    pose: np.ndarray            # 4x4 camera-to-world the depth was computed with
    update_seq: int = 0         # PoseGraphUpdate.seq it reflects, 0 for a new keyframe
    is_update: bool = False     # replaces an earlier depth of the same keyframe
    timestamp: float = 0.0      # keyframe image stamp, seconds
    revision: int = 0

    SOURCE_EMPTY = 0
    SOURCE_MULTIVIEW = 1
    SOURCE_MONO = 2
    SOURCE_BA = 3               # BA-grid depth in a multi-view hole (no mono model)

    @property
    def valid(self) -> np.ndarray:
        return np.asarray(self.source) > 0

    def depth_weight(self, ba_weight: float) -> np.ndarray:
        """The mapper's per-pixel depth-loss weight: 1 where the depth is multi-view or mono,
        ``ba_weight`` where it is the BA depth filling a hole, 0 where there is none (a bool
        mask when no pixel is BA-filled or ``ba_weight`` is 1)."""
        s = np.asarray(self.source)
        ba = s == self.SOURCE_BA
        if ba_weight == 1.0 or not ba.any():
            return s > 0
        return np.where(ba, np.float32(ba_weight), (s > 0).astype(np.float32))


@dataclass
class TrackStep:
    """What :meth:`Tracker.track` returns for one input frame."""
    frame_index: int
    timestamp: float
    is_keyframe: bool
    kf_id: Optional[int]
    pose: np.ndarray                         # 4x4 camera-to-world, current estimate
    events: List[UpdateEvent] = field(default_factory=list)
    keyframe: Optional[KeyframeData] = None  # the newest keyframe published this step
    lost: bool = False
    # every keyframe published this step (usually 0 or 1; the end of the warm-up
    # publishes all warm-up keyframes at once) - consumers should iterate this
    keyframes: List[KeyframeData] = field(default_factory=list)
    initialized: bool = True
    info: Dict[str, float] = field(default_factory=dict)


@dataclass
class TrackingResult:
    timestamps: np.ndarray            # full trajectory
    poses: np.ndarray                 # (N, 4, 4) camera-to-world
    kf_timestamps: np.ndarray
    kf_poses: np.ndarray
    kf_ids: List[int]
    events: List[UpdateEvent]
    timings: Dict[str, float]
    n_frames: int
    n_keyframes: int
    n_lost: int
    wall_s: float
