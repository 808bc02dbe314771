"""Rendering quality of a map: PSNR, SSIM, LPIPS and depth L1 of rendered views.

:func:`evaluate_map` renders the mapped keyframes (each with its learned exposure, as the
reference evaluates) or given frames and scores them against their images and depths;
:func:`evaluate_keyframes` is what a run reports, with the renders and
:func:`write_keyframe_views` (the per-keyframe files of mapping/keyframe_views.py and
``keyframes.json``, which the run report reads) written beside them; :func:`save_renders`
writes the keyframe renders of a map alone.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence

import cv2
import numpy as np
import torch

from splat_slam_ros.evaluation.depth import depth_l1_cm
from splat_slam_ros.evaluation.image import psnr, ssim, summarize
from splat_slam_ros.evaluation.inputs import MetricError
from splat_slam_ros.evaluation.perceptual import lpips
from splat_slam_ros.mapping.keyframe_inputs import MapError
from splat_slam_ros.mapping.keyframe_views import KEYFRAMES_JSON, depth_scale_for, encode_depth


def evaluate_map(mapper, frames: Optional[Iterable] = None, gt_depth=None,
                 poses: Optional[Sequence[np.ndarray]] = None, render_dir=None,
                 lpips_model=None, lpips_weights=None) -> dict:
    """Rendering metrics (PSNR, SSIM, LPIPS with a backbone file, depth L1 in cm).

    ``frames=None``: the mapped keyframes, each with its learned exposure (as the
    reference evaluates); ``gt_depth`` then maps kf_id -> sensor depth (H,W metres).
    Otherwise ``frames`` are :class:`~splat_slam_ros.types.Frame` objects rendered at
    ``poses`` (default: their ``gt_pose``) against ``frame.image`` / ``frame.gt_depth``.
    Also reports the Gaussian count and map size (MB)."""
    views = []
    if frames is None:
        for k, kf in sorted(mapper.keyframes.items()):
            gd = None
            if gt_depth is not None:
                gd = gt_depth.get(k) if isinstance(gt_depth, dict) else gt_depth[kf.index]
            views.append((f"kf_{k:05d}", kf.pose, kf.image.cpu().numpy(), gd, k))
    else:
        for i, fr in enumerate(frames):
            pose = poses[i] if poses is not None else fr.gt_pose
            if pose is None:
                raise MapError(f"frame {fr.index} has no pose to render from")
            views.append((f"frame_{fr.index:05d}", pose, np.asarray(fr.image),
                          fr.gt_depth, None))
    per_view = []
    for name, pose, ref, gd, kid in views:
        H, W = ref.shape[:2]
        rgb, depth = mapper.render(pose, W, H, kf_id=kid)
        m = {"psnr": psnr(rgb, ref), "ssim": ssim(rgb, ref)}
        if lpips_model is not None:
            m["lpips"] = lpips(rgb, ref, lpips_model, lpips_weights)
        if gd is not None:
            m["depth_l1_cm"] = depth_l1_cm(depth, gd)
        per_view.append(m)
        if render_dir is not None:
            Path(render_dir).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(Path(render_dir) / f"{name}.png"), rgb[..., ::-1])
    return _summary(mapper, per_view)


def _summary(mapper, per_view: List[Dict[str, float]]) -> dict:
    """Per-view metrics averaged, with the view count and the map's size."""
    out = summarize(per_view) if per_view else {}
    out.update({"views": len(per_view), "gaussians": len(mapper.map),
                "map_mb": round(mapper.map.nbytes() / 2 ** 20, 4)})
    return out


def evaluate_keyframes(mapper, render_dir=None, gt_depth=None, renders=None) -> dict:
    """Keyframe metrics (what the pipeline reports), renders written to ``render_dir``
    (with the per-keyframe views for the report: each keyframe is rendered once, or taken
    from ``renders``, :meth:`Mapper.keyframe_renders`)."""
    if render_dir is None:
        return evaluate_map(mapper, None, gt_depth=gt_depth)
    _, per_view = _keyframe_views(mapper, Path(render_dir), gt_depth, renders=renders)
    return _summary(mapper, [{k: m[k] for k in ("psnr", "ssim", "depth_l1_cm") if k in m}
                             for m in per_view])


