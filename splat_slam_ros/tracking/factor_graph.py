"""Keyframe factor graph G(V, E) (paper Sec. 3.1): edges carry optical-flow measurements.

Nodes are keyframe ids (the pose/disparity values live with their owner: the
tracker's window or the loop closer's store). An edge ``(i, j)`` stores the
target coordinates ``p~_ij`` (h, w, 2; BA pixels, absolute) and the weights
``Sigma_ij`` (h, w, 2) of Eq. 1, plus its age (BA rounds it took part in).
The same structure serves local BA (sliding window), loop BA and global BA;
only the edge selection differs (``proximity_pairs``).
"""
from __future__ import annotations

from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import torch

from splat_slam_ros.tracking.dense_ba import induced_flow_distance
from splat_slam_ros.geometry import pixel_grid


class FactorGraph:
    """Flow edges between keyframes, keyed by (i, j) keyframe ids."""

    def __init__(self, h: int, w: int, device="cpu", store_dtype=torch.float32):
        self.h, self.w = h, w
        self.device = torch.device(device)
        self.store_dtype = store_dtype
        self.edges: Dict[Tuple[int, int], Tuple[torch.Tensor, torch.Tensor]] = {}
        self.age: Dict[Tuple[int, int], int] = {}
        self.kind: Dict[Tuple[int, int], str] = {}
        self._grid = pixel_grid(h, w, device=self.device)

    def __len__(self) -> int:
        return len(self.edges)

    def __contains__(self, e) -> bool:
        return tuple(e) in self.edges

    def add(self, i: int, j: int, flow: torch.Tensor, weight: torch.Tensor,
            kind: str = "odometry") -> None:
        """Add edge i -> j from a flow (h, w, 2) BA pixels and weight (h, w, 2)."""
        tgt = (self._grid + flow.to(self.device, torch.float32)).to(self.store_dtype)
        self.edges[(int(i), int(j))] = (tgt, weight.to(self.device, self.store_dtype))
        self.age[(int(i), int(j))] = 0
        self.kind[(int(i), int(j))] = kind

    def flow(self, i: int, j: int) -> torch.Tensor:
        """The measured flow (h, w, 2) of edge i -> j (target minus the pixel grid)."""
        return self.edges[(int(i), int(j))][0].float() - self._grid

    def remove(self, pairs: Iterable[Tuple[int, int]]) -> None:
        for p in list(pairs):
            self.edges.pop(p, None)
            self.age.pop(p, None)
            self.kind.pop(p, None)

    def remove_node(self, k: int) -> None:
        self.remove([e for e in self.edges if k in e])

    def pairs(self) -> List[Tuple[int, int]]:
        return list(self.edges.keys())

    def neighbours(self, k: int) -> List[int]:
        return sorted({j for (i, j) in self.edges if i == k} | {i for (i, j) in self.edges if j == k})

    def gather(self, ids: Sequence[int], pairs: Optional[Sequence[Tuple[int, int]]] = None,
               ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, list]:
        """Edges with both ends in ``ids`` -> local (ii, jj) indices into ``ids``,
        stacked targets (E, h, w, 2) and weights; also the list of pairs."""
        pos = {k: n for n, k in enumerate(ids)}
        sel = [p for p in (pairs if pairs is not None else self.edges)
               if p[0] in pos and p[1] in pos and p in self.edges]
        if not sel:
            z = torch.zeros(0, dtype=torch.long, device=self.device)
            e = torch.zeros(0, self.h, self.w, 2, device=self.device)
            return z, z, e, e, []
        ii = torch.tensor([pos[p[0]] for p in sel], dtype=torch.long, device=self.device)
        jj = torch.tensor([pos[p[1]] for p in sel], dtype=torch.long, device=self.device)
        tgt = torch.stack([self.edges[p][0] for p in sel]).float()
        wgt = torch.stack([self.edges[p][1] for p in sel]).float()
        return ii, jj, tgt, wgt, sel

    def age_edges(self, pairs: Iterable[Tuple[int, int]]) -> None:
        for p in pairs:
            if p in self.age:
                self.age[p] += 1

    def prune(self, keep_ids: Iterable[int], max_age: int, max_factors: int,
              protect: Iterable[int] = ()) -> None:
        """Drop edges leaving ``keep_ids``, older than ``max_age`` (unless they
        touch a ``protect``-ed node), then the oldest until ``max_factors`` remain."""
        keep = set(keep_ids)
        prot = set(protect)
        self.remove([p for p in self.edges if p[0] not in keep or p[1] not in keep])
        self.remove([p for p, a in self.age.items()
                     if a > max_age and not (p[0] in prot or p[1] in prot)
                     and abs(p[0] - p[1]) > 1])
        if len(self.edges) > max_factors:
            # oldest first, consecutive (odometry backbone) edges last
            order = sorted(self.edges, key=lambda p: (abs(p[0] - p[1]) <= 1, -self.age[p]))
            self.remove(order[: len(self.edges) - max_factors])


def proximity_pairs(ids: Sequence[int], poses: torch.Tensor, disps: torch.Tensor, intr,
                    sources: Sequence[int], thresh: float, max_pairs: int,
                    exclude: Iterable[Tuple[int, int]] = (), min_gap: int = 1,
                    nms: int = 0, stride: int = 4) -> List[Tuple[int, int, float]]:
    """Candidate edges (i, j) between ``sources`` and all ``ids`` ranked by the
    mean flow the current estimate induces (BA pixels, symmetric mean); keeps
    those below ``thresh`` with ``|i - j| >= min_gap``, not in ``exclude``, with
    non-maximum suppression of radius ``nms`` around already chosen pairs
    (in keyframe ids); at most ``max_pairs``. Returns (i, j, distance)."""
    pos = {k: n for n, k in enumerate(ids)}
    excl = {tuple(p) for p in exclude}
    cand = [(s, k) for s in sources for k in ids
            if s != k and abs(s - k) >= min_gap and (s, k) not in excl and (k, s) not in excl]
    # deduplicate unordered pairs
    seen = set()
    uniq = []
    for a, b in cand:
        key = (min(a, b), max(a, b))
        if key not in seen:
            seen.add(key)
            uniq.append(key)
    if not uniq:
        return []
    ii = torch.tensor([pos[a] for a, _ in uniq], device=disps.device)
    jj = torch.tensor([pos[b] for _, b in uniq], device=disps.device)
    d1 = induced_flow_distance(poses, disps, intr, ii, jj, stride=stride)
    d2 = induced_flow_distance(poses, disps, intr, jj, ii, stride=stride)
    dist = 0.5 * (d1 + d2)
    order = torch.argsort(dist).tolist()
    chosen: List[Tuple[int, int, float]] = []
    for n in order:
        dval = float(dist[n])
        if dval > thresh or len(chosen) >= max_pairs:
            break
        a, b = uniq[n]
        if nms > 0 and any(abs(a - c) <= nms and abs(b - e) <= nms for c, e, _ in chosen):
            continue
        chosen.append((a, b, dval))
    return chosen
