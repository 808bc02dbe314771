"""Network range and node subset of ``splat-slam-launch`` (``--network``, ``--nodes``).

``--network localhost`` (default) keeps the graph on this machine: shared memory + UDPv4 on the
loopback interface only (``config/fastdds.xml``). ``--network subnet`` (or
``SPLAT_SLAM_DDS_RANGE=subnet``) uses UDPv4 on every interface (``config/fastdds_subnet.xml``)
so nodes on several hosts with the same ``ROS_DOMAIN_ID`` form one graph; ``--nodes`` then
starts only this host's share of the graph (e.g. ``--nodes depth,mapper`` on a GPU host).
"""
from __future__ import annotations

import os
from typing import List, MutableMapping, Optional

from splat_slam_ros.ros_env import RANGE_ENV, RANGES

PIPELINE_NODES = ("tracker", "loop_closure", "depth", "mapper")


class NetworkArgError(ValueError):
    """Invalid --network / --nodes value (one-line message)."""


def apply_network(network: Optional[str], environ: Optional[MutableMapping[str, str]] = None) -> str:
    """Set ``SPLAT_SLAM_DDS_RANGE`` from ``--network`` (when given); return the range in use."""
    env = os.environ if environ is None else environ
    if network:
        if network not in RANGES:
            raise NetworkArgError(f"--network must be one of {', '.join(RANGES)}, got {network!r}")
        env[RANGE_ENV] = network
    return env.get(RANGE_ENV, "").strip().lower() or "localhost"


def select_nodes(spec: Optional[str], planned: List[str]) -> List[str]:
    """The pipeline nodes this launcher starts: ``planned`` filtered by ``--nodes a,b``."""
    if not spec:
        return list(planned)
    want = [s.strip() for s in spec.split(",") if s.strip()]
    if not want:
        raise NetworkArgError("--nodes is empty (name nodes, e.g. --nodes tracker,depth)")
    for n in want:
        if n not in PIPELINE_NODES:
            raise NetworkArgError(f"--nodes: unknown node {n!r} (known: {', '.join(PIPELINE_NODES)})")
        if n not in planned:
            raise NetworkArgError(f"--nodes: {n} is not part of this graph (planned: "
                                  f"{', '.join(planned)}); check --tracking-only / "
                                  "--no-loop-closure")
    return [n for n in planned if n in want]