def save_renders(mapper, folder, depth_scale: float = 1000.0) -> int:
    """Write ``kf_<id>.png`` (rendered colour with the keyframe's exposure) and
    ``kf_<id>_depth.png`` (16-bit, ``depth_scale`` units per metre) per keyframe."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for k, kf in sorted(mapper.keyframes.items()):
        rgb, depth = mapper.render(kf.pose, kf_id=k)
        cv2.imwrite(str(folder / f"kf_{k:05d}.png"), rgb[..., ::-1])
        d = np.clip(depth * depth_scale, 0, 65535).astype(np.uint16)
        cv2.imwrite(str(folder / f"kf_{k:05d}_depth.png"), d)
    write_keyframe_views(mapper, folder, depth_scale=depth_scale)   # for the run report
    return len(mapper.keyframes)


def _view_metrics(rgb: np.ndarray, ref: np.ndarray, depth: torch.Tensor,
                  proxy: torch.Tensor, valid: torch.Tensor, gt_depth) -> Dict[str, float]:
    m: Dict[str, float] = {"psnr": psnr(rgb, ref), "ssim": ssim(rgb, ref)}
    rendered = depth > 0
    m["coverage"] = float(rendered.float().mean())
    m["proxy_valid"] = float(valid.float().mean())
    both = rendered & valid
    if bool(both.any()):
        # mean |D^r - D| over pixels with both (the Eq. 11 depth term, unweighted), map units
        m["depth_l1_proxy"] = float((depth[both] - proxy[both]).abs().mean())
    if gt_depth is not None:
        try:
            m["depth_l1_cm"] = depth_l1_cm(depth.cpu().numpy(), gt_depth)
        except MetricError:
            pass
    return m


def write_keyframe_views(mapper, folder, gt_depth=None,
                         depth_scale: Optional[float] = None) -> List[dict]:
    """Write the per-keyframe images and ``keyframes.json`` (see the module docstring).

    ``gt_depth``: kf_id -> ground-truth depth (H, W metres), optional; ``depth_scale``: 16-bit
    steps per map unit (default: :func:`depth_scale_for` the deepest pixel). Returns the per
    keyframe entries."""
    return _keyframe_views(mapper, Path(folder), gt_depth, depth_scale)[0]


def _keyframe_views(mapper, folder: Path, gt_depth=None, depth_scale: Optional[float] = None,
                    renders=None):
    """:func:`write_keyframe_views`; also returns each keyframe's unrounded metrics
    (``renders``: :meth:`Mapper.keyframe_renders` when already made)."""
    folder.mkdir(parents=True, exist_ok=True)
    entries: List[dict] = []
    metrics: List[Dict[str, float]] = []
    views = []
    max_depth = 0.0
    for k, kf in sorted(mapper.keyframes.items()):
        rgb, depth = mapper.render(kf.pose, kf_id=k) if renders is None else \
            mapper.exposed(renders[k], kf_id=k)
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
        metrics.append(m)
        name = f"kf_{k:05d}"
        cv2.imwrite(str(folder / f"{name}.png"), rgb[..., ::-1])
        cv2.imwrite(str(folder / f"{name}_input.png"), ref[..., ::-1])
        cv2.imwrite(str(folder / f"{name}_depth.png"), encode_depth(depth_t, scale))
        cv2.imwrite(str(folder / f"{name}_proxy.png"),
                    encode_depth(torch.where(kf.valid, kf.depth, torch.zeros_like(kf.depth)),
                                 scale))
        entries.append({"kf_id": int(k), "index": int(kf.index),
                        "timestamp": float(kf.timestamp),
                        **{key: round(v, 6) for key, v in m.items()}})
    doc = {"depth_scale": scale, "keyframes": entries,
           "history": list(getattr(mapper, "history", [])), "map": mapper.stats()}
    (folder / KEYFRAMES_JSON).write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    return entries, metrics
