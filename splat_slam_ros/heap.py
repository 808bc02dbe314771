"""Giving freed memory back to the OS, for long-running processes (no torch import: the bag
player uses it too)."""
from __future__ import annotations

import ctypes
import sys
from typing import Dict

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


M_TRIM_THRESHOLD = -1          # glibc mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
# One offline run (``splat-slam-run``): the mapping step's image- and map-sized tensors (0.3-4
# MB, freed within the step) stay in the heap instead of a fresh mapping each, whose pages
# fault in again on every use (16.6M page faults in a 200-frame drone run; 0.5M with these).
RUN_MMAP_THRESHOLD = 64 << 20
RUN_TRIM_THRESHOLD = 512 << 20
# A tracking-only run has no mapping step: the free top of its heap above 4 MiB goes back to
# the OS (peak RSS 370 -> 340 MB on a 200-frame drone clip of 64 keyframes, the same wall time).
TRACKING_TRIM_THRESHOLD = 4 << 20


def bound_heap(mmap_threshold: int = 1 << 19, arenas: int = 2,
               trim_threshold: int = 0) -> bool:
    """Allocator settings for long-running processes (glibc ``mallopt``).

    glibc serves an allocation above the mmap threshold with its own mapping, unmapped on
    free; but the threshold rises to the size of every such block freed (up to 32 MiB), so
    after the first large tensors are freed, later ones come from the heap, where blocks of
    changing sizes fragment it and RSS creeps up over a long run. A fixed threshold (setting
    it turns the adjustment off) keeps large blocks out of the heap. 512 KiB puts a decoded
    640x480 RGB frame (0.9 MB) and the BA's per-chunk Jacobians in their own mappings (at
    1 MiB they came from the heap: 4 MB more peak RSS over a 300-frame tracking run, at no
    measurable speed difference). Fewer arenas keep the threads (executor, worker, BLAS)
    from each holding their own fragmented heap. ``trim_threshold`` > 0: free memory at the
    heap's top is given back only beyond this (0: glibc's default, 128 KiB). A one-shot run
    uses :data:`RUN_MMAP_THRESHOLD` and :data:`RUN_TRIM_THRESHOLD` (7 % faster on a 200-frame
    drone clip, 1.58 GB peak instead of 1.49-1.52). Returns False where the C library has no
    ``mallopt``."""
    fn = getattr(_LIBC, "mallopt", None)
    if fn is None:
        return False
    ok = bool(fn(M_MMAP_THRESHOLD, int(mmap_threshold))) & bool(fn(M_ARENA_MAX, int(arenas)))
    if trim_threshold > 0:
        ok &= bool(fn(M_TRIM_THRESHOLD, int(trim_threshold)))
    return ok


def proc_memory_mb(pid="self") -> Dict[str, float]:
    """The memory fields (kB lines: VmRSS, VmHWM, RssAnon, RssShmem, ...) of
    ``/proc/<pid>/status`` in MB; empty when the process is gone (or there is no /proc)."""
    out = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                key, _, val = line.partition(":")
                parts = val.split()
                if len(parts) == 2 and parts[1] == "kB":
                    out[key] = int(parts[0]) / 1024.0
    except (OSError, ValueError):
        return {}
    return out


def peak_rss_mb() -> float:
    """Peak resident memory (MB) of this process since it started its program (``VmHWM``).

    Unlike ``getrusage``'s ``ru_maxrss``, which Linux carries over from the parent across
    fork + exec (a child started by a 350 MB benchmark process reports at least 350 MB),
    this is the program's own peak."""
    hwm = proc_memory_mb().get("VmHWM")
    if hwm is None:
        raise RuntimeError("/proc/self/status has no VmHWM line")
    return hwm
