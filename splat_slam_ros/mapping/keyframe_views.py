"""Files of the per-keyframe views beside a run's renders, and the map's history rows.

For every mapped keyframe the renders folder holds (written by
``evaluation.rendering.write_keyframe_views``):

- ``kf_<id>.png``        rendered colour (with the keyframe's learned exposure, Eq. 11)
- ``kf_<id>_input.png``  the keyframe's input image (what the map was fitted to)
- ``kf_<id>_depth.png``  rendered depth, 16-bit, ``depth_scale`` units per map unit
  (:func:`encode_depth`, :func:`depth_scale_for`)
- ``kf_<id>_proxy.png``  the proxy depth the mapper used (0 = no depth), same encoding

and ``keyframes.json`` (:data:`KEYFRAMES_JSON`): per keyframe PSNR, SSIM, rendered-vs-proxy
depth L1 (map units), depth L1 against ground-truth depth (cm) when given, rendered
coverage; plus the mapper's history (:func:`history_entry`: one row per keyframe offered:
Gaussians, mapped keyframes, time) and the final map statistics. ``splat_slam_ros.report``
reads these files only.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

KEYFRAMES_JSON = "keyframes.json"


def history_entry(stats: dict, timestamp: Optional[float]) -> dict:
    """One row of ``Mapper.history`` from the statistics ``Mapper.add_keyframe`` returns."""
    return {"kf_id": int(stats["kf_id"]),
            "timestamp": None if timestamp is None else float(timestamp),
            "mapped": bool(stats["mapped"]), "gaussians": int(stats["gaussians"]),
            "keyframes": int(stats["keyframes"]), "iterations": int(stats["iterations"]),
            "steps": int(stats.get("steps", 0)), "steps_skipped": int(stats.get("steps_skipped", 0)),
            "ms": round(float(stats["last_ms"]), 2)}


def depth_scale_for(max_depth: float) -> float:
    """16-bit depth encoding: 1000 steps per map unit unless the scene is deeper than 65."""
    if not np.isfinite(max_depth) or max_depth <= 0:
        return 1000.0
    return float(min(1000.0, np.floor(65535.0 / max_depth)))


def encode_depth(depth: torch.Tensor, scale: float) -> np.ndarray:
    """16-bit depth image, ``scale`` steps per map unit (0: missing / non-finite)."""
    d = torch.nan_to_num(depth.float(), nan=0.0, posinf=0.0).clamp_min(0)
    return (d * scale + 0.5).clamp(0, 65535).to(torch.int32).cpu().numpy().astype(np.uint16)
