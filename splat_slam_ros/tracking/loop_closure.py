"""Loop closure and online / final global BA (paper Sec. 3.1), as a self-contained stage.

In the ROS graph this runs in its own node, so :class:`LoopCloser` keeps its
own keyframe store (poses, disparities, flow-ready images) and its own flow
edges; the only coupling with the tracker is messages: keyframes in
(:meth:`add_keyframe`), pose/disparity updates in both directions
(:meth:`apply_update`, and the events returned by :meth:`step` /
:meth:`finalize`).

Loop detection by induced flow and loop BA: :mod:`loop_detection`. Here: the keyframe
store, odometry edges, update events, keyframe merging and the graph summary a session
keeps. Online global BA runs every ``global_ba_every`` keyframes;
``finalize`` runs the final global BA passes (stopping early once an iteration
gains less than 0.1 %). After each online global BA, settled keyframes that revisit an older
keyframe's view leave the graph and follow it rigidly (:mod:`keyframe_merge`), so a long
run in one place keeps a bounded graph.
"""
from __future__ import annotations

import itertools
import logging
import time
from collections import defaultdict
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.geometry import intr_tensor, pixel_grid, se3_inverse
from splat_slam_ros.imaging import flow_input
from splat_slam_ros.runtime import limit_threads, resolve_device
from splat_slam_ros.tracking import dense_ba
from splat_slam_ros.tracking.dense_ba import bundle_adjust, reproject
from splat_slam_ros.tracking.factor_graph import FactorGraph
from splat_slam_ros.tracking.flow_frontend import make_flow_predictor
from splat_slam_ros.tracking.global_ba import normalized_global_ba, spatial_pairs
from splat_slam_ros.tracking.keyframe_merge import MergedKeyframe, merge_candidates, splits
from splat_slam_ros.tracking.keyframe_set import KeyframeSet, KeyframeState
from splat_slam_ros.tracking.loop_detection import LoopDetection
from splat_slam_ros.tracking.motion_filter import MotionFilter, flow_scale
from splat_slam_ros.types import LOOP_SEQ_START, Intrinsics, KeyframeData, UpdateEvent

log = logging.getLogger(__name__)


