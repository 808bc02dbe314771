"""The keyframe store of the tracker and of the loop closer: one record per keyframe.

Each keyframe has its BA state (camera-to-world pose ``omega`` and BA-grid disparity ``d``,
the variables of Eq. 1), its source frame, and the data the flow front end and the graph
still need (prepared image for new flow edges, full-size image until the keyframe is
published, flow confidence). Ids are kept sorted (keyframe ids only grow).
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Any, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple

import numpy as np
import torch

from splat_slam_ros.geometry import se3_inverse, se3_log
from splat_slam_ros.types import UpdateEvent


# why a keyframe was made (KeyframeState.cause): the warm-up's, the motion threshold's, fast
# motion's and a view leaving the last keyframe's (MotionFilter.candidate), the last frame's at
# the end of the input, loaded from a saved session, or the frame before one whose flow to the
# last keyframe failed (TrackerFrontend._retreat)
KEYFRAME_CAUSES = ("warmup", "threshold", "fast", "losing", "final", "loaded", "promoted")
# counted in tracking.max_keyframe_rate
BUDGET_CAUSES = ("threshold", "losing", "promoted")


@dataclass
class KeyframeState:
    pose: torch.Tensor                   # (4, 4) float64 camera-to-world
    disp: torch.Tensor                   # (h, w) float32 BA-grid disparity (inverse depth)
    frame_index: int
    timestamp: float
    prep: Any = None                     # flow front end's prepared image (None once dropped)
    image: Optional[np.ndarray] = None   # full-size RGB, kept until published (None after)
    conf: Optional[torch.Tensor] = None  # (h, w) flow confidence of the keyframe's edges
    cause: str = "warmup"                # one of KEYFRAME_CAUSES


class KeyframeSet:
    """Keyframes by id, in id order; ``ks[k]`` is the :class:`KeyframeState` of ``k``."""

    def __init__(self):
        self._kf: Dict[int, KeyframeState] = {}
        self._ids: List[int] = []

    # ------------------------------------------------------------ container
    def __contains__(self, k) -> bool:
        return k in self._kf

    def __getitem__(self, k: int) -> KeyframeState:
        return self._kf[k]

    def __len__(self) -> int:
        return len(self._ids)

    def __iter__(self) -> Iterator[int]:
        return iter(list(self._ids))

    @property
    def ids(self) -> List[int]:
        """All keyframe ids, ascending (a copy)."""
        return list(self._ids)

    def add(self, k: int, state: KeyframeState) -> KeyframeState:
        k = int(k)
        if k not in self._kf:
            bisect.insort(self._ids, k)
        self._kf[k] = state
        return state

    def remove(self, k: int) -> None:
        if self._kf.pop(k, None) is not None:
            self._ids.remove(k)

    def clear(self) -> None:
        self._kf.clear()
        self._ids.clear()

    # ------------------------------------------------------------ views
    def with_prep(self) -> List[int]:
        """Ids whose prepared image is still kept (flow edges can be measured)."""
        return [k for k in self._ids if self._kf[k].prep is not None]

    def with_image(self) -> List[int]:
        """Ids whose full-size image is still kept (not published yet)."""
        return [k for k in self._ids if self._kf[k].image is not None]

    def drop_prep(self, k: int) -> None:
        if k in self._kf:
            self._kf[k].prep = None

    def drop_image(self, k: int) -> None:
        if k in self._kf:
            self._kf[k].image = None

    def stack(self, ids: Sequence[int]) -> Tuple[torch.Tensor, torch.Tensor]:
        """(N, 4, 4) poses and (N, h, w) disparities of ``ids`` (the BA variables of Eq. 1)."""
        return (torch.stack([self._kf[k].pose for k in ids]),
                torch.stack([self._kf[k].disp for k in ids]))

    def write_back(self, ids: Sequence[int], poses: torch.Tensor, disps: torch.Tensor) -> None:
        """Store optimised poses / disparities of ``ids`` (rows in the same order)."""
        for n, k in enumerate(ids):
            self._kf[k].pose = poses[n]
            self._kf[k].disp = disps[n]

    def snapshot(self, ids: Iterable[int]) -> Dict[int, Tuple[torch.Tensor, torch.Tensor]]:
        """{id: (pose, disparity)} copies, to measure what an optimisation changed."""
        return {k: (self._kf[k].pose.clone(), self._kf[k].disp.clone()) for k in ids}

    def trajectory(self, ids: Sequence[int]) -> Tuple[np.ndarray, np.ndarray]:
        """(timestamps, camera-to-world poses) of ``ids`` as numpy."""
        return (np.array([self._kf[k].timestamp for k in ids]),
                np.stack([self._kf[k].pose.cpu().numpy() for k in ids]) if len(ids) else
                np.zeros((0, 4, 4)))

    def changed(self, before: Dict[int, Tuple[torch.Tensor, torch.Tensor]], pose_thresh: float,
                disp_thresh: float) -> List[int]:
        """Ids of ``before`` (a :meth:`snapshot`) that moved by more than ``pose_thresh``
        (rotation in rad, translation relative to the mean depth) or whose mean disparity
        changed by more than ``disp_thresh`` (relative): what an update event must carry."""
        ids = [k for k in before if k in self._kf]
        if not ids:
            return []
        # one batched log over every keyframe (a global BA asks about all of them)
        P0 = torch.stack([before[k][0] for k in ids])
        P1 = torch.stack([self._kf[k].pose for k in ids])
        D0 = torch.stack([before[k][1] for k in ids])
        D1 = torch.stack([self._kf[k].disp for k in ids])
        dxi = se3_log(se3_inverse(P0) @ P1)
        scale = 1.0 / D1.flatten(1).mean(1).clamp_min(1e-6)
        moved = (dxi[:, :3].norm(dim=1) > pose_thresh * scale) | \
            (dxi[:, 3:].norm(dim=1) > pose_thresh)
        dd = (D1 - D0).abs().flatten(1).mean(1) / D0.abs().flatten(1).mean(1).clamp_min(1e-9)
        return [k for k, m in zip(ids, (moved | (dd > disp_thresh)).tolist()) if m]

    def update_event(self, seq: int, reason: str, ids: Sequence[int]) -> UpdateEvent:
        """An :class:`UpdateEvent` with the current poses / disparities of ``ids``."""
        return UpdateEvent(seq=seq, reason=reason, kf_ids=list(ids),
                           poses=np.stack([self._kf[k].pose.cpu().numpy() for k in ids]),
                           disparities=np.stack([self._kf[k].disp.cpu().numpy()
                                                 for k in ids]).astype(np.float32))
