"""Full trajectory: poses of the non-keyframes (paper Sec. 3.1 / reference "trajectory filler").

Every tracked frame remembers its reference keyframe, the flow from that
keyframe into it (BA grid, stored as float16) and its pose relative to the
keyframe when it was tracked. At the end (or whenever asked) each frame's pose
is initialised from the keyframe's *current* pose (after local BA, loop
closure and global BA) - or, for frames without a usable flow (lost frames),
by interpolation between the neighbouring keyframes in time - and refined by
a short pose-only Gauss-Newton against its flow with the keyframe's current
disparity (the target-pose block of Eq. 1).

The records are the tracker's (:class:`TrajectoryRecorder`): a non-keyframe tracked against
the newest keyframe also gets the flow from the next keyframe once that exists, so that it
is aligned against a keyframe on both sides; at the end of input the last frame becomes a
keyframe when it moved enough since the last one.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.geometry import pixel_grid, se3_exp, se3_inverse, se3_log
from splat_slam_ros.runtime import limit_threads
from splat_slam_ros.tracking.dense_ba import pose_only_refine_batch
from splat_slam_ros.types import Frame, UpdateEvent


@dataclass
class FrameRecord:
    index: int
    timestamp: float
    kf_id: Optional[int] = None              # set when the frame is a keyframe
    ref_kf: Optional[int] = None             # reference keyframe of a non-keyframe
    rel_pose: Optional[np.ndarray] = None    # T_ref^-1 T_frame when tracked (None: unknown)
    ref_scale: float = 1.0                   # mean disparity of the reference when tracked
    flow: Optional[torch.Tensor] = None      # (h, w, 2) float16, ref -> frame, BA pixels
    weight: Optional[torch.Tensor] = None    # (h, w, 2) float16
    lost: bool = False
    online_pose: Optional[np.ndarray] = None
    ref2_kf: Optional[int] = None            # the next keyframe (set once it exists)
    flow2: Optional[torch.Tensor] = None     # (h, w, 2) float16, ref2 -> frame, BA pixels
    weight2: Optional[torch.Tensor] = None
    skipped: bool = False                    # live input, tracker busy: never tracked (posed
                                             # between its neighbours, _interpolate_skipped)


def se3_interpolate(T0: torch.Tensor, T1: torch.Tensor, a: float) -> torch.Tensor:
    """Geodesic interpolation T0 exp(a log(T0^-1 T1)) of camera-to-world poses."""
    return T0 @ se3_exp(a * se3_log(se3_inverse(T0) @ T1))


def interpolate_from_keyframes(ts: float, kf_ts: np.ndarray, kf_poses: torch.Tensor
                               ) -> torch.Tensor:
    """Pose at time ``ts`` from keyframes sorted by time (clamped at the ends)."""
    n = len(kf_ts)
    k = int(np.searchsorted(kf_ts, ts))
    if k <= 0:
        return kf_poses[0].clone()
    if k >= n:
        return kf_poses[-1].clone()
    t0, t1 = kf_ts[k - 1], kf_ts[k]
    a = 0.0 if t1 <= t0 else float((ts - t0) / (t1 - t0))
    return se3_interpolate(kf_poses[k - 1], kf_poses[k], a)


def fill_trajectory(records: List[FrameRecord], kf_poses: Dict[int, torch.Tensor],
                    kf_disps: Dict[int, torch.Tensor], intr, iters: int = 3,
                    huber: Optional[float] = None) -> Tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and camera-to-world poses (N, 4, 4) of every recorded frame
    that can be placed (frames before the first keyframe pose exist are skipped).
    The non-keyframes' motion-only alignments are solved together
    (:func:`pose_only_refine_batch`)."""
    known = sorted(k for k in kf_poses)
    if not known:
        return np.zeros(0), np.zeros((0, 4, 4))
    by_id = {r.kf_id: r for r in records if r.kf_id is not None}
    # interpolation in time between the keyframes recorded here (a loaded map's keyframes
    # are references of tracked frames but have no time in this input)
    timed = [k for k in known if k in by_id]
    kf_ts = np.array([by_id[k].timestamp for k in timed])
    order = np.argsort(kf_ts)
    kf_ts = kf_ts[order]
    stack = torch.stack([kf_poses[timed[o]].to(torch.float64).cpu() for o in order]) \
        if timed else None
    pose = {k: kf_poses[k].to(torch.float64).cpu() for k in known}
    disp = {k: kf_disps[k].float().cpu() for k in known if k in kf_disps}
    ts_out, poses_out, fit, skipped = [], [], [], []
    for r in records:
        if r.skipped:
            skipped.append(len(poses_out))
            ts_out.append(r.timestamp)
            poses_out.append(None)
            continue
        if r.kf_id is not None and r.kf_id in kf_poses:
            ts_out.append(r.timestamp)
            poses_out.append(pose[r.kf_id])
            continue
        # a keyframe gone since (a warm-up that started again) is placed as a lost frame
        lost = r.kf_id is not None or r.lost or r.ref_kf not in pose or r.ref_kf not in disp \
            or r.flow is None
        if stack is None and (lost or r.rel_pose is None):   # nothing to place it by
            continue
        ts_out.append(r.timestamp)
        if lost:
            poses_out.append(interpolate_from_keyframes(r.timestamp, kf_ts, stack))
            continue
        if r.rel_pose is not None:
            rel = torch.as_tensor(r.rel_pose, dtype=torch.float64).clone()
            s_now = float(disp[r.ref_kf].mean())
            if s_now > 0 and r.ref_scale > 0:
                rel[:3, 3] *= r.ref_scale / s_now      # follow a disparity rescale
            T = pose[r.ref_kf] @ rel
        else:
            T = interpolate_from_keyframes(r.timestamp, kf_ts, stack)
        fit.append((len(poses_out), r))
        poses_out.append(T)
    if fit:
        _refine(fit, poses_out, pose, disp, intr, iters, huber)
    if skipped:
        _interpolate_skipped(ts_out, poses_out, skipped, kf_ts, stack)
    return (np.asarray(ts_out, dtype=np.float64),
            torch.stack(poses_out).numpy().astype(np.float64) if poses_out
            else np.zeros((0, 4, 4)))


