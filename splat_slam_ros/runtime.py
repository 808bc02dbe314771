"""Run-time helpers shared by every stage: torch device resolution and thread limits."""
from __future__ import annotations

import contextlib

import cv2
import torch

from splat_slam_ros.config import ConfigError


class DeviceError(ConfigError):
    """A device setting that is not a torch device or asks for CUDA where there is none."""


def resolve_device(name, setting: str = "device") -> torch.device:
    """``auto`` | ``cpu`` | ``cuda`` | ``cuda:N`` (or a torch.device) -> torch.device.

    ``auto`` picks CUDA when present; an explicit CUDA device without CUDA, or a name torch
    does not know, raises :class:`DeviceError` naming ``setting`` (e.g. ``tracking.device``).
    """
    if isinstance(name, torch.device):
        name = str(name)
    name = str(name or "cpu").strip().lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise DeviceError(f"{setting}={name!r} is not a torch device "
                          "(use cpu, cuda, cuda:N or auto)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DeviceError(f"{setting}={name} but CUDA is not available; use cpu or auto")
    return dev


@contextlib.contextmanager
def limit_threads(n: int):
    """Run a block with ``n`` torch/OpenCV threads (0: unchanged). The tracker's
    tensors are small: on a shared 2-core machine one thread avoids the thread
    pools' spinning and oversubscription (measured several times faster)."""
    if not n or n <= 0:
        yield
        return
    old_t, old_cv = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(int(n))
    cv2.setNumThreads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old_t)
        cv2.setNumThreads(old_cv)
