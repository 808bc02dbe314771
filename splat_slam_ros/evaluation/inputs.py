"""Checked metric inputs: :class:`MetricError` and the conversions every metric shares
(arrays to float64, images to H x W x C in [0, 1], masks)."""
from __future__ import annotations

from typing import Tuple

import numpy as np
import torch


class MetricError(ValueError):
    """A metric cannot be computed from the given inputs (a user-facing, one-line reason)."""


def to_float64(x, name: str) -> np.ndarray:
    if torch.is_tensor(x):
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise MetricError(f"{name} must be numeric array-like") from None


# --------------------------------------------------------- image handling
def as_image(x, name: str) -> torch.Tensor:
    """Any H x W x C / C x H x W (C in 1, 3) image -> float64 tensor H x W x C in [0, 1]."""
    if isinstance(x, np.ndarray):
        t = torch.from_numpy(np.ascontiguousarray(x))
    elif torch.is_tensor(x):
        t = x.detach()
    else:
        raise MetricError(f"{name} must be a numpy array or torch tensor, got {type(x).__name__}")
    if t.dtype == torch.uint8:
        t = t.double() / 255.0
    elif t.is_floating_point():
        t = t.double()
    else:
        raise MetricError(f"{name} must be float in [0, 1] or uint8, got {t.dtype}")
    if t.ndim == 2:
        t = t[..., None]
    if t.ndim != 3:
        raise MetricError(f"{name} must be H x W x 3 or 3 x H x W, got shape {tuple(t.shape)}")
    if t.shape[-1] not in (1, 3) and t.shape[0] in (1, 3):
        t = t.permute(1, 2, 0)
    if t.shape[-1] not in (1, 3):
        raise MetricError(f"{name} must have 1 or 3 channels, got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise MetricError(f"{name} contains non-finite values")
    if t.numel() and (t.max() > 2.0 or t.min() < -1.0):
        raise MetricError(f"{name} values span [{float(t.min()):.3g}, {float(t.max()):.3g}]; "
                          "float images must be in [0, 1] (divide 8-bit images by 255)")
    return t.clamp(0.0, 1.0)


def image_pair(img, ref) -> Tuple[torch.Tensor, torch.Tensor]:
    a, b = as_image(img, "image"), as_image(ref, "reference image")
    if a.shape != b.shape:
        raise MetricError(f"image shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    return a, b.to(a.device)


def as_mask(mask, shape, device) -> torch.Tensor:
    m = torch.as_tensor(np.asarray(mask) if isinstance(mask, np.ndarray) else mask,
                        device=device).bool()
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if tuple(m.shape) != tuple(shape):
        raise MetricError(f"mask shape {tuple(m.shape)} does not match image {tuple(shape)}")
    return m
