"""Keyframe selection and the local mapping window by covisibility (MonoGS rules).

Supplementary "Keyframe Selection and Local Windowing". A Gaussian is *visible* from a
keyframe when it took part in rasterising that view before the accumulated transmittance
fell below 0.5 (the rasterizer's ``visible`` output). With G_v^i the visible set of i:

    IOU_cov(i, j) = |G_v^i ∩ G_v^j| / |G_v^i ∪ G_v^j|          (supp. Eq. 16)
    OC_cov(i, j)  = |G_v^i ∩ G_v^j| / min(|G_v^i|, |G_v^j|)    (supp. Eq. 17)

- a tracker keyframe i is mapped (joins the window) if, with j the last mapped keyframe,
  IOU_cov(i, j) < k_fcov or the camera moved more than k_fm x median depth of i;
- a window keyframe j is dropped when OC_cov(i, j) < k_fc with i the newly added one (the
  newest two are always kept);
- if the window is still larger than its size, the most redundant keyframe goes (MonoGS:
  the one closest to the other window keyframes relative to its distance from the newest).

Visible sets are stored as Gaussian uids (stable under pruning and densification).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np
import torch


def _inter(a: torch.Tensor, b: torch.Tensor) -> int:
    if a.numel() == 0 or b.numel() == 0:
        return 0
    return int(torch.isin(a, b).sum())


def covisibility_iou(a: torch.Tensor, b: torch.Tensor) -> float:
    """Supp. Eq. 16 on two sets of Gaussian uids (unique values)."""
    i = _inter(a, b)
    u = a.numel() + b.numel() - i
    return i / u if u > 0 else 0.0


def overlap_coefficient(a: torch.Tensor, b: torch.Tensor) -> float:
    """Supp. Eq. 17 on two sets of Gaussian uids (unique values)."""
    m = min(a.numel(), b.numel())
    return _inter(a, b) / m if m > 0 else 0.0


@dataclass
class KeyframeDecision:
    mapped: bool
    reason: str            # "first", "covisibility", "translation", "redundant"
    iou: float
    translation: float     # metres between camera centres
    threshold: float       # k_fm x median depth


class KeyframeWindow:
    """The set of keyframes optimised together, newest first."""

    KEEP_NEWEST = 2

    def __init__(self, size: int = 8, k_fcov: float = 0.90, k_fm: float = 0.08,
                 k_fc: float = 0.3):
        if size < 1:
            raise ValueError("keyframe window size must be >= 1")
        self.size = int(size)
        self.k_fcov = float(k_fcov)
        self.k_fm = float(k_fm)
        self.k_fc = float(k_fc)
        self.window: List[int] = []
        self.visibility: Dict[int, torch.Tensor] = {}
        # the map's seeding generation each visible set was taken at (Mapper.seedings): a set
        # older than the newest seeding lacks its Gaussians (visibility pruning refreshes it)
        self.visibility_at: Dict[int, int] = {}
        self.last: Optional[int] = None            # last mapped keyframe

    def __len__(self) -> int:
        return len(self.window)

    @property
    def full(self) -> bool:
        return len(self.window) >= self.size

    def set_visibility(self, kf_id: int, uids: torch.Tensor, at: int = -1) -> None:
        """``uids``: the Gaussians visible from keyframe ``kf_id`` at seeding generation ``at``."""
        self.visibility[kf_id] = uids.detach().flatten().unique()
        self.visibility_at[kf_id] = int(at)

    def stale(self, generation: int) -> List[int]:
        """Window keyframes whose visible set was taken before seeding generation ``generation``."""
        return [j for j in self.window if self.visibility_at.get(j, -1) < generation]

    def forget(self, kf_id: int) -> None:
        self.visibility.pop(kf_id, None)
        self.visibility_at.pop(kf_id, None)

    def drop(self, kf_id: int, successor: int) -> None:
        """A keyframe leaves the map (merged into ``successor``): out of the window; if it was
        the last mapped one, the newest window keyframe (else ``successor``) takes its place."""
        if kf_id in self.window:
            self.window.remove(kf_id)
        self.forget(kf_id)
        if self.last == kf_id:
            self.last = self.window[0] if self.window else successor

    # ----------------------------------------------------------- selection
    def decide(self, visible_uids: torch.Tensor, pose: np.ndarray, median_depth: float,
               poses: Dict[int, np.ndarray]) -> KeyframeDecision:
        """Should a new keyframe (visible set from rendering the map at ``pose``) be mapped?"""
        if self.last is None:
            return KeyframeDecision(True, "first", 0.0, 0.0, 0.0)
        last_vis = self.visibility.get(self.last, visible_uids.new_zeros(0))
        iou = covisibility_iou(visible_uids.unique(), last_vis)
        t = float(np.linalg.norm(np.asarray(pose)[:3, 3] - np.asarray(poses[self.last])[:3, 3]))
        thr = self.k_fm * float(median_depth)
        if t > thr:
            return KeyframeDecision(True, "translation", iou, t, thr)
        if iou < self.k_fcov:
            return KeyframeDecision(True, "covisibility", iou, t, thr)
        return KeyframeDecision(False, "redundant", iou, t, thr)

    # -------------------------------------------------------------- window
    def add(self, kf_id: int, visible_uids: torch.Tensor,
            poses: Dict[int, np.ndarray], at: int = -1) -> List[int]:
        """Insert a newly mapped keyframe (``visible_uids`` taken at seeding generation
        ``at``); returns the keyframes that left the window."""
        self.set_visibility(kf_id, visible_uids, at)
        self.window.insert(0, kf_id)
        self.last = kf_id
        new_vis = self.visibility[kf_id]
        removed: List[int] = []
        # OC cutoff against the new keyframe (the two newest are kept)
        for j in list(self.window[self.KEEP_NEWEST:]):
            vj = self.visibility.get(j, new_vis.new_zeros(0))
            if overlap_coefficient(new_vis, vj) < self.k_fc:
                self.window.remove(j)
                removed.append(j)
        # still too many: drop the most redundant one (MonoGS distance heuristic)
        while len(self.window) > self.size:
            j = self._most_redundant(poses)
            self.window.remove(j)
            removed.append(j)
        for j in removed:              # visible sets are only needed inside the window
            self.forget(j)
        return removed

    def _most_redundant(self, poses: Dict[int, np.ndarray]) -> int:
        cands = self.window[self.KEEP_NEWEST:]
        c0 = np.asarray(poses[self.window[0]])[:3, 3]
        centres = {k: np.asarray(poses[k])[:3, 3] for k in cands}
        score = []
        for i in cands:
            inv = sum(1.0 / (np.linalg.norm(centres[i] - centres[j]) + 1e-6)
                      for j in cands if j != i)
            score.append(np.sqrt(np.linalg.norm(centres[i] - c0)) * inv)
        return cands[int(np.argmax(score))]
