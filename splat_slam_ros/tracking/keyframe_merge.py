"""Merging of redundant keyframes, so a long run in one place keeps a bounded BA graph.

The tracker makes a keyframe whenever the flow to its *current* reference keyframe is large;
on a revisit it does not know that an older keyframe already has the same view, so a camera
that keeps moving around one room keeps adding keyframes. Global BA (Eq. 1, paper Sec. 3.1)
over all of them grows without bound in time and memory (its dense pose block is quadratic
in the number of keyframes). A keyframe ``k`` is therefore merged into an older one ``o``
when:

1. ``k`` is settled: older than the newest ``settle`` keyframes (the loop window and the
   temporal radius, which the tracker's local BA and the loop BA still move);
2. a *measured* non-temporal flow edge (a spatial or loop edge, not only the estimate) joins
   ``k`` and ``o``, with ``o`` older than ``k`` and kept;
3. the flow the current estimate induces between them (mean of both directions, BA px) is
   below ``thresh`` (by default the tracker's keyframe threshold: ``k`` is a keyframe the
   tracker would not have made had it tracked against ``o``);
4. the graph without ``k`` stays connected (one gauge for global BA).

A merged keyframe leaves the BA graph (its edges and variables go) and follows ``o`` rigidly:
``T_k = T_o T_rel`` with ``T_rel = T_o^-1 T_k`` frozen at the merge (camera-to-world poses).
Its pose keeps being reported when ``o`` moves (poses-only updates), so the tracker's
trajectory and the map still follow loop closure and global BA.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Dict, Iterable, List, Sequence, Set, Tuple

import torch

from splat_slam_ros.tracking.dense_ba import induced_flow_distance

TEMPORAL_KINDS = ("odometry",)


@dataclass
class MergedKeyframe:
    anchor: int                  # the kept keyframe it follows
    rel: torch.Tensor            # (4, 4) float64 T_anchor^-1 T_k (camera-to-world poses)
    timestamp: float


def connected_without(pairs: Iterable[Tuple[int, int]], nodes: Iterable[int], drop: int) -> bool:
    """Whether ``nodes`` minus ``drop`` form one connected component over ``pairs``."""
    keep = set(nodes) - {drop}
    if len(keep) <= 1:
        return True
    adj: Dict[int, Set[int]] = defaultdict(set)
    for a, b in pairs:
        if a in keep and b in keep:
            adj[a].add(b)
            adj[b].add(a)
    start = next(iter(keep))
    seen, todo = {start}, [start]
    while todo:
        for n in adj[todo.pop()]:
            if n not in seen:
                seen.add(n)
                todo.append(n)
    return len(seen) == len(keep)


def merge_candidates(ids: Sequence[int], poses: torch.Tensor, disps: torch.Tensor, intr,
                     kinds: Dict[Tuple[int, int], str], settle: int, thresh: float
                     ) -> List[Tuple[int, int, float]]:
    """(k, o, induced distance) for every settled ``k`` joined to an older ``o`` by a
    measured non-temporal edge with a mean induced flow below ``thresh`` (rules 1-3 above;
    the closest ``o`` per ``k``). ``poses``/``disps`` are rows of ``ids``."""
    ids = list(ids)
    if thresh <= 0 or len(ids) <= settle:
        return []
    pos = {k: n for n, k in enumerate(ids)}
    settled = set(ids[:len(ids) - settle])
    pairs = sorted({(max(a, b), min(a, b)) for (a, b), kind in kinds.items()
                    if kind not in TEMPORAL_KINDS and a in settled and b in pos
                    and max(a, b) in settled})
    if not pairs:
        return []
    ii = torch.tensor([pos[k] for k, _ in pairs], device=disps.device)
    jj = torch.tensor([pos[o] for _, o in pairs], device=disps.device)
    dist = 0.5 * (induced_flow_distance(poses, disps, intr, ii, jj)
                  + induced_flow_distance(poses, disps, intr, jj, ii))
    best: Dict[int, Tuple[int, float]] = {}
    for (k, o), d in zip(pairs, dist.tolist()):
        if d < thresh and (k not in best or d < best[k][1]):
            best[k] = (o, d)
    return [(k, o, d) for k, (o, d) in sorted(best.items())]
