"""Initialisation of the tracker (paper §3.1): the warm-up before the first pose estimate.

Warm-up keyframes are taken by the motion filter (its threshold, or a view leaving the last
keyframe) until ``init_min_keyframes`` span ``init_parallax`` (or ``warmup`` keyframes
exist); the initialisation BA then starts from the identity and from a two-view start
(:mod:`two_view`), keeps the better one and normalises the mean disparity to 1. At the end of
input a late initialisation uses what was collected. After ``reinit_after`` lost frames a
new segment starts a new warm-up whose first keyframe is placed where the motion before the
loss leads, with the last keyframe's mean disparity.

:class:`TrackerInitialisation` is a part of :class:`~splat_slam_ros.tracking.tracker.Tracker`
and works on that object's state.
"""
from __future__ import annotations

import logging
import time
from typing import Dict

import numpy as np
import torch

from splat_slam_ros.geometry import se3_inverse
from splat_slam_ros.tracking.dense_ba import bundle_adjust
from splat_slam_ros.tracking.factor_graph import FactorGraph
from splat_slam_ros.tracking.flow_frontend import compose_flows
from splat_slam_ros.tracking.motion_filter import parallax, predict_pose
from splat_slam_ros.tracking.rolling_shutter import median_depth, readout_motion, rectify
from splat_slam_ros.tracking.two_view import two_view_start
from splat_slam_ros.types import Frame, TrackStep

log = logging.getLogger(__name__)

# a late initialisation (end of input) accepts this fraction of tracking.init_parallax
LATE_INIT_PARALLAX = 0.25


