"""Motion filter and keyframe selection by mean optical-flow magnitude (paper Sec. 3.1).

A frame becomes a keyframe candidate when the mean flow from the last keyframe
exceeds ``tracking.motion_filter_thresh``, fewer than ``tracking.max_keyframe_rate``
keyframes were made in the last second of stream time and the last one is at least
``tracking.min_keyframe_interval`` old (fast motion: a few keyframes per second, not one per
frame). Two candidates pass the rate budget: a frame whose mean flow is above
``keyframe_urgent_flow`` x the threshold ("fast", once the interval has passed; not counted)
and one whose confident cells fell to ``keyframe_urgent_valid`` x their typical fraction
("losing", at once and even below the threshold: the reference is renewed before the flow to
it fails; counted). The warm-up takes a keyframe at the threshold or when losing (without a
bound; its keyframes are not counted). After the local BA a candidate whose flow *induced by
the optimised poses and disparities* stays below the keyframe threshold tau
(``tracking.keyframe_thresh``) is dropped again. Both
thresholds are given in *reference* BA-grid pixels - those of the reference's setting (a
640x480 TUM camera, fx = 525, at 1/8: a BA focal length of 65.625 px) - and
scaled by the actual BA focal length (:func:`flow_scale`), so the same value
selects the same viewing-angle change at 320x240, 640x480 or 1200x680.
:func:`parallax` measures whether the first keyframes see enough translation to
initialise. Frames whose flow confidence collapses are reported as lost: fewer confident
cells than ``tracking.lost_min_valid``, or, on a view with little texture, than
``tracking.lost_rel_texture`` x the cells its texture could make confident at most.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np
import torch

from splat_slam_ros.geometry import se3_exp, se3_log
from splat_slam_ros.tracking.flow_frontend import mean_flow


REF_BA_FOCAL = 525.0 / 8.0        # BA-grid focal length the flow thresholds are given for


def flow_scale(intr) -> float:
    """Factor from reference BA pixels to this camera's BA pixels: (fx_ba + fy_ba) / 2 / 65.625."""
    return 0.5 * (float(intr[0]) + float(intr[1])) / REF_BA_FOCAL


def flow_correspondences(flow: torch.Tensor, weight: torch.Tensor, cell_weight: float = 0.2):
    """(src, dst) float32 (P, 2) BA-pixel positions of the cells whose mean weight exceeds
    ``cell_weight`` and whose flow (h, w, 2) stays inside the image."""
    h, w = flow.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    f = flow.detach().float().cpu().numpy()
    dst = np.stack([u + f[..., 0], v + f[..., 1]], -1)
    m = (weight.detach().float().cpu().numpy().mean(-1) > cell_weight) & \
        (dst[..., 0] >= 0) & (dst[..., 0] <= w - 1) & (dst[..., 1] >= 0) & (dst[..., 1] <= h - 1)
    return np.stack([u[m], v[m]], -1), dst[m]


def parallax(flow: torch.Tensor, weight: torch.Tensor, cell_weight: float = 0.2) -> float:
    """Upper-quartile flow residual (BA px) after the best (RANSAC) homography: the part of
    the motion that a pure rotation (or one dominant plane) cannot explain. 0 when too few
    confident cells."""
    src, dst = flow_correspondences(flow, weight, cell_weight)
    if len(src) < 16:
        return 0.0
    H, _ = cv2.findHomography(src, dst, cv2.RANSAC, 0.5)
    if H is None:
        return 0.0
    p = np.concatenate([src, np.ones((len(src), 1), np.float32)], 1) @ H.T
    p = p[:, :2] / np.where(np.abs(p[:, 2:]) < 1e-9, 1e-9, p[:, 2:])
    return float(np.percentile(np.linalg.norm(p - dst, axis=1), 75))


@dataclass
class FlowCheck:
    mean_flow: float        # BA pixels over confident cells
    valid_frac: float       # fraction of cells with a usable weight
    ok: bool                # flow trustworthy (not lost)