class LoopCloser(LoopDetection):
    """Loop closure + global BA over its own keyframe store (see module docstring)."""

    def __init__(self, cfg: SlamConfig, intrinsics: Optional[Intrinsics] = None,
                 flow_predictor=None, seq_start: int = LOOP_SEQ_START):
        self.cfg = cfg
        self.tc = tc = cfg.tracking
        self.device = resolve_device(tc.device, "tracking.device")
        dense_ba.use_backend(tc.ba_backend, self.device)
        self.flow = flow_predictor if flow_predictor is not None else make_flow_predictor(tc)
        self.raw_intrinsics = intrinsics
        self.intr = None                       # BA-grid (fx, fy, cx, cy), from the keyframes
        self.h = self.w = 0
        self.graph: Optional[FactorGraph] = None
        self.kfs = KeyframeSet()               # pose, disparity, prepared image per keyframe
        self.loop_pairs: set = set()           # accepted loop edges (i, j)
        self.checked: set = set()              # candidate pairs already measured (rejected)
        self.new_since_gba: List[int] = []
        self.merged: Dict[int, MergedKeyframe] = {}   # redundant keyframes following a kept one
        self._seq = itertools.count(seq_start)      # update numbers (types.LOOP_SEQ_START)
        self.motion = MotionFilter(tc.motion_filter_thresh, min_valid_frac=tc.lost_min_valid)
        self.huber = tc.robust_huber_px / tc.ba_downsample if tc.robust_huber_px > 0 else None
        self.gate = tc.edge_gate_px / tc.ba_downsample
        self.timings: Dict[str, float] = defaultdict(float)
        self.n_loops = 0
        self.fixed_ids: set = set()            # a loaded map's keyframes (add_fixed)
        self.loaded_edges: List[List] = []     # its graph's edges (restore_graph_summary)

    # ------------------------------------------------------------ inputs
    def _setup(self, kd: KeyframeData) -> None:
        h, w = kd.disparity.shape                  # the tracker's BA grid (any image size)
        bi = kd.intrinsics.resized(w, h)
        self.intr = intr_tensor(bi, torch.float32, self.device)
        self.px_scale = flow_scale(self.intr)      # thresholds are in reference BA px
        self.h, self.w = h, w
        self.graph = FactorGraph(h, w, self.device)
        self.grid = pixel_grid(h, w, device=self.device)

    def add_keyframe(self, kf: KeyframeData) -> None:
        """Store a new keyframe and measure its odometry edges to the previous ones."""
        if self.graph is None:
            self._setup(kf)
        with limit_threads(self.tc.threads):
            t0 = time.perf_counter()
            k = int(kf.kf_id)
            prev = [i for i in self.kfs.ids if i < k][-max(self.tc.global_ba_radius, 1):]
            self._store(kf)
            self.new_since_gba.append(k)
            for n, p in enumerate(reversed(prev)):
                # the previous keyframe in both directions, further ones k -> p only
                self._measure(p, k, kind="odometry", both=(n == 0), gate=self.gate)
            self._evict()
            self.timings["add"] += time.perf_counter() - t0

    def add_fixed(self, kf: KeyframeData) -> None:
        """A keyframe of a loaded map (extend runs): stored without edges of its own and held
        fixed in every BA, so loops from new keyframes to it pull the new ones onto the
        loaded map (never the reverse)."""
        if self.graph is None:
            self._setup(kf)
        self._store(kf)
        self.fixed_ids.add(int(kf.kf_id))

    def _store(self, kf: KeyframeData) -> None:
        """Pose, disparity and the flow-ready image of a keyframe."""
        self.kfs.add(int(kf.kf_id), KeyframeState(
            torch.as_tensor(np.asarray(kf.pose), dtype=torch.float64, device=self.device),
            torch.as_tensor(np.asarray(kf.disparity), dtype=torch.float32, device=self.device),
            int(kf.frame_index), float(kf.timestamp), prep=self.flow.prepare(
                flow_input(kf.image, kf.disparity.shape, self.tc.ba_downsample))))

    def _gauge(self, ids: Sequence[int], fixed: torch.Tensor) -> torch.Tensor:
        """``fixed`` (a mask over ``ids``) plus a loaded map's keyframes; at least two."""
        fixed = fixed | torch.tensor([k in self.fixed_ids for k in ids], device=self.device)
        if int(fixed.sum()) < 2:
            fixed[:2] = True
        return fixed

    def _evict(self) -> None:
        """Bound the store to ``keyframe_buffer`` keyframes (oldest images dropped first)."""
        cap = self.tc.keyframe_buffer
        ids = self.kfs.ids
        for k in ids[: max(len(ids) - cap, 0)]:
            self.kfs.drop_prep(k)

    def apply_update(self, ev: UpdateEvent) -> None:
        """Pose/disparity changes made elsewhere (the tracker's local BA)."""
        for n, k in enumerate(ev.kf_ids):
            k = int(k)
            if k not in self.kfs:
                continue
            self.kfs[k].pose = torch.as_tensor(np.asarray(ev.poses[n]), dtype=torch.float64,
                                            device=self.device)
            if ev.disparities is not None:
                self.kfs[k].disp = torch.as_tensor(np.asarray(ev.disparities[n]),
                                                dtype=torch.float32, device=self.device)

    # ------------------------------------------------------------ helpers
    def _induced_pair(self, a, b):
        P, D = self.kfs.stack([a, b])
        uv, _ = reproject(P, D, self.intr, torch.tensor([0, 1], device=self.device),
                          torch.tensor([1, 0], device=self.device))
        return uv - self.grid

    def _measure(self, a: int, b: int, kind: str, both: bool = True, mode: str = "induced",
                 gate: float = 0.0):
        """Measure flow a <-> b and add the edge(s); returns the FlowCheck or None.

        ``mode``: ``"induced"`` pre-warps DIS by the flow the current estimate
        induces (large but predictable displacements: the tracker's poses are
        good), falling back to DIS from scratch if that is not confident;
        ``"scratch"`` the other way round (loop candidates, where drift can make
        the induced flow worse than none). The more confident result is kept.
        ``gate`` (BA px, > 0): cells whose measured flow is further than this
        from the induced one get zero weight (DIS locking onto a wrong period
        of a repetitive texture is confident but wrong)."""
        if not (a in self.kfs and b in self.kfs) or self.kfs[a].prep is None \
                or self.kfs[b].prep is None:
            return None
        from splat_slam_ros.tracking.flow_frontend import predict_both
        t0 = time.perf_counter()
        init = self._induced_pair(a, b)
        order = ["induced", "scratch"] if mode == "induced" else ["scratch", "induced"]
        if not hasattr(self.flow, "predict_pair"):
            order = ["scratch"]
        best = None
        for how in order:
            if how == "scratch":
                res = predict_both(self.flow, self.kfs[a].prep, self.kfs[b].prep)
            else:
                res = self.flow.predict_pair(self.kfs[a].prep, self.kfs[b].prep,
                                             init_ij=init[0].cpu(), init_ji=init[1].cpu())
            f, w, fb, wb = (x.to(self.device) for x in res)
            if gate > 0:
                w = w * ((f - init[0]).norm(dim=-1, keepdim=True) < gate)
                wb = wb * ((fb - init[1]).norm(dim=-1, keepdim=True) < gate)
            fc = self.motion.check(f, w)
            if best is None or fc.valid_frac > best[0].valid_frac:
                best = (fc, f, w, fb, wb)
            if fc.ok and fc.valid_frac >= 0.6 * self.motion.typical_valid_frac:
                break
        self.timings["flow"] += time.perf_counter() - t0
        fc, f, w, fb, wb = best
        if not fc.ok:
            return fc
        self.graph.add(a, b, f, w, kind=kind)
        if both:
            self.graph.add(b, a, fb, wb, kind=kind)
        return fc

    def _event(self, reason: str, before: Dict[int, Tuple[torch.Tensor, torch.Tensor]]
               ) -> List[UpdateEvent]:
        """Updates for the keyframes that changed since ``before``, then (poses only) for
        the merged keyframes that follow a changed one or were merged since ``before``."""
        ids = self.kfs.changed(before, self.tc.event_pose_thresh, self.tc.event_disp_thresh)
        out = [self.kfs.update_event(next(self._seq), reason, ids)] if ids else []
        moved = set(ids)
        follow = [k for k, m in sorted(self.merged.items()) if m.anchor in moved or k in before]
        if follow:
            out.append(UpdateEvent(seq=next(self._seq), reason=reason, kf_ids=follow,
                                   poses=np.stack([self.merged_pose(k).cpu().numpy()
                                                   for k in follow])))
        return out

    def merged_pose(self, k: int) -> torch.Tensor:
        m = self.merged[k]
        return self.kfs[m.anchor].pose @ m.rel

    def _merge_redundant(self) -> List[int]:
        """Merge settled keyframes that revisit an older kept one (:mod:`keyframe_merge`)."""
        tc = self.tc
        ids = self.kfs.ids
        settle = max(tc.loop_window, tc.global_ba_radius + 1)
        P, D = self.kfs.stack(ids)
        cands = merge_candidates(ids, P, D, self.intr, self.graph.kind, settle,
                                 tc.merge_flow * self.px_scale, min_gap=tc.global_ba_radius + 1)
        done = []
        for k, o, _ in cands:
            if k not in self.kfs or o not in self.kfs or \
                    splits(self.graph.pairs(), self.kfs.ids, k):
                continue
            rel = se3_inverse(self.kfs[o].pose) @ self.kfs[k].pose      # frozen T_o^-1 T_k
            for m in self.merged.values():              # followers of k now follow o
                if m.anchor == k:
                    m.anchor, m.rel = o, rel @ m.rel
            self._detach(k, o, rel, self.kfs[k].timestamp)
            done.append(k)
        if done:
            log.info("merged %d redundant keyframe(s) %s; %d kept, %d merged", len(done), done,
                     len(self.kfs), len(self.merged))
        return done

    def _detach(self, k: int, anchor: int, rel: torch.Tensor, timestamp: float) -> None:
        """Keyframe ``k`` leaves the BA graph and follows ``anchor`` (T_k = T_anchor rel)."""
        self.merged[k] = MergedKeyframe(anchor, rel, timestamp)
        self.graph.remove_node(k)
        self.kfs.remove(k)
        self.loop_pairs = {p for p in self.loop_pairs if k not in p}
        self.checked = {p for p in self.checked if k not in p}

    def loop_stats(self) -> dict:
        """Keyframes merged into older views, loop edges, and loop edges from a new keyframe
        to a loaded map's (extend runs)."""
        return {"merged": len(self.merged), "loop_edges": len(self.loop_pairs),
                "loop_edges_to_loaded": sum(1 for p in self.loop_pairs
                                            if len(set(p) & self.fixed_ids) == 1)}

    def graph_summary(self) -> dict:
        """The loop-closure graph as a session keeps it: its edges ([i, j, kind]: odometry,
        loop, global), the accepted loop pairs and the merged keyframes; with a loaded map's
        (restore_graph_summary) included."""
        edges = {(int(i), int(j)): str(k) for i, j, k in self.loaded_edges}
        edges.update({(int(i), int(j)): str(k) for (i, j), k in
                      (self.graph.kind.items() if self.graph is not None else ())})
        return {"edges": [[i, j, k] for (i, j), k in sorted(edges.items())],
                "loop_pairs": sorted([int(a), int(b)] for a, b in self.loop_pairs),
                "merged": self.merged_list()}

    def restore_graph_summary(self, summary: Optional[dict]) -> None:
        """A loaded map's :meth:`graph_summary` (after :meth:`add_fixed`): its loop pairs
        count as found and checked, its edges are kept for the next session. Their flow
        terms are not measured again: between fixed keyframes they would move nothing."""
        if not summary:
            return

        def loaded(p) -> bool:
            return int(p[0]) in self.fixed_ids and int(p[1]) in self.fixed_ids
        self.loaded_edges = [e for e in summary.get("edges", []) if loaded(e)]
        pairs = {(int(a), int(b)) for a, b in summary.get("loop_pairs", []) if loaded((a, b))}
        self.loop_pairs |= pairs
        self.checked |= pairs

    def merged_list(self) -> List[List]:
        """[kf_id, anchor, timestamp] of every merged keyframe (a checkpoint's part)."""
        return [[int(k), int(m.anchor), float(m.timestamp)] for k, m in sorted(self.merged.items())]

    def restore_merged(self, entries: Sequence[Sequence]) -> None:
        """Merge again, after a restart, the keyframes of :meth:`merged_list`; their stored
        poses (kept current by the follower updates) give the frozen relative pose."""
        for k, anchor, ts in sorted((int(a), int(b), float(c)) for a, b, c in entries):
            if k in self.kfs and anchor in self.kfs:
                self._detach(k, anchor, se3_inverse(self.kfs[anchor].pose) @ self.kfs[k].pose,
                             ts)

    def _optimize(self, ids: Sequence[int], iters: int, fixed: int, normalize: bool):
        ii, jj, tgt, wgt, pairs = self.graph.gather(ids)
        if not pairs:
            return None
        P, D = self.kfs.stack(ids)
        if normalize:
            P, D, infos = normalized_global_ba(P, D, self.intr, ii, jj, tgt, wgt, iters,
                                               fixed=fixed, huber=self.huber)
        else:
            P, D, infos = bundle_adjust(P, D, self.intr, ii, jj, tgt, wgt, iters=iters,
                                        fixed=fixed, huber=self.huber)
        return P, D, infos, pairs

    # ------------------------------------------------------------ global BA
    def _add_spatial_edges(self) -> None:
        tc = self.tc
        ids = self.kfs.ids
        if len(ids) < 3:
            return
        P, D = self.kfs.stack(ids)
        sources = [k for k in self.new_since_gba if k in self.kfs and self.kfs[k].prep is not None]
        pairs = spatial_pairs(ids, P, D, self.intr, sources, tc.global_ba_radius,
                              tc.global_ba_thresh * self.px_scale, tc.global_ba_max_edges,
                              exclude=set(self.graph.pairs()) | self.checked)
        for a, b, _ in pairs:
            new, old = (a, b) if a > b else (b, a)
            fc = self._measure(new, old, kind="global", both=False)
            self.checked.add((a, b))
            if fc is None or not fc.ok:
                continue

    def global_ba(self, iters: int, reason: str = "global_ba") -> List[UpdateEvent]:
        """Global BA over all stored keyframes (temporal + spatial + loop edges)."""
        if len(self.kfs) < 3:
            return []
        t0 = time.perf_counter()
        self._add_spatial_edges()
        self.new_since_gba = []
        ids = self.kfs.ids
        before = self.kfs.snapshot(ids)
        res = self._optimize(ids, iters, normalize=True, fixed=self._gauge(
            ids, torch.zeros(len(ids), dtype=torch.bool, device=self.device)))
        self.timings["global_ba"] += time.perf_counter() - t0
        if res is None:
            return []
        P, D, infos, pairs = res
        self.kfs.write_back(ids, P, D)
        log.info("global BA (%s): %d keyframes, %d edges, rms %.3f -> %.3f BA px", reason,
                 len(ids), len(pairs), infos[0].rms, infos[-1].rms)
        if reason == "global_ba" and self.tc.merge_flow > 0:
            self._merge_redundant()
        return self._event(reason, before)

    # ------------------------------------------------------------ public API
    def step(self) -> List[UpdateEvent]:
        """Loop detection + loop BA, and the online global BA when it is due."""
        if self.graph is None:
            return []
        events: List[UpdateEvent] = []
        with limit_threads(self.tc.threads):
            t0 = time.perf_counter()
            loop = []
            if self.tc.loop_closure:
                loop = self._close_loops()
                events += loop
            due = self.tc.global_ba and len(self.new_since_gba) >= self.tc.global_ba_every
            if due:
                events += self.global_ba(self.tc.global_ba_iters)
            self.timings["step"] += time.perf_counter() - t0
        return events

    def finalize(self) -> List[UpdateEvent]:
        """Final global BA (two passes, ``final_ba_iters``); one event per changed set."""
        if self.graph is None or not self.tc.global_ba:
            return []
        with limit_threads(self.tc.threads):
            if self.tc.loop_closure:
                pre = self._close_loops()
            else:
                pre = []
            start = self.kfs.snapshot(self.kfs.ids)
            for it in self.tc.final_ba_iters:
                self.global_ba(int(it), reason="final")
            ev = self._event("final", start)
        return pre + ev

    def trajectory_keyframes(self) -> Tuple[np.ndarray, np.ndarray]:
        """(timestamps, camera-to-world poses) of every keyframe, kept and merged, by id."""
        ts, P = self.kfs.trajectory(self.kfs.ids)
        if not self.merged:
            return ts, P
        rows = {k: (t, T) for k, t, T in zip(self.kfs.ids, ts, P)}
        rows.update({k: (m.timestamp, self.merged_pose(k).cpu().numpy())
                     for k, m in self.merged.items()})
        order = sorted(rows)
        return (np.array([rows[k][0] for k in order]), np.stack([rows[k][1] for k in order]))
