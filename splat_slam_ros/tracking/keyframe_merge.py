"""Merging of redundant keyframes, so a long run in one place keeps a bounded BA graph.

The tracker makes a keyframe whenever the flow to its *current* reference keyframe is large;
on a revisit it does not know that an older keyframe already has the same view, so a camera
that keeps moving around one room keeps adding keyframes. Global BA (Eq. 1, paper Sec. 3.1)
over all of them grows without bound in time and memory (its dense pose block is quadratic
in the number of keyframes). A keyframe ``k`` is therefore merged into an older one ``o``
when:

1. ``k`` is settled: older than the newest ``settle`` keyframes (the loop window and the
   temporal radius, which the tracker's local BA and the loop BA still move);
2. ``k``'s pose is tied to the older map by a *measured* non-temporal flow edge (a spatial
   or loop edge to an older keyframe, not only the estimate), so the estimate places it
   where the older keyframes are;
3. ``o`` is the older kept keyframe (not a temporal neighbour) to which the current
   estimate induces the smallest flow (mean of both directions, BA px), and that flow is
   below ``thresh`` (by default the tracker's keyframe threshold: ``k`` is a keyframe the
   tracker would not have made had it tracked against ``o``). ``o`` need not be the
   keyframe of the edge in rule 2: loop detection and global BA measure at most a couple
   of edges per keyframe, rarely to the very nearest older one (in the soak, 64 of 269
   keyframes that had an older one within the threshold also had an edge to it);
4. removing ``k`` does not cut its part of the graph in two (one gauge for global BA).

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


def components(pairs: Iterable[Tuple[int, int]], nodes: Iterable[int]) -> int:
    """The number of connected components of ``nodes`` over ``pairs``."""
    nodes = set(nodes)
    adj: Dict[int, Set[int]] = defaultdict(set)
    for a, b in pairs:
        if a in nodes and b in nodes:
            adj[a].add(b)
            adj[b].add(a)
    seen: Set[int] = set()
    n = 0
    for start in nodes:
        if start in seen:
            continue
        n += 1
        seen.add(start)
        todo = [start]
        while todo:
            for m in adj[todo.pop()]:
                if m not in seen:
                    seen.add(m)
                    todo.append(m)
    return n


def splits(pairs: Sequence[Tuple[int, int]], nodes: Sequence[int], drop: int) -> bool:
    """Whether removing ``drop`` cuts its component of the graph in two (rule 4: each
    component keeps one gauge; a graph that is already in pieces, e.g. after a tracking
    gap no edge bridged, still lets its pieces merge within themselves)."""
    return components(pairs, set(nodes) - {drop}) > components(pairs, nodes) - (
        0 if any(drop in p for p in pairs) else 1)


def merge_candidates(ids: Sequence[int], poses: torch.Tensor, disps: torch.Tensor, intr,
                     kinds: Dict[Tuple[int, int], str], settle: int, thresh: float,
                     min_gap: int = 1, stride: int = 4) -> List[Tuple[int, int, float]]:
    """(k, o, induced distance) for every settled ``k`` with a measured non-temporal edge to
    an older keyframe, ``o`` the keyframe of ``ids`` at least ``min_gap`` ids older (a
    revisit, not the temporal neighbour) nearest to it by induced flow, when that is below
    ``thresh`` (rules 1-3 above). ``poses``/``disps`` are rows of ``ids``; the flow is
    measured on a ``stride``-subsampled grid."""
    ids = list(ids)
    if thresh <= 0 or len(ids) <= settle:
        return []
    pos = {k: n for n, k in enumerate(ids)}
    settled = set(ids[:len(ids) - settle])
    tied = sorted({max(a, b) for (a, b), kind in kinds.items()
                   if kind not in TEMPORAL_KINDS and a in pos and b in pos
                   and max(a, b) in settled})
    pairs = [(k, o) for k in tied for o in ids if o <= k - min_gap]
    if not pairs:
        return []
    ii = torch.tensor([pos[k] for k, _ in pairs], device=disps.device)
    jj = torch.tensor([pos[o] for _, o in pairs], device=disps.device)
    dist = 0.5 * (induced_flow_distance(poses, disps, intr, ii, jj, stride=stride)
                  + induced_flow_distance(poses, disps, intr, jj, ii, stride=stride))
    best: Dict[int, Tuple[int, float]] = {}
    for (k, o), d in zip(pairs, dist.tolist()):
        if d < thresh and (k not in best or d < best[k][1]):
            best[k] = (o, d)
    return [(k, o, d) for k, (o, d) in sorted(best.items())]
