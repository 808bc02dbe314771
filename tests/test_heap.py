"""release_free_memory: freed heap pages go back to the OS (what keeps node RSS flat)."""
import sys

import pytest
import torch

from splat_slam_ros.heap import release_free_memory


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        return int(next(l for l in f if l.startswith("VmRSS")).split()[1]) / 1024


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc_trim: Linux only")
def test_freed_fragmented_heap_is_given_back():
    keep = []
    for i in range(100):          # growing tensors freed between smaller ones that stay
        churn = [torch.ones(100000 + 997 * i) for _ in range(20)]
        keep.append(torch.ones(30000))
        del churn
    before = rss_mb()
    assert release_free_memory() is True
    after = rss_mb()
    assert after < before - 10, (before, after)
    assert float(sum(k.sum() for k in keep)) == 100 * 30000          # what is in use stays
