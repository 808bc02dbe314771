"""Loop detection and loop BA (paper §3.1 "Loop Closure") of :class:`LoopCloser`.

Loop detection: the mean flow that the current estimate induces between the active
keyframes (the last ``loop_window``) and every older keyframe; pairs below ``tau_loop``
(``loop_flow_thresh``) and more than ``tau_t`` (``loop_time_gap``) keyframes apart become
candidates. Each candidate's flow is measured (DIS from scratch and initialised with the
induced flow, the more confident kept) and, if confident, added to the graph - in both
directions: the old keyframe's settled disparity pins the loop's scale, which one edge from
the active side alone leaves free. Loop BA (Eq. 1) then runs over the active keyframes and
their loop nodes (with their temporal neighbours); the older side is held fixed as the
gauge, all disparities move. A loop whose edges still do not fit afterwards is rejected.

:class:`LoopDetection` is a part of :class:`~splat_slam_ros.tracking.loop_closure.LoopCloser`
and works on that object's state.
"""
from __future__ import annotations

import logging
import time
from typing import List, Tuple

import torch

from splat_slam_ros.tracking.dense_ba import reproject
from splat_slam_ros.tracking.factor_graph import proximity_pairs
from splat_slam_ros.types import UpdateEvent

log = logging.getLogger(__name__)


class LoopDetection:
    """Loop candidates by induced flow, their flow edges and the loop BA of the loop closer."""

    def _edge_rms(self, pair, poses=None, disps=None, ids=None) -> float:
        """Weighted RMS reprojection error (BA px) of one stored edge."""
        a, o = pair
        if poses is None:
            ids = [a, o]
            poses, disps = self.kfs.stack(ids)
        pos = {k: n for n, k in enumerate(ids)}
        tgt, wgt = self.graph.edges[(a, o)]
        uv, valid = reproject(poses, disps, self.intr, torch.tensor([pos[a]], device=self.device),
                              torch.tensor([pos[o]], device=self.device))
        r = (uv[0] - tgt.float()).norm(dim=-1)
        wm = wgt.float().mean(-1) * valid[0]
        return float(((r ** 2 * wm).sum() / wm.sum().clamp_min(1e-9)) ** 0.5)

    def detect(self) -> List[Tuple[int, int, float]]:
        """Loop candidates (active, old, induced distance) by the Sec. 3.1 criteria."""
        tc = self.tc
        ids = self.kfs.ids                     # (ids need not be contiguous: merges, a
        if not ids or ids[-1] - ids[0] <= tc.loop_time_gap:      # loaded map's keyframes)
            return []
        active = self.kfs.ids[-tc.loop_window:]
        old = [k for k in self.kfs.with_prep() if k < active[-1] - tc.loop_time_gap]
        if not old:
            return []
        cand_ids = sorted(set(active) | set(old))
        P, D = self.kfs.stack(cand_ids)
        excl = set(self.loop_pairs) | set(self.checked) | set(self.graph.pairs())
        cands = proximity_pairs(cand_ids, P, D, self.intr, active, tc.loop_flow_thresh * self.px_scale,
                                max_pairs=10 * max(tc.loop_max_edges, 1), exclude=excl,
                                min_gap=tc.loop_time_gap + 1, nms=0, stride=4)
        # keep (active, old) orientation, non-maximum suppression in id space
        out: List[Tuple[int, int, float]] = []
        for a, b, d in cands:
            act, o = (b, a) if a < b else (a, b)
            if o not in old:
                continue
            if any(abs(act - x) <= tc.loop_nms and abs(o - y) <= tc.loop_nms for x, y, _ in out):
                continue
            out.append((act, o, d))
            if len(out) >= tc.loop_max_edges:
                break
        return out

    def _close_loops(self) -> List[UpdateEvent]:
        tc = self.tc
        cands = self.detect()
        if not cands:
            return []
        added = []
        for act, o, d in cands:
            fc = self._measure(act, o, kind="loop", both=True, mode="scratch")
            self.checked.add((act, o))
            if fc is not None and fc.ok and fc.valid_frac >= 0.5 * self.motion.typical_valid_frac:
                added.append((act, o))
        if not added:
            return []
        # a loop the current estimate already agrees with needs no loop BA: keep its
        # edges for the global BA (saves most loop BAs when there is little drift)
        fits = [self._edge_rms(p) < self.tc.loop_fit_rms for p in added]
        if all(fits):
            self.loop_pairs.update(added)
            self.n_loops += len(added)
            log.info("loop closure: %d edge(s) %s already consistent, no loop BA",
                     len(added), added)
            return []
        active = self.kfs.ids[-tc.loop_window:]
        nodes = set(active)
        for act, o in added:
            nodes.add(o)
            nodes.update(n for n in self.graph.neighbours(o) if abs(n - o) <= 2)
        for p in self.loop_pairs:
            if p[0] in nodes or p[1] in nodes:
                nodes.update(p)
        ids = sorted(nodes)
        # the older side (loop nodes and their neighbours) holds the gauge and the
        # scale; the active keyframes move onto it (their disparities all move)
        act_set = set(active)
        fixed = self._gauge(ids, torch.tensor([k not in act_set for k in ids], device=self.device))
        before = self.kfs.snapshot(ids)
        t0 = time.perf_counter()
        res = self._optimize(ids, tc.loop_ba_iters, fixed=fixed, normalize=True)
        self.timings["loop_ba"] += time.perf_counter() - t0
        if res is None:
            return []
        P, D, infos, pairs = res
        # verify: the new loop edges must fit after the loop BA
        ok_pairs = []
        for act, o in added:
            rms = self._edge_rms((act, o), P, D, ids)
            if rms < max(4 * infos[-1].rms, 0.5):
                ok_pairs.append((act, o))
            else:
                self.graph.remove([(act, o), (o, act)])
        if not ok_pairs:
            return []
        if len(ok_pairs) < len(added):      # re-run without the rejected edges
            res = self._optimize(ids, tc.loop_ba_iters, fixed=fixed, normalize=True)
            P, D, infos, pairs = res
        self.kfs.write_back(ids, P, D)
        self.loop_pairs.update(ok_pairs)
        self.n_loops += len(ok_pairs)
        log.info("loop closure: %d edge(s) %s, loop BA rms %.3f BA px over %d keyframes",
                 len(ok_pairs), ok_pairs, infos[-1].rms, len(ids))
        return self._event("loop_closure", before)
