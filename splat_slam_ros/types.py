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
from typing import List, Optional, Sequence

import numpy as np


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

    def scaled(self, sx: float, sy: Optional[float] = None) -> "Intrinsics":
        """Intrinsics of the image resized by (sx, sy) (pixel-centre convention)."""
        sy = sx if sy is None else sy
        return Intrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                          (self.cy + 0.5) * sy - 0.5, int(round(self.width * sx)),
                          int(round(self.height * sy)), self.distortion_model,
                          list(self.distortion))


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
class UpdateEvent:
    """A change of keyframe poses/disparities made by BA, loop closure or global BA.

    This is what ``splat_slam_msgs/PoseGraphUpdate`` carries between nodes.
    """
    seq: int                                 # monotonically increasing
    reason: str                              # one of REASONS
    kf_ids: Sequence[int]
    poses: np.ndarray                        # N x 4 x 4 camera-to-world
    disparities: Optional[np.ndarray] = None  # N x h x w (BA resolution) or None = poses only

    REASONS = ("local_ba", "loop_closure", "global_ba", "final")
