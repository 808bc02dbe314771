"""Giving freed memory back to the OS, for long-running processes (no torch import: the bag
player uses it too)."""
from __future__ import annotations

import ctypes
import sys

_LIBC = ctypes.CDLL(None) if sys.platform.startswith("linux") else None


def release_free_memory() -> bool:
    """Hand memory the process freed back to the OS (glibc ``malloc_trim``).

    A long-running node allocates and frees large blocks per keyframe and per update (flow,
    BA workspace, proxy depths of every keyframe a global BA moved); glibc keeps freed heap
    pages mapped, so RSS stays at the largest such peak and creeps up with fragmentation.
    Trimming after the work keeps RSS at what is actually in use (about 10 ms when there is
    much to give back). Returns False where the C library has no ``malloc_trim``."""
    fn = getattr(_LIBC, "malloc_trim", None)
    if fn is None:
        return False
    fn(0)
    return True
