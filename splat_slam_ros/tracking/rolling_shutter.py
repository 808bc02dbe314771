"""Rolling-shutter rectification of the tracking images.

A rolling-shutter camera reads its rows one after another: row ``v`` of an H-row image is
read ``tau_v = readout * (v / (H - 1) - stamp_row)`` seconds after the image stamp
(``stamp_row``: the row whose readout time the stamp gives; 0 = top, 1 = bottom). The method
(paper §3.1) models a global shutter, so on fast motion every image is skewed against its
pose. Moving at angular velocity ``omega`` and velocity ``v`` (camera frame), row ``v``'s
camera is the stamp's turned by ``exp(tau_v omega)`` and moved by ``tau_v v``; a point ``P``
of the stamp's camera frame is ``exp(-tau_v omega) (P - tau_v v)`` in the row's. With every
point on a plane at the scene's depth ``Z`` (``P = Z K^-1 y``), a pixel ``y`` of the image
the stamp's camera would have taken shows up at ``x = K exp(-tau_v omega) (K^-1 y -
tau_v v / Z)`` in the rolling-shutter image (the row of ``y`` stands for the row of ``x``: a
few pixels apart, a few tenths of a millisecond). The rectified image samples the input
there. The translation is exact on that plane only, and the tracker knows the motion of the
frames before, not of this one (docs/tracking.md "Rolling shutter").
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import cv2
import numpy as np
import torch

from splat_slam_ros.geometry import intr_tensor, so3_exp, so3_log


class RollingShutterError(ValueError):
    """Invalid rolling-shutter settings (camera.rolling_shutter_*)."""


def check_settings(readout_ms: float, stamp_row: float) -> None:
    if not np.isfinite(readout_ms) or readout_ms < 0:
        raise RollingShutterError(f"camera.rolling_shutter_ms must be >= 0, got {readout_ms}")
    if not np.isfinite(stamp_row) or not 0.0 <= stamp_row <= 1.0:
        raise RollingShutterError("camera.rolling_shutter_stamp_row must be in [0, 1] "
                                  f"(0 = top row, 1 = bottom row), got {stamp_row}")


def median_depth(disparity) -> float:
    """The scene depth a keyframe's disparity map stands for in the rectification: the
    inverse of its median."""
    return 1.0 / max(float(disparity.median()), 1e-6)


def row_times(height: int, readout_s: float, stamp_row: float) -> np.ndarray:
    """Readout time of each row relative to the stamp (s; negative before it)."""
    v = np.arange(int(height), dtype=np.float64)
    return readout_s * (v / max(int(height) - 1, 1) - stamp_row)


class ReadoutMotion(NamedTuple):
    """The camera's motion during a readout (camera frame): angular velocity (rad/s),
    velocity (units/s) and the scene depth (same units) that turns the velocity into an
    image motion (0: the rotation only)."""
    omega: np.ndarray
    velocity: np.ndarray
    depth: float


def readout_motion(step: np.ndarray, dt: float, depth: float = 0.0) -> Optional[ReadoutMotion]:
    """The motion of a relative pose ``step`` (camera-to-world before^-1 @ after, 4x4) over
    ``dt`` seconds, at scene ``depth``; None without a positive ``dt``."""
    step = np.asarray(step, dtype=np.float64)
    w = angular_velocity(step[:3, :3], dt)
    if w is None:
        return None
    return ReadoutMotion(w, step[:3, 3] / dt, float(depth) if np.isfinite(depth) else 0.0)


def rectify(image: np.ndarray, intrinsics, motion: Optional[ReadoutMotion],
            readout_s: float, stamp_row: float) -> np.ndarray:
    """``image`` (H x W [x C]; pinhole ``intrinsics``: an Intrinsics or (fx, fy, cx, cy)) as
    the camera at the stamp would have seen it, moving by ``motion`` during the readout (its
    translation as if the scene were a plane at ``motion.depth``). Returned unchanged without
    a readout time or a motion."""
    if motion is None or readout_s <= 0:
        return image
    w = np.asarray(motion.omega, dtype=np.float64).reshape(3)
    vel = np.asarray(motion.velocity, dtype=np.float64).reshape(3)
    moves = motion.depth > 0 and np.isfinite(vel).all() and np.any(vel)
    if not np.isfinite(w).all() or not (np.any(w) or moves):
        return image
    H, W = image.shape[:2]
    fx, fy, cx, cy = (float(x) for x in intr_tensor(intrinsics, torch.float64)[:4])
    tau = row_times(H, readout_s, stamp_row)
    R = so3_exp(torch.from_numpy(-tau[:, None] * w[None])).numpy()          # (H, 3, 3)
    u = (np.arange(W, dtype=np.float64) - cx) / fx
    v = (np.arange(H, dtype=np.float64) - cy) / fy
    # ray (u, v_row, 1) of every pixel of a row, turned by that row's rotation
    X = R[:, None, :, 0] * u[None, :, None] + (R[:, :, 1] * v[:, None] + R[:, :, 2])[:, None]
    if moves:
        # the row's camera is tau_v velocity from the stamp's: the point moves by -tau_v v
        c = -tau[:, None] * vel[None] / motion.depth
        X = X + np.einsum("rab,rb->ra", R, c)[:, None]
    z = np.maximum(X[..., 2], 1e-6)
    mx = (fx * X[..., 0] / z + cx).astype(np.float32)
    my = (fy * X[..., 1] / z + cy).astype(np.float32)
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def angular_velocity(R_step: np.ndarray, dt: float) -> Optional[np.ndarray]:
    """Camera-frame angular velocity (rad/s) of a relative rotation ``R_step`` (camera-to-
    world before^-1 @ after) over ``dt`` seconds; None without a positive ``dt``."""
    if not dt > 0:
        return None
    return so3_log(torch.as_tensor(np.asarray(R_step, dtype=np.float64))).numpy() / dt
