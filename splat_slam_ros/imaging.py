"""Shared image utilities of every stage: grey conversion, resizing to a grid or a size, and
the degenerate-frame test (plain OpenCV / numpy, no project imports)."""
from __future__ import annotations

import cv2
import numpy as np


def to_gray(img: np.ndarray) -> np.ndarray:
    """(H, W, 3|4) RGB(A) or (H, W) grey -> contiguous (H, W) grey of the same dtype."""
    img = np.asarray(img)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(img)


def image_at(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """``image`` at ``width`` x ``height`` (itself when it is that size already)."""
    if image.shape[:2] == (height, width):
        return image
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def flow_input(image: np.ndarray, disp_shape, ba_downsample: int) -> np.ndarray:
    """A keyframe image as the flow front end's input: resized to the disparity grid x
    ``ba_downsample`` when it was handed on at another size (``tracking.max_pixels``: the
    mapping size), so that the flows land on the grid of the keyframe's disparity."""
    h, w = int(disp_shape[0]) * ba_downsample, int(disp_shape[1]) * ba_downsample
    img = np.asarray(image)
    if img.shape[:2] == (h, w):
        return img
    interp = cv2.INTER_AREA if img.shape[0] > h else cv2.INTER_LINEAR
    return cv2.resize(img, (w, h), interpolation=interp)


def image_is_degenerate(img: np.ndarray, min_std: float = 2.0, min_grad: float = 0.5) -> bool:
    """True for frames that cannot be tracked (black, saturated, uniform)."""
    g = to_gray(img)
    small = cv2.resize(g, (max(g.shape[1] // 4, 8), max(g.shape[0] // 4, 8)),
                       interpolation=cv2.INTER_AREA).astype(np.float32)
    if float(small.std()) < min_std:
        return True
    gx = np.abs(np.diff(small, axis=1)).mean()
    gy = np.abs(np.diff(small, axis=0)).mean()
    return float(gx + gy) < min_grad