def _interpolate_skipped(ts_out, poses_out, skipped, kf_ts, kf_stack) -> None:
    """Frames the tracker skipped (live input, busy) take the geodesic interpolation between
    the nearest posed frames before and after them in time (in place); at the ends of the
    trajectory, between the nearest keyframes."""
    ts = np.asarray(ts_out, dtype=np.float64)
    have = np.array([p is not None for p in poses_out])
    known = np.flatnonzero(have)
    kt = ts[known]
    order = np.argsort(kt, kind="stable")
    known, kt = known[order], kt[order]
    for i in skipped:
        k = int(np.searchsorted(kt, ts[i]))
        if 0 < k < len(kt) and kt[k] > kt[k - 1]:
            a = (ts[i] - kt[k - 1]) / (kt[k] - kt[k - 1])
            poses_out[i] = se3_interpolate(poses_out[known[k - 1]], poses_out[known[k]],
                                           float(a))
        elif kf_stack is not None:
            poses_out[i] = interpolate_from_keyframes(float(ts[i]), kf_ts, kf_stack)
        else:                           # no keyframe of this input: the nearest posed frame
            poses_out[i] = poses_out[known[min(k, len(known) - 1)]].clone()


def _refine(fit, poses_out, pose, disp, intr, iters, huber, max_cells: int = 1 << 14):
    """Pose-only alignment (Eq. 1 target block) of the frames in ``fit`` (index into
    ``poses_out``, record) against their reference keyframe and, where it has one, the next
    keyframe (two edges); ``poses_out`` is updated in place. Solved in batches of
    ``max_cells`` BA cells, so the flows are stacked a batch at a time."""
    h, w = fit[0][1].flow.shape[:2]
    grid = pixel_grid(h, w)
    step = max(1, max_cells // (2 * h * w))
    for s in range(0, len(fit), step):
        batch = fit[s:s + step]
        refs, disps, flows, wts, n_it = [], [], [], [], []
        for _i, r in batch:
            two = r.flow2 is not None and r.ref2_kf in pose and r.ref2_kf in disp
            k2 = r.ref2_kf if two else r.ref_kf
            refs.append(torch.stack([pose[r.ref_kf], pose[k2]]))
            disps.append(torch.stack([disp[r.ref_kf], disp[k2]]))
            flows.append(torch.stack([r.flow, r.flow2 if two else r.flow]).float())
            w2 = r.weight2 if two else torch.zeros_like(r.weight)  # a missing edge weighs 0
            wts.append(torch.stack([r.weight, w2]).float())
            n_it.append(iters + (0 if r.rel_pose is not None else 3))
        T = pose_only_refine_batch(torch.stack(refs), torch.stack(disps),
                                   torch.stack([poses_out[i] for i, _ in batch]), intr,
                                   grid + torch.stack(flows), torch.stack(wts),
                                   torch.tensor(n_it), huber=huber)
        for (i, _r), Ti in zip(batch, T):
            poses_out[i] = Ti


class TrajectoryRecorder:
    """The tracker's frame records for :func:`fill_trajectory`: one per input frame, the
    flows of each non-keyframe from its reference keyframe and, once it exists, from the
    next keyframe; the full and keyframe trajectories. A part of
    :class:`~splat_slam_ros.tracking.tracker.Tracker` working on that object's state."""

    def _record(self, frame: Frame, replace: bool = False, **kw) -> FrameRecord:
        r = FrameRecord(frame.index, float(frame.timestamp), **kw)
        if replace:     # a frame recorded as a non-keyframe, promoted later (finalize)
            old = [n for n, x in enumerate(self.records) if x.index == frame.index]
            if old:
                self.records[old[-1]] = r
                return r
        self.records.append(r)
        # bound memory on long live runs: older frames keep only their relative pose
        old = len(self.records) - 1 - self.tc.max_stored_flows
        if old >= 0:
            self.records[old].flow = self.records[old].weight = None
            self.records[old].flow2 = self.records[old].weight2 = None
        return r

    def skip(self, index: int, timestamp: float, frame: Optional[Frame] = None) -> np.ndarray:
        """A frame not tracked (live, busy): placed between its tracked neighbours later.
        With its ``frame`` it is kept (``tracking.bridge_frames``) until the next frame is
        tracked, which may track it after all to bridge a large motion
        (:meth:`~splat_slam_ros.tracking.frontend.TrackerFrontend._bridge`)."""
        self.n_skipped += 1
        self.records.append(FrameRecord(int(index), float(timestamp), skipped=True))
        self.skipped_at.append((int(index), float(timestamp)))
        if frame is not None and self.initialized and self.tc.bridge_frames > 0:
            self._gap.append(frame)
            if len(self._gap) > self.tc.bridge_frames:   # thinned, spread over the gap
                self._gap = self._gap[::2]
        return self.predict()

    def _take_skipped(self, index: int) -> Tuple[int, FrameRecord]:
        """Remove the skipped record of frame ``index`` (to be tracked): its position and
        the record."""
        pos = next(n for n in range(len(self.records) - 1, -1, -1)
                   if self.records[n].index == index and self.records[n].skipped)
        self.n_skipped -= 1
        return pos, self.records.pop(pos)

    def _move_record(self, index: int, start: int, pos: int) -> None:
        """The record of frame ``index`` appended at ``start`` or later goes to ``pos`` (the
        place of its skipped record: the records stay in frame order)."""
        n = next(n for n in range(start, len(self.records)) if self.records[n].index == index)
        self.records.insert(pos, self.records.pop(n))

    def unskip(self, index: int) -> bool:
        """Frame ``index``, the newest and skipped, is to be tracked after all (the end of
        live input, the tracker free again): its skipped record goes, so that :meth:`track`
        records it. False (nothing changed) unless the newest record is that skipped frame."""
        if not self.records or not self.records[-1].skipped or self.records[-1].index != index:
            return False
        self.records.pop()
        self.n_skipped -= 1
        if self.skipped_at and self.skipped_at[-1][0] == index:
            self.skipped_at.pop()
        return True

    def _add_pending(self, rec: FrameRecord, frame, img, prep) -> None:
        if rec.ref_kf == self.window[-1]:
            self._pending.append((rec, prep))
        self._last_input = (frame, img, prep)

    def _next_keyframe_flows(self, kid: int) -> None:
        """Flows from the new keyframe into the non-keyframes tracked since the previous
        one (DIS started from the flow the current estimate induces), so that each is
        aligned against both neighbouring keyframes (:func:`fill_trajectory`)."""
        t0 = time.perf_counter()
        ks = self.kfs[kid]
        todo = []                   # (record, prepared image, induced flow or None)
        for rec, prep in self._pending:
            if rec.ref_kf not in self.kfs or rec.index == ks.frame_index:
                continue
            init = None                 # warm-up: no pose estimate yet
            if rec.rel_pose is not None:
                T = self.kfs[rec.ref_kf].pose @ torch.as_tensor(
                    rec.rel_pose, dtype=torch.float64, device=self.device)
                init = self._induced(ks.pose, ks.disp, T)
            todo.append((rec, prep, init))
        warm = [t for t in todo if t[2] is None]          # warm-up frames: two DIS calls each
        if 0 < self.tc.next_kf_flows < len(warm):
            drop = {id(t[0]) for t in warm[:-self.tc.next_kf_flows]}
            todo = [t for t in todo if id(t[0]) not in drop]
        fwd = [t for t in todo if t[2] is not None] \
            if hasattr(self.flow, "predict_forward_many") else []      # one DIS call each
        flows = dict(zip((id(t[0]) for t in fwd), self.flow.predict_forward_many(
            ks.prep, [t[1] for t in fwd], [t[2] for t in fwd]))) if fwd else {}
        tex = self._ref_tex(kid)
        need = self.motion.min_valid(tex)               # one keyframe: one threshold
        for rec, prep, init in todo:
            if id(rec) in flows:
                f, w = (x.to(self.device) for x in flows[id(rec)])
            else:
                f, w, _, _ = self._flows(ks.prep, prep, init)
            if self.motion.check(f, w, tex).valid_frac < need:
                continue
            rec.ref2_kf = kid
            rec.flow2, rec.weight2 = self._store_flow(f, w)
        self._pending = []
        self.timings["next_kf_flows"] += time.perf_counter() - t0

    def _last_frame_keyframe(self) -> List[UpdateEvent]:
        """End of input: the last frame becomes a keyframe when it moved since the last
        one (half the motion threshold), so the frames after the last keyframe are
        aligned against a keyframe on both sides too."""
        step = self._promote_last_input("final")
        if step is None:
            return []
        self.final_keyframes.extend(step.keyframes)
        return list(step.events)

    def _promote_last_input(self, cause: str):
        """The newest input frame, tracked against the newest keyframe and not a keyframe,
        becomes one (``cause``) when its flow from that keyframe, started from its pose, is
        confident and at least half the motion threshold: the keyframe's step, or None."""
        if not self._pending or self._last_input is None:
            return None
        frame, img, prep = self._last_input
        rec = self.records[-1]
        if rec.index != frame.index or rec.kf_id is not None or \
                rec.ref_kf != self.window[-1] or rec.rel_pose is None:
            return None             # (no pose: a warm-up frame after a late initialisation)
        ref = rec.ref_kf
        T = self.kfs[ref].pose @ torch.as_tensor(rec.rel_pose, dtype=torch.float64,
                                                 device=self.device)
        init = self._induced(self.kfs[ref].pose, self.kfs[ref].disp, T)
        f, w, fb, wb = self._flows(self.kfs[ref].prep, prep, init)
        fc = self.motion.check(f, w, self._ref_tex(ref))
        if not fc.ok or fc.mean_flow < 0.5 * self.motion.thresh:
            return None
        self._pending = [(r, p) for r, p in self._pending if r.index != frame.index]
        self._last_input = None
        return self._new_keyframe(frame, img, prep, ref, T, f, w, fb, wb, {}, force=True,
                                  cause=cause)

    def trajectory_keyframes(self) -> Tuple[np.ndarray, np.ndarray]:
        return self.kfs.trajectory(self.keyframe_ids())

    def trajectory_full(self) -> Tuple[np.ndarray, np.ndarray]:
        """(timestamps, poses) of every input frame (non-keyframes filled)."""
        t0 = time.perf_counter()
        if self.initialized:
            kp = {k: self.kfs[k].pose.cpu() for k in self.published}
            kd = {k: self.kfs[k].disp.cpu() for k in self.published}
        else:    # never initialised (static camera): everything at the first keyframe
            kp = {k: self.kfs[k].pose.cpu() for k in self.window[:1]}
            kd = {}
        with limit_threads(self.tc.threads):
            ts, poses = fill_trajectory(self.records, kp, kd, self.intr.cpu(),
                                        iters=self.tc.filler_iters, huber=self.huber)
        self.timings["filler"] += time.perf_counter() - t0
        return ts, poses
