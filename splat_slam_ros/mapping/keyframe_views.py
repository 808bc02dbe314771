"""Per-keyframe views and the map's history, written beside the renders for the run report.

For every mapped keyframe ``write_keyframe_views`` stores, in the renders folder:

- ``kf_<id>.png``        rendered colour (with the keyframe's learned exposure, Eq. 11)
- ``kf_<id>_input.png``  the keyframe's input image (what the map was fitted to)
- ``kf_<id>_depth.png``  rendered depth, 16-bit, ``depth_scale`` units per map unit
- ``kf_<id>_proxy.png``  the proxy depth the mapper used (0 = no depth), same encoding

and ``keyframes.json``: per keyframe PSNR, SSIM, rendered-vs-proxy depth L1 (map units),
depth L1 against ground-truth depth (cm) when given, rendered coverage; plus the mapper's
history (one entry per keyframe offered: Gaussians, mapped keyframes, time) and the final
map statistics. ``splat_slam_ros.report`` reads these files only.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Optional

import cv2
import numpy as np
import torch

from splat_slam_ros import evaluation as ev

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


def _encode_depth(depth: torch.Tensor, scale: float) -> np.ndarray:
    d = torch.nan_to_num(depth.float(), nan=0.0, posinf=0.0).clamp_min(0)
    return (d * scale + 0.5).clamp(0, 65535).to(torch.int32).cpu().numpy().astype(np.uint16)


def _view_metrics(rgb: np.ndarray, ref: np.ndarray, depth: torch.Tensor,
                  proxy: torch.Tensor, valid: torch.Tensor, gt_depth) -> Dict[str, float]:
    m: Dict[str, float] = {"psnr": ev.psnr(rgb, ref), "ssim": ev.ssim(rgb, ref)}
    rendered = depth > 0
    m["coverage"] = float(rendered.float().mean())
    m["proxy_valid"] = float(valid.float().mean())
    both = rendered & valid
    if bool(both.any()):
        # mean |D^r - D| over pixels with both (the Eq. 11 depth term, unweighted), map units
        m["depth_l1_proxy"] = float((depth[both] - proxy[both]).abs().mean())
    if gt_depth is not None:
        try:
            m["depth_l1_cm"] = ev.depth_l1_cm(depth.cpu().numpy(), gt_depth)
        except ev.MetricError:
            pass
    return m


def write_keyframe_views(mapper, folder, gt_depth=None,
                         depth_scale: Optional[float] = None) -> List[dict]:
    """Write the per-keyframe images and ``keyframes.json`` (see the module docstring).

    ``gt_depth``: kf_id -> ground-truth depth (H, W metres), optional; ``depth_scale``: 16-bit
    steps per map unit (default: :func:`depth_scale_for` the deepest pixel). Returns the per
    keyframe entries."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    entries: List[dict] = []
    views = []
    max_depth = 0.0
    for k, kf in sorted(mapper.keyframes.items()):
        rgb, depth = mapper.render(kf.pose, kf_id=k)
        depth_t = torch.from_numpy(depth).to(kf.depth.device)
        views.append((k, kf, rgb, depth_t))
        for d in (depth_t, kf.depth):
            if d.numel():
                max_depth = max(max_depth, float(torch.nan_to_num(d.float()).max()))
    scale = float(depth_scale) if depth_scale else depth_scale_for(max_depth)
    for k, kf, rgb, depth_t in views:
        ref = kf.image.cpu().numpy()
        gd = gt_depth.get(k) if isinstance(gt_depth, dict) else None
        m = _view_metrics(rgb, ref, depth_t, kf.depth, kf.valid, gd)
        name = f"kf_{k:05d}"
        cv2.imwrite(str(folder / f"{name}.png"), rgb[..., ::-1])
        cv2.imwrite(str(folder / f"{name}_input.png"), ref[..., ::-1])
        cv2.imwrite(str(folder / f"{name}_depth.png"), _encode_depth(depth_t, scale))
        cv2.imwrite(str(folder / f"{name}_proxy.png"),
                    _encode_depth(torch.where(kf.valid, kf.depth, torch.zeros_like(kf.depth)),
                                  scale))
        entries.append({"kf_id": int(k), "index": int(kf.index),
                        "timestamp": float(kf.timestamp),
                        **{key: round(v, 6) for key, v in m.items()}})
    doc = {"depth_scale": scale, "keyframes": entries,
           "history": list(getattr(mapper, "history", [])), "map": mapper.stats()}
    (folder / KEYFRAMES_JSON).write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    return entries
