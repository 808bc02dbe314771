"""release_free_memory: freed heap pages go back to the OS (what keeps node RSS flat)."""
import sys

import pytest


FRAGMENT = """
import torch
from splat_slam_ros.heap import release_free_memory
def rss_mb():
    with open("/proc/self/status") as f:
        return int(next(l for l in f if l.startswith("VmRSS")).split()[1]) / 1024
keep = []
for i in range(100):          # growing tensors freed between smaller ones that stay
    churn = [torch.ones(100000 + 997 * i) for _ in range(20)]
    keep.append(torch.ones(30000))
    del churn
before = rss_mb()
ok = release_free_memory()
after = rss_mb()
print(ok, before, after, float(sum(k.sum() for k in keep)))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc_trim: Linux only")
def test_freed_fragmented_heap_is_given_back():
    """In a fresh interpreter: what the heap looks like, and so what a trim can give back,
    depends on everything the process allocated before (glibc moves its mmap threshold up
    after large frees), so in the test process it would depend on the tests run before."""
    import subprocess
    out = subprocess.run([sys.executable, "-c", FRAGMENT], check=True, capture_output=True,
                         text=True, timeout=120).stdout.split()
    ok, before, after, kept = out[0] == "True", float(out[1]), float(out[2]), float(out[3])
    assert ok
    assert after < before - 10, (before, after)
    assert kept == 100 * 30000                                        # what is in use stays


def child_rss_mb(script: str, flags) -> dict:
    """{flag: RSS in MB at the end of ``script`` run in a fresh interpreter with ``flag``}
    (allocator settings only take effect in a process of their own)."""
    import subprocess
    code = script + 'with open("/proc/self/status") as f:\n' \
        '    print(int(next(l for l in f if l.startswith("VmRSS")).split()[1]) // 1024)\n'
    return {flag: int(subprocess.run([sys.executable, "-c", code, flag], check=True,
                                     capture_output=True, text=True).stdout.split()[-1])
            for flag in flags}


CHURN = """
import sys, torch
from splat_slam_ros.heap import bound_heap
if sys.argv[1] == "1":
    assert bound_heap() is True
big = torch.ones(1000000)      # 4 MB, mmapped and freed: glibc raises its mmap threshold
del big
blocks, keep = [], []
for i in range(50):            # 2 MB blocks between small ones that stay, then freed
    blocks.append(torch.ones(500000))
    keep.append(torch.ones(1000))
del blocks
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt: Linux only")
def test_bounded_heap_keeps_large_freed_blocks_out_of_the_heap():
    """bound_heap (every node's start-up): large blocks stay mmapped and go back to the OS
    when freed, without waiting for a trim; glibc's default lets them into the heap once
    the first one was freed, where they stay resident."""
    rss = child_rss_mb(CHURN, ("0", "1"))
    assert rss["1"] < rss["0"] - 60, rss               # 50 x 2 MB freed


FRAMES = """
import sys, numpy as np
from splat_slam_ros.heap import bound_heap
assert (bound_heap(1 << 20) if sys.argv[1] == "1MiB" else bound_heap()) is True
frames, keep = [], []
for i in range(60):            # decoded 640x480 RGB frames between small arrays that stay
    frames.append(np.ones((480, 640, 3), np.uint8))
    keep.append(np.ones(2000))
del frames
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt: Linux only")
def test_bounded_heap_returns_freed_frames_to_the_os():
    """A decoded 640x480 frame (0.9 MB) is above bound_heap's default threshold: freed, it
    goes back to the OS; with a 1 MiB threshold it came from the heap and stayed resident
    (part of the tracker's peak RSS)."""
    rss = child_rss_mb(FRAMES, ("1MiB", "default"))
    assert rss["default"] < rss["1MiB"] - 40, rss       # 60 x 0.9 MB freed


REUSE = """
import resource, sys, torch
from splat_slam_ros.heap import RUN_MMAP_THRESHOLD, RUN_TRIM_THRESHOLD, bound_heap
assert (bound_heap(RUN_MMAP_THRESHOLD, trim_threshold=RUN_TRIM_THRESHOLD) if sys.argv[1] == "run"
        else bound_heap()) is True
x = torch.ones(1000, 1000)
for i in range(3):                                        # warm up
    (x * 2.0).sum()
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for i in range(50):            # a step's temporaries: 4 MB tensors made and freed
    (x * 2.0).sum()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt: Linux only")
def test_a_runs_heap_reuses_the_steps_temporaries():
    """splat-slam-run's allocator settings (heap.RUN_*): a freed 4 MB temporary is reused from
    the heap; with a node's bounded heap each one is a fresh mapping whose 1 000 pages fault
    in again."""
    import subprocess
    faults = {mode: int(subprocess.run([sys.executable, "-c", REUSE, mode], check=True,
                                       capture_output=True, text=True).stdout.split()[-1])
              for mode in ("run", "node")}
    assert faults["node"] > 50 * 900 and faults["run"] < 50 * 100, faults


def test_peak_rss_is_the_programs_own_not_the_parents():
    """A child started by a big process reports its own peak (the benchmarks' RSS column):
    getrusage's ru_maxrss can carry the parent's peak over across fork + exec."""
    import subprocess
    import sys
    import numpy as np
    from splat_slam_ros.heap import peak_rss_mb
    big = np.ones(300 * 2**20 // 8)                       # 300 MB touched in the parent
    assert peak_rss_mb() > 300
    code = "from splat_slam_ros.heap import peak_rss_mb; print(peak_rss_mb())"
    child = float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                 check=True).stdout)
    assert 1 < child < 100, child
    del big


TOP = """
import sys, numpy as np
from splat_slam_ros import heap
trim = heap.TRACKING_TRIM_THRESHOLD if sys.argv[1] == "tracking" else heap.RUN_TRIM_THRESHOLD
assert heap.bound_heap(heap.RUN_MMAP_THRESHOLD, trim_threshold=trim) is True
blocks = [np.ones(125000) for _ in range(40)]       # 40 x 1 MB at the top of the heap, freed
del blocks
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt: Linux only")
def test_a_tracking_only_run_gives_the_free_top_of_its_heap_back():
    """splat-slam-run --tracking-only (heap.TRACKING_TRIM_THRESHOLD): a free top of the heap
    above 4 MiB goes back to the OS; a mapping run keeps it for its next step."""
    rss = child_rss_mb(TOP, ("tracking", "run"))
    assert rss["tracking"] < rss["run"] - 30, rss       # 40 MB freed at the top
