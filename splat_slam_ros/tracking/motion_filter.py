"""Motion filter and keyframe selection by mean optical-flow magnitude (paper Sec. 3.1).

A frame becomes a keyframe candidate when the mean flow from the last keyframe
exceeds ``tracking.motion_filter_thresh``; after the local BA a candidate whose
flow *induced by the optimised poses and disparities* stays below the keyframe
threshold tau (``tracking.keyframe_thresh``) is dropped again. Both thresholds
are in BA-grid pixels (1/8 of the tracking image by default), as in the
reference. Frames whose flow confidence collapses are reported as lost.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from splat_slam_ros.tracking.flow_frontend import mean_flow


@dataclass
class FlowCheck:
    mean_flow: float        # BA pixels over confident cells
    valid_frac: float       # fraction of cells with a usable weight
    ok: bool                # flow trustworthy (not lost)


class MotionFilter:
    """Decides keyframe candidates and tracking loss from a flow (last keyframe -> frame)."""

    def __init__(self, thresh: float, min_valid_frac: float = 0.12, rel_valid_frac: float = 0.35,
                 cell_weight: float = 0.2):
        self.thresh = float(thresh)
        self.min_valid_frac = min_valid_frac
        self.rel_valid_frac = rel_valid_frac
        self.cell_weight = cell_weight
        self._typical = None            # running median-ish of valid_frac on good frames

    def check(self, flow: torch.Tensor, weight: torch.Tensor) -> FlowCheck:
        wm = weight.mean(-1)
        valid = float((wm > self.cell_weight).float().mean())
        mf = mean_flow(flow, weight, self.cell_weight)
        need = self.min_valid_frac
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

    def is_candidate(self, fc: FlowCheck) -> bool:
        return fc.ok and fc.mean_flow >= self.thresh