class MotionFilter:
    """Decides keyframe candidates and tracking loss from a flow (last keyframe -> frame)."""

    def __init__(self, thresh: float, min_valid_frac: float = 0.12, rel_valid_frac: float = 0.35,
                 cell_weight: float = 0.2, max_rate: float = 0.0, min_interval: float = 0.0,
                 urgent_flow: float = 2.0, urgent_valid: float = 0.7,
                 rel_texture: float = 0.0):
        self.thresh = float(thresh)
        self.max_rate = float(max_rate)             # keyframes in any second (0 = no bound)
        self.min_interval = float(min_interval)     # stream seconds
        self.urgent_flow = float(urgent_flow) * self.thresh
        self.urgent_valid = float(urgent_valid)
        self.min_valid_frac = min_valid_frac
        self.rel_valid_frac = rel_valid_frac
        self.rel_texture = float(rel_texture)
        self.cell_weight = cell_weight
        self._typical = None            # running median-ish of valid_frac on good frames

    def confident_fraction(self, weight: torch.Tensor) -> float:
        """Fraction of BA cells whose mean flow weight exceeds ``cell_weight``."""
        return float((weight.mean(-1) > self.cell_weight).float().mean())

    def min_valid(self, tex: Optional[np.ndarray] = None) -> float:
        """The confident-cell fraction below which a flow is lost. ``tex`` (h x w x 2, the
        reference image's texture factor per BA cell and axis, which bounds a cell's weight):
        on a view with little texture ``rel_texture`` x the fraction of cells it could make
        confident, when that is lower, but at least a quarter of ``min_valid_frac``."""
        need = self.min_valid_frac
        if tex is not None and self.rel_texture > 0:
            textured = float((np.asarray(tex).mean(-1) > self.cell_weight).mean())
            need = max(0.25 * need, min(need, self.rel_texture * textured))
        return need

    def check(self, flow: torch.Tensor, weight: torch.Tensor,
              tex: Optional[np.ndarray] = None) -> FlowCheck:
        """``tex``: the reference's texture factor (:meth:`min_valid`), None if unknown."""
        valid = self.confident_fraction(weight)
        mf = mean_flow(flow, weight, self.cell_weight)
        need = self.min_valid(tex)
        if self._typical is not None:
            need = max(need, self.rel_valid_frac * self._typical)
        ok = valid >= need
        if ok:
            self._typical = valid if self._typical is None else 0.9 * self._typical + 0.1 * valid
        return FlowCheck(mf, valid, ok)

    @property
    def typical_valid_frac(self) -> float:
        """Running mean of the confident-cell fraction over good frames (0 before the first)."""
        return 0.0 if self._typical is None else float(self._typical)

    def losing(self, fc: FlowCheck) -> bool:
        """The view is leaving the last keyframe: the confident cells down to
        ``keyframe_urgent_valid`` x their typical fraction."""
        return fc.valid_frac < self.urgent_valid * self.typical_valid_frac

    def candidate(self, fc: FlowCheck, since_kf: Optional[float] = None,
                  recent: int = 0) -> Optional[str]:
        """Why the frame is a keyframe candidate, or None. ``since_kf``: stream seconds since
        the last keyframe (None: the warm-up, no rate bound); ``recent``: keyframes of the
        budget in the last second. ``"losing"``: the confident cells are dropping (at once,
        even below the threshold); ``"fast"``: mean flow above ``keyframe_urgent_flow`` x the
        threshold (past the rate budget, not the interval); ``"threshold"``: enough flow and
        the rate bound allows one; ``"warmup"``: enough flow, no bound."""
        if not fc.ok:
            return None
        if since_kf is not None and self.losing(fc):
            return "losing"
        if fc.mean_flow < self.thresh:
            return None
        if since_kf is None:
            return "warmup"
        if since_kf < self.min_interval:
            return None
        if fc.mean_flow >= self.urgent_flow:
            return "fast"
        return None if 0 < self.max_rate <= recent else "threshold"

    def is_candidate(self, fc: FlowCheck, since_kf: Optional[float] = None,
                     recent: int = 0) -> bool:
        """:meth:`candidate` is not None."""
        return self.candidate(fc, since_kf, recent) is not None


def predict_pose(last_pose: torch.Tensor, velocity: torch.Tensor, spacing, index: int):
    """Constant velocity across the frames since the last pose: ``velocity`` (the motion of
    the last tracked step, ``spacing`` = (its first, its last frame index)) scaled to the
    frames from ``spacing[1]`` to ``index`` (frames skipped on live input, a gap)."""
    prev, last = spacing
    if prev is None or last is None or last <= prev or index <= last:
        return last_pose @ velocity
    s = (index - last) / (last - prev)
    return last_pose @ se3_exp(se3_log(velocity) * s)