class TrackerInitialisation:
    """Warm-up, initialisation BA, late initialisation and new segments of the tracker."""

    def _warmup(self, frame, img, prep) -> TrackStep:
        eye = torch.eye(4, dtype=torch.float64, device=self.device)
        ones = torch.ones(self.h, self.w, device=self.device)
        if not self.window:
            kid = self._add_keyframe(frame, img, prep, eye, ones)
            self._record(frame, kf_id=kid)
            return TrackStep(frame.index, float(frame.timestamp), False, None,
                             eye.cpu().numpy(), initialized=False)
        ref = self.window[-1]
        init = self._last_flow[1] if self._last_flow is not None and \
            self._last_flow[0] == ref else None
        f, w, fb, wb = self._flows(self.kfs[ref].prep, prep, init)
        fc = self.motion.check(f, w, self._ref_tex(ref))
        if not fc.ok:
            self._last_flow = None
            if self.lost_count > 10:       # the first frames were bad: restart the warm-up
                log.warning("frame %d: restarting initialisation", frame.index)
                self._reset()
                return self._warmup(frame, img, prep)
            return self._lost(frame, f"low flow confidence ({fc.valid_frac:.2f})")
        self.lost_count = 0
        self._last_flow = (ref, f)
        info = {"mean_flow": fc.mean_flow, "valid": fc.valid_frac}
        # a warm-up keyframe at the motion threshold, or before the flow to the last one
        # fails (its confident cells down to keyframe_urgent_valid x their typical fraction:
        # forward motion, whose fast periphery fails while the mean flow stays low)
        if not self.motion.is_candidate(fc) and not self.motion.losing(fc):
            sf, sw = self._store_flow(f, w)
            self._add_pending(self._record(frame, ref_kf=ref, flow=sf, weight=sw), frame, img,
                              prep)
            if self._warm_best is None or fc.mean_flow > self._warm_best[0]:
                self._warm_best = (fc.mean_flow, frame, img, prep, (f, w, fb, wb))
            return TrackStep(frame.index, float(frame.timestamp), False, None,
                             eye.cpu().numpy(), initialized=False, info=info)
        self._warm_keyframe(frame, img, prep, ref, (f, w, fb, wb))
        if not self._ready_to_initialize(info):
            return TrackStep(frame.index, float(frame.timestamp), False, None,
                             eye.cpu().numpy(), initialized=False, info=info)
        return self._initialize(frame, info)

    def _warm_keyframe(self, frame, img, prep, ref, flows) -> int:
        """A warm-up keyframe (pose/disparity found by the initialisation BA)."""
        f, w, fb, wb = flows
        kid = self._add_keyframe(frame, img, prep, torch.eye(4, dtype=torch.float64),
                                 torch.ones(self.h, self.w))
        self.kfs[kid].conf = wb.mean(-1)
        self.graph.add(ref, kid, f, w)
        self.graph.add(kid, ref, fb, wb)
        # a late keyframe (finalize: _warm_best) was recorded as a non-keyframe already
        self._record(frame, replace=True, kf_id=kid)
        self._warm_best = None
        self._next_keyframe_flows(kid)
        return kid

    def _ready_to_initialize(self, info: Dict[str, float]) -> bool:
        """``init_min_keyframes`` span ``init_parallax``, or ``warmup`` keyframes are there."""
        n = len(self.window)
        if n >= max(self.tc.warmup, 2):
            return True
        if n < max(self.tc.init_min_keyframes, 2):
            return False
        par = self._window_parallax()
        info["init_parallax"] = par
        return par >= self.tc.init_parallax

    def _window_parallax(self) -> float:
        """Parallax (reference BA px) first -> newest warm-up keyframe (flows composed)."""
        flows, w = self._flows_from_first(self.window)
        return parallax(flows[-1], w, self.motion.cell_weight) / self.px_scale

    def _flows_from_first(self, ids):
        """Flows ids[0] -> ids[k] (BA px) composed along the chain; the first edge's weight."""
        flows = [self.graph.flow(ids[0], ids[1])]
        for a, b in zip(ids[1:-1], ids[2:]):
            flows.append(compose_flows(flows[-1], self.graph.flow(a, b)))
        return flows, self.graph.edges[(ids[0], ids[1])][1].float()

    def _new_segment(self, index: int) -> None:
        """Lost for ``tracking.reinit_after`` frames: a new warm-up and initialisation, its
        first keyframe where the constant-velocity motion before the loss leads, with the
        last keyframe's mean disparity (the scale carries over if the scene's depth does);
        published keyframes stay."""
        # (a tracker restored while lost has no motion before the loss: the last pose)
        T, vel, spacing = self._before_loss or (self.last_pose, self.velocity, (None, None))
        self._anchor = (predict_pose(T, vel, spacing, index),
                        float(self.kfs[self.window[-1]].disp.mean()))
        log.warning("frame %d: lost for %d frames: initialising again from here", index,
                    self.lost_count)
        for k in self.window:
            self.kfs.drop_prep(k)
            self.kfs.drop_image(k)
        self.initialized, self._last_flow = False, None
        self.n_segments += 1
        self._reset()

    def _reset(self) -> None:
        if self.published:              # a new segment: the published keyframes stay
            for k in [k for k in self.window if k not in self.published]:
                self.kfs.remove(k)
        else:
            self.kfs.clear()
        self.graph = FactorGraph(self.h, self.w, self.device)
        self.window = []
        self.lost_count = 0
        self.motion = self._motion_filter()
        self._warm_best = None
        self._pending = []
        self._rs_raw = {}

    def _init_ba(self, ids, poses, disps, ii, jj, tgt, wgt):
        """Initialisation BA from the identity and from the two-view start: the better one."""
        n = self.tc.init_iters
        best = bundle_adjust(poses, disps, self.intr, ii, jj, tgt, wgt, iters=n, fixed=1,
                             huber=self.huber)
        flows, w = self._flows_from_first(ids)
        start = two_view_start(flows, [w] * len(flows), self.intr, self.motion.cell_weight)
        if start is not None:
            alt = bundle_adjust(start.to(poses), disps, self.intr, ii, jj, tgt, wgt, iters=n,
                                fixed=1, huber=self.huber)
            log.info("initialisation BA: rms %.3f from the identity, %.3f from two views",
                     best[2][-1].rms, alt[2][-1].rms)
            if alt[2][-1].rms < best[2][-1].rms:
                best = alt
        return best

    def _rectify_warmup(self, ids, poses, disps):
        """Rolling shutter (camera.rolling_shutter_ms): the warm-up keyframes came before any
        motion estimate, unrectified, and the initialisation fixes the structure and scale
        that the later keyframes inherit. They are rectified now at the motion of the
        initialisation's poses (centred differences over the keyframes, each at its own
        median depth), their edges' flows measured again from the previous ones, and the
        initialisation BA continued."""
        for n, k in enumerate(ids):
            raw = self._rs_raw.pop(k, None)
            if raw is None:
                continue
            a, b = max(n - 1, 0), min(n + 1, len(ids) - 1)
            ks = self.kfs[k]
            w = readout_motion((se3_inverse(poses[a]) @ poses[b]).cpu().numpy(),
                               self.kfs[ids[b]].timestamp - self.kfs[ids[a]].timestamp,
                               median_depth(disps[n]))
            img = rectify(raw, self.intrinsics, w, self.rs_readout, self.rs_stamp_row)
            ks.prep = self.flow.prepare(img)
            if ks.image is not None:
                ks.image = img if self.map_pre is None else rectify(
                    ks.image, self.map_intrinsics, w, self.rs_readout, self.rs_stamp_row)
            self._rs_motion[ks.frame_index] = w
        done = set()
        for (a, b) in self.graph.gather(ids)[4]:
            if (a, b) in done:
                continue
            back = (b, a) in self.graph
            f, w_, fb, wb = self._flows(self.kfs[a].prep, self.kfs[b].prep, self.graph.flow(a, b),
                                        self.graph.flow(b, a) if back else None)
            kind = self.graph.kind[(a, b)]
            self.graph.add(a, b, f, w_, kind=kind)
            if back:
                self.graph.add(b, a, fb, wb, kind=self.graph.kind[(b, a)])
                if kind == "odometry" and ids.index(b) == ids.index(a) + 1:
                    self.kfs[b].conf = wb.mean(-1)
            done |= {(a, b), (b, a)}
        ii, jj, tgt, wgt, _ = self.graph.gather(ids)
        poses, disps, infos = bundle_adjust(poses, disps, self.intr, ii, jj, tgt, wgt,
                                            iters=self.tc.init_iters, fixed=1, huber=self.huber)
        log.info("initialisation on rolling-shutter-rectified keyframes: rms %.3f BA px",
                 infos[-1].rms)
        return poses, disps

    def _initialize(self, frame, info) -> TrackStep:
        ids = list(self.window)
        # extra edges k -> k-2 (and back) for a stiffer warm-up graph
        for a, m, b in zip(ids[:-2], ids[1:-1], ids[2:]):
            init = compose_flows(self.graph.flow(a, m), self.graph.flow(m, b))
            f, w, fb, wb = self._flows(self.kfs[a].prep, self.kfs[b].prep, init)
            self.graph.add(a, b, f, w, kind="init")
            self.graph.add(b, a, fb, wb, kind="init")
        poses, disps = self.kfs.stack(ids)
        ii, jj, tgt, wgt, pairs = self.graph.gather(ids)
        t0 = time.perf_counter()
        poses, disps, infos = self._init_ba(ids, poses, disps, ii, jj, tgt, wgt)
        if self._rs_raw:
            poses, disps = self._rectify_warmup(ids, poses, disps)
            ii, jj, tgt, wgt, pairs = self.graph.gather(ids)
        # Monocular scale is arbitrary: normalise the mean disparity to 1.
        s = float(disps.mean())
        disps = disps / s
        poses = poses.clone()
        poses[:, :3, 3] *= s
        if self._anchor is not None:    # a new segment: in the world frame of the first one
            T0, d0 = self._anchor
            disps = disps * d0
            poses[:, :3, 3] /= d0
            poses = T0.to(poses) @ poses
        poses, disps, infos2 = bundle_adjust(poses, disps, self.intr, ii, jj, tgt, wgt,
                                             iters=self.tc.ba_iters, fixed=2, huber=self.huber)
        self.timings["ba"] += time.perf_counter() - t0
        log.info("initialised from %d keyframes: reprojection rms %.3f -> %.3f BA px",
                 len(ids), infos[0].rms, infos2[-1].rms)
        self.kfs.write_back(ids, poses, disps)
        self.initialized = True
        self.last_pose = poses[-1].clone()
        self.velocity = torch.eye(4, dtype=torch.float64, device=self.device)
        self._spacing = (None, None)
        kds = []
        for k in ids:
            kds.append(self._keyframe_data(k))
            self.published.add(k)
        self._trim_window()
        kid = ids[-1]
        return TrackStep(frame.index, float(frame.timestamp), True, kid,
                         self.kfs[kid].pose.cpu().numpy().copy(), keyframe=kds[-1], keyframes=kds,
                         info={**info, "ba_rms": infos2[-1].rms})

    def _late_initialize(self) -> None:
        """End of input before initialisation: initialise from every warm-up keyframe plus
        the frame that moved most since the last one; the keyframes go to
        :attr:`final_keyframes` (published by the tracker role with its final message)."""
        best = self._warm_best
        if best is not None and self.window and (len(self.window) == 1 or
                                                 best[0] >= 0.5 * self.motion.thresh):
            _, frame, img, prep, flows = best
            self._warm_keyframe(frame, img, prep, self.window[-1], flows)
        par = self._window_parallax() if len(self.window) >= 2 else 0.0
        if par < LATE_INIT_PARALLAX * self.tc.init_parallax:
            log.warning("end of input: too little parallax to initialise (%.2f reference BA px "
                        "over %d keyframes)", par, len(self.window))
            return
        last = max(self.kfs[k].frame_index for k in self.window)
        rec = next(r for r in self.records if r.index == last)
        step = self._initialize(Frame(rec.index, rec.timestamp, np.zeros((1, 1, 3), np.uint8),
                                      self.intrinsics), {})
        self.final_keyframes = list(step.keyframes)
        log.info("initialised at the end of input from %d keyframes (parallax %.2f reference "
                 "BA px)", len(step.keyframes), par)
