"""Image metrics of a rendered view against its reference: PSNR (optionally after
per-channel exposure compensation, :func:`exposure_compensate`, as in the reference
evaluation), SSIM, and all metrics of one view (:func:`image_metrics`) and their mean over
views (:func:`summarize`).

Images are in [0, 1] (float, torch or numpy, H x W x 3 or 3 x H x W; uint8 images are
divided by 255).
"""
from __future__ import annotations

from typing import Dict, Sequence

import numpy as np
import torch

from splat_slam_ros.evaluation.depth import depth_l1_cm
from splat_slam_ros.evaluation.inputs import MetricError, as_mask, image_pair
from splat_slam_ros.evaluation.perceptual import lpips


def exposure_compensate(img, ref, mask=None, return_params: bool = False):
    """Fit ``a * img + b`` to ``ref`` per channel (least squares) and return it clamped to [0, 1].

    Removes a global brightness/contrast difference (the per-keyframe exposure the map
    learns) before PSNR, like the reference evaluation. Output is a float64 torch tensor
    H x W x C; with ``return_params`` also the (C,) arrays ``a`` and ``b``.
    """
    a_img, r = image_pair(img, ref)
    m = (torch.ones(a_img.shape[:2], dtype=torch.bool, device=a_img.device) if mask is None
         else as_mask(mask, a_img.shape[:2], a_img.device))
    if int(m.sum()) < 2:
        raise MetricError("exposure compensation needs at least 2 valid pixels")
    x, y = a_img[m], r[m]                            # (n, C)
    mx, my = x.mean(0), y.mean(0)
    vx = ((x - mx) ** 2).mean(0)
    cxy = ((x - mx) * (y - my)).mean(0)
    a = torch.where(vx > 1e-12, cxy / vx.clamp_min(1e-12), torch.ones_like(vx))
    b = my - a * mx
    out = (a_img * a + b).clamp(0.0, 1.0)
    if return_params:
        return out, a.cpu().numpy(), b.cpu().numpy()
    return out


def psnr(img, ref, mask=None, exposure_compensation: bool = False) -> float:
    """Peak signal-to-noise ratio (dB) for images in [0, 1]; ``inf`` if identical.

    ``mask`` (H x W bool) restricts the mean squared error to those pixels.
    """
    a, b = image_pair(img, ref)
    if exposure_compensation:
        a = exposure_compensate(a, b, mask)
    if mask is not None:
        m = as_mask(mask, a.shape[:2], a.device)
        if not bool(m.any()):
            raise MetricError("psnr mask selects no pixels")
        a, b = a[m], b[m]
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else float(-10.0 * np.log10(mse))


def ssim(img, ref, win_size: int = 11) -> float:
    """Structural similarity (Gaussian window 11, sigma 1.5) via pytorch-msssim."""
    from pytorch_msssim import ssim as _ssim
    a, b = image_pair(img, ref)
    h, w = a.shape[:2]
    if min(h, w) < win_size:
        raise MetricError(f"ssim needs images of at least {win_size}x{win_size} px, got {h}x{w}")
    X = a.permute(2, 0, 1)[None].float()
    Y = b.permute(2, 0, 1)[None].float()
    return float(_ssim(X, Y, data_range=1.0, size_average=True, win_size=win_size))


def image_metrics(img, ref, depth=None, ref_depth=None, lpips_model=None,
                  lpips_weights=None, exposure_compensation: bool = True) -> Dict[str, float]:
    """All rendering metrics of one view: psnr (optionally exposure-compensated), ssim,
    lpips (when a backbone is given) and depth_l1_cm (when both depths are given)."""
    out = {"psnr": psnr(img, ref, exposure_compensation=exposure_compensation),
           "ssim": ssim(img, ref)}
    if lpips_model is not None:
        out["lpips"] = lpips(img, ref, lpips_model, lpips_weights)
    if depth is not None and ref_depth is not None:
        out["depth_l1_cm"] = depth_l1_cm(depth, ref_depth)
    return out


def summarize(values: Sequence[Dict[str, float]]) -> Dict[str, float]:
    """Mean of each metric over views (``inf`` PSNRs are kept out of the PSNR mean)."""
    keys = sorted({k for v in values for k in v})
    out = {}
    for k in keys:
        xs = np.array([v[k] for v in values if k in v], dtype=np.float64)
        xs = xs[np.isfinite(xs)]
        if len(xs):
            out[k] = float(xs.mean())
    return out
