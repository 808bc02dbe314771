"""What the mapper takes in: a mapped keyframe's record and the checks of a keyframe's
image, proxy depth (with its validity mask or depth-loss weights) and pose."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional, Tuple

import numpy as np
import torch


class MapError(ValueError):
    """A user-facing mapping mistake (bad input shapes, missing poses/depth, bad file)."""


@dataclass
class MappedKeyframe:
    kf_id: int
    index: int                      # order of mapping (0 = first)
    timestamp: float
    pose: np.ndarray                # 4x4 camera-to-world (float64), current estimate
    image: torch.Tensor             # (H, W, 3) uint8
    depth: torch.Tensor             # (H, W) float32 proxy depth, 0 where invalid
    valid: torch.Tensor             # (H, W) bool
    exposure: torch.Tensor          # (2,) (log a, b): colour a * C + b (Eq. 11)
    weight: Optional[torch.Tensor] = None   # (H, W) depth-loss weight; None: 1 where valid


def lattice_view(kf: MappedKeyframe, n: int, dx: int, dy: int) -> MappedKeyframe:
    """The keyframe's pixels (n i + dx, n j + dy) (views, no copies); the same exposure
    tensor, so a loss on the lattice trains the keyframe's exposure."""
    def sub(t):
        return None if t is None else t[dy::n, dx::n]
    return replace(kf, image=sub(kf.image), depth=sub(kf.depth), valid=sub(kf.valid),
                   weight=sub(kf.weight))


def check_keyframe_inputs(image, depth, valid, W: int, H: int, device
                          ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                     Optional[torch.Tensor]]:
    """(image uint8 (H,W,3), depth (0 where invalid), valid bool, weight or None) on
    ``device``. ``valid``: None, a bool mask, or float depth-loss weights in [0, 1] (0 = no
    depth; ``weight`` is None when they are all 1)."""
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, -1)
    if image.shape != (H, W, 3):
        raise MapError(f"keyframe image is {image.shape}, the mapper's intrinsics are for "
                       f"{W}x{H}x3")
    if image.dtype != np.uint8:
        raise MapError(f"keyframe image must be uint8 RGB, got {image.dtype}")
    depth = np.asarray(depth, dtype=np.float32)
    if depth.shape != (H, W):
        raise MapError(f"proxy depth is {depth.shape}, expected {(H, W)}")
    ok = np.isfinite(depth) & (depth > 0)
    weight = None
    if valid is not None:
        valid = np.asarray(valid)
        if valid.shape != depth.shape:
            raise MapError(f"depth validity mask is {valid.shape}, expected {depth.shape}")
        if valid.dtype != bool:                     # per-pixel weights in [0, 1]
            w = np.clip(np.nan_to_num(valid.astype(np.float32)), 0.0, 1.0)
            ok &= w > 0
            if (w[ok] < 1).any():
                weight = torch.from_numpy(np.where(ok, w, 0).astype(np.float32)).to(device)
        else:
            ok &= valid
    return (torch.from_numpy(np.ascontiguousarray(image)).to(device),
            torch.from_numpy(np.where(ok, depth, 0).astype(np.float32)).to(device),
            torch.from_numpy(ok).to(device), weight)


def check_pose(pose) -> np.ndarray:
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise MapError(f"pose must be a finite 4x4 camera-to-world matrix, got {pose.shape}")
    return pose
