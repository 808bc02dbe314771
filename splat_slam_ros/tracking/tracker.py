"""The tracker of Splat-SLAM (paper Sec. 3.1): flow front end + local dense BA over keyframes.

Per input frame: the image is prepared (undistort/crop/resize), dense flow from
the last keyframe is predicted (``FlowPredictor``, OpenCV DIS by default), the
frame pose is estimated against the keyframe's disparity (pose-only Gauss-Newton
on Eq. 1) and the motion filter decides whether it becomes a keyframe. A new
keyframe gets flow edges to its predecessor and to nearby window keyframes
(factor graph), then the window runs dense BA (Eq. 1, optionally alternated
with DSPO through the ``depth_prior`` hook). Every change to an already
published keyframe is reported as an :class:`UpdateEvent`.

Loop closure and global BA live in :mod:`loop_closure` (their own node in the
ROS graph); their events come back through :meth:`Tracker.apply_update`.
:func:`splat_slam_ros.coordinator.track_sequence` runs tracker + loop closer over a sequence.
"""
from __future__ import annotations

import itertools
import logging
import time
from collections import defaultdict
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.tracking.dense_ba import (bundle_adjust, induced_flow_distance,
                                              pose_only_refine, reproject)
from splat_slam_ros.tracking.factor_graph import FactorGraph, proximity_pairs
from splat_slam_ros.tracking.keyframe_set import KeyframeSet, KeyframeState
from splat_slam_ros.tracking.flow_frontend import (ImagePreprocessor, compose_flows, image_is_degenerate,
                            make_flow_predictor, mapping_preprocessor, predict_both)
from splat_slam_ros.geometry import disparity_through_flow, intr_tensor, orthonormalize, pixel_grid, se3_exp, se3_inverse, se3_log
from splat_slam_ros.tracking.motion_filter import MotionFilter, flow_scale, parallax, predict_pose
from splat_slam_ros.depth.dspo import make_depth_prior
from splat_slam_ros.runtime import limit_threads, resolve_device
from splat_slam_ros.tracking.trajectory_filler import FrameRecord, fill_trajectory
from splat_slam_ros.tracking.two_view import two_view_start
from splat_slam_ros.types import (TRACKER_SEQ_START, Frame, Intrinsics, KeyframeData,
                                  TrackingResult, TrackStep, UpdateEvent)

log = logging.getLogger(__name__)

# a late initialisation (end of input) accepts this fraction of tracking.init_parallax
LATE_INIT_PARALLAX = 0.25


class TrackingError(ValueError):
    """A user-facing tracking configuration/input mistake."""


@dataclass
class BAState:
    """What the optional ``depth_prior`` hook (DSPO, Eq. 2) sees after each local BA.

    The hook returns new disparities (N, h, w) for ``kf_ids`` or None. Edges
    are ``ii -> jj`` (indices into ``kf_ids``) with ``target``/``weight`` as
    in :func:`dense_ba.ba_step`; ``images`` maps kf ids to the RGB images handed on
    with the keyframes (mapping size, for a mono depth network).
    """
    kf_ids: List[int]
    poses: torch.Tensor
    disps: torch.Tensor
    intr: torch.Tensor
    ii: torch.Tensor
    jj: torch.Tensor
    target: torch.Tensor
    weight: torch.Tensor
    images: Dict[int, np.ndarray]
    fixed: int


class Tracker:
    """Frame-by-frame tracker. ``Tracker(cfg, intrinsics)``; see module docstring."""

    def __init__(self, cfg: SlamConfig, intrinsics: Intrinsics, flow_predictor=None,
                 depth_prior: Optional[Callable[[BAState], Optional[torch.Tensor]]] = None,
                 seq_start: int = TRACKER_SEQ_START):
        self.cfg = cfg
        tc = self.tc = cfg.tracking
        self.device = resolve_device(tc.device, "tracking.device")
        cam = cfg.camera
        W0, H0 = intrinsics.width - 2 * cam.crop, intrinsics.height - 2 * cam.crop
        w, h = tc.processing_size(cam, W0, H0)               # tracking size (0x0: input)
        self.pre = ImagePreprocessor(intrinsics, tc.ba_downsample, w, h, cam.crop, cam.undistort)
        self.intrinsics = self.pre.intrinsics
        # keyframes are handed on at the mapping size (camera.*), which may be smaller
        self.map_pre = mapping_preprocessor(cfg, intrinsics)
        if self.map_pre.trim == self.pre.trim:
            self.map_pre = None
        self.map_intrinsics = self.intrinsics if self.map_pre is None else \
            self.map_pre.intrinsics
        self.ba_intrinsics = self.pre.ba_intrinsics
        self.intr = intr_tensor(self.ba_intrinsics, torch.float32, self.device)
        self.h, self.w = self.ba_intrinsics.height, self.ba_intrinsics.width
        self.flow = flow_predictor if flow_predictor is not None else make_flow_predictor(tc)
        # flow thresholds are in reference BA px (motion_filter.flow_scale): size-independent
        self.px_scale = flow_scale(self.intr)
        self.motion = self._motion_filter()
        self.graph = FactorGraph(self.h, self.w, self.device)
        self.grid = pixel_grid(self.h, self.w, device=self.device)
        self.huber = tc.robust_huber_px / tc.ba_downsample if tc.robust_huber_px > 0 else None
        # keyframe store (all keyframes: pose + disparity; images only while needed)
        self.kfs = KeyframeSet()
        self.window: List[int] = []
        self.published: set = set()
        self.records: List[FrameRecord] = []
        self.initialized = False
        self.next_kf = 0
        self._seq = itertools.count(seq_start)      # update numbers (types.TRACKER_SEQ_START)
        self.last_pose = torch.eye(4, dtype=torch.float64, device=self.device)
        self.velocity = torch.eye(4, dtype=torch.float64, device=self.device)
        self._spacing = (None, None)   # frame indices of the velocity's step (predict_pose)
        self.lost_count = self.n_lost = 0
        self.n_skipped = 0              # frames skip() posed without tracking (live, busy)
        self.n_segments = 1             # initialisations (a new one after a long loss)
        self._anchor = self._before_loss = None   # a new segment's start; the motion at a loss
        self.on_pose_estimate: Optional[Callable] = None   # (index, stamp, pose) before BA
        self._last_flow = None          # (ref kf, flow ref -> previous frame): DIS init
        self._warm_best = None          # warm-up: the frame that moved most since the last kf
        # non-keyframes tracked against the newest keyframe: (record, prepared image); they
        # are aligned against the next keyframe too once it exists (_next_keyframe_flows)
        self._pending: List[Tuple[FrameRecord, object]] = []
        self._last_input = None         # (frame, image, prep) of the newest non-keyframe
        self.final_keyframes: List[KeyframeData] = []   # published by a late initialisation
        self.timings: Dict[str, float] = defaultdict(float)
        self.depth_prior = depth_prior if depth_prior is not None else self._default_prior(
            intrinsics)

    # ------------------------------------------------------------ helpers
    def _motion_filter(self) -> MotionFilter:
        tc = self.tc
        return MotionFilter(tc.motion_filter_thresh * self.px_scale,
                            min_valid_frac=tc.lost_min_valid, max_rate=tc.max_keyframe_rate,
                            urgent_flow=tc.keyframe_urgent_flow,
                            urgent_valid=tc.keyframe_urgent_valid)

    def _default_prior(self, intrinsics):
        if not (self.cfg.depth.mono_model and self.tc.dspo):
            return None
        return make_depth_prior(self.cfg, self.map_intrinsics)   # Eq. 2 (DSPO); errors propagate

    def next_seq(self) -> int:
        return next(self._seq)

    def _flows(self, a, b, init_ab=None, init_ba=None):
        """Flows a -> b and b -> a with weights; ``init_*`` (BA-grid flows expected
        from the current estimate) are passed to predictors that accept them."""
        t0 = time.perf_counter()
        if init_ab is not None and hasattr(self.flow, "predict_pair"):
            out = self.flow.predict_pair(a, b, init_ij=init_ab.cpu(),
                                         init_ji=None if init_ba is None else init_ba.cpu())
        else:
            out = predict_both(self.flow, a, b)
        self.timings["flow"] += time.perf_counter() - t0
        return tuple(x.to(self.device) for x in out)

    def _induced(self, T_a, d_a, T_b) -> torch.Tensor:
        """Flow (h, w, 2) that keyframe a's disparity and the poses induce a -> b."""
        P = torch.stack([T_a, T_b])
        uv, _ = reproject(P, d_a[None], self.intr, torch.tensor([0], device=self.device),
                          torch.tensor([1], device=self.device))
        return uv[0] - self.grid

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

    def _store_flow(self, f, w):
        return f.detach().to("cpu", torch.float16), w.detach().to("cpu", torch.float16)

    def _keyframe_data(self, kid: int) -> KeyframeData:
        ks = self.kfs[kid]
        mono = None
        if self.depth_prior is not None and hasattr(self.depth_prior, "take_mono_depth"):
            mono = self.depth_prior.take_mono_depth(kid)     # DSPO ran the mono model already
        return KeyframeData(kf_id=kid, frame_index=ks.frame_index, timestamp=ks.timestamp,
                            pose=ks.pose.cpu().numpy().copy(),
                            image=ks.image, intrinsics=self.map_intrinsics,
                            disparity=ks.disp.cpu().numpy().astype(np.float32),
                            confidence=ks.conf.cpu().numpy().astype(np.float32),
                            mono_depth=mono)

    def _new_kf_id(self) -> int:
        k = self.next_kf
        self.next_kf += 1
        return k

    # ------------------------------------------------------------ public
    def track(self, frame: Frame) -> TrackStep:
        with limit_threads(self.tc.threads):
            return self._track_frame(frame)

    def _track_frame(self, frame: Frame) -> TrackStep:
        t0 = time.perf_counter()
        try:
            img = self.pre(frame.image)
        except ValueError as e:
            raise TrackingError(str(e)) from None
        if image_is_degenerate(img):
            step = self._lost(frame, "degenerate image (black/uniform)")
        else:
            prep = self.flow.prepare(img)
            if self.initialized and 0 < self.tc.reinit_after <= self.lost_count:
                self._new_segment(frame.index)
            if not self.initialized:
                step = self._warmup(frame, img, prep)
            else:
                step = self._track(frame, img, prep)
        self.timings["track"] += time.perf_counter() - t0
        self.timings["frames"] += 1
        return step

    def skip(self, index: int, timestamp: float) -> np.ndarray:
        """A frame not tracked (live, busy): placed between its tracked neighbours later."""
        self.n_skipped += 1
        self.records.append(FrameRecord(int(index), float(timestamp), skipped=True))
        return self.predict()

    def predict(self) -> np.ndarray:     # constant velocity: the next frame's camera-to-world
        return (self.last_pose @ self.velocity).cpu().numpy()

    def _lost(self, frame: Frame, why: str) -> TrackStep:
        self.lost_count += 1
        self.n_lost += 1
        if self.lost_count == 1:        # the motion before the loss (a new segment's start)
            self._before_loss = (self.last_pose.clone(), self.velocity, self._spacing)
        self.velocity = torch.eye(4, dtype=torch.float64, device=self.device)
        self._spacing = (None, None)
        if self.lost_count == 1 or self.lost_count % 30 == 0:
            log.warning("frame %d: tracking lost (%s)%s", frame.index, why,
                        "" if self.lost_count == 1 else f", {self.lost_count} frames so far")
        self._record(frame, lost=True)
        return TrackStep(frame.index, float(frame.timestamp), False, None,
                         self.last_pose.cpu().numpy().copy(), lost=True,
                         initialized=self.initialized, info={"why": why})

    # ------------------------------------------------------------ warm-up
    def _add_keyframe(self, frame, img, prep, pose, disp) -> int:
        kid = self._new_kf_id()
        if self.map_pre is not None:         # the image handed on: at the mapping size
            img = self.map_pre(frame.image)
        self.kfs.add(kid, KeyframeState(
            orthonormalize(pose.to(self.device, torch.float64)), disp.to(self.device, torch.float32),
            frame.index, float(frame.timestamp), prep=prep, image=img,
            conf=torch.ones(self.h, self.w, device=self.device)))
        self.window.append(kid)
        return kid

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
        fc = self.motion.check(f, w)
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
        if not self.motion.is_candidate(fc):
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

    # ------------------------------------------------------------ tracking
    def _try_reference(self, ref, prep, use_last: bool = True):
        # DIS is initialised with the previous frame's measured flow to the same
        # keyframe (temporal propagation; image-based, so a wrong disparity
        # cannot corrupt it)
        init = self._last_flow[1] if use_last and self._last_flow is not None and \
            self._last_flow[0] == ref else None
        f, w, fb, wb = self._flows(self.kfs[ref].prep, prep, init)
        return (f, w, fb, wb), self.motion.check(f, w)

    def _fit_pose(self, ref, f, w, inits):
        """Pose-only fit of the frame against the flow ref -> frame; best of ``inits``."""
        best = None
        t0 = time.perf_counter()
        for T0 in inits:
            T, info = pose_only_refine(self.kfs[ref].pose, self.kfs[ref].disp, T0, self.intr,
                                       self.grid + f, w, iters=self.tc.pose_iters,
                                       huber=self.huber)
            if info is not None and np.isfinite(info.rms) and (best is None or
                                                                info.rms < best[1].rms):
                best = (T, info)
            if best is not None and best[1].rms < 0.5 * self.tc.lost_rms:
                break
        self.timings["pose"] += time.perf_counter() - t0
        return best if best is not None else (inits[0], None)

    def _track(self, frame, img, prep) -> TrackStep:
        tc = self.tc
        ref = self.window[-1]
        was_lost = self.lost_count > 0
        pred = self.last_pose @ self.velocity
        flows, fc = self._try_reference(ref, prep, not was_lost)
        if not fc.ok and not was_lost:
            # a large motion since the last tracked frame (skipped frames on live input, fast
            # motion): DIS again, pre-warped by the flow the constant-velocity pose induces
            if self._spacing[0] is None and len(self.window) > 1:   # no step since init / loss
                a, b = self.kfs[self.window[-2]], self.kfs[self.window[-1]]   # keyframes' motion
                T_p = predict_pose(b.pose, se3_inverse(a.pose) @ b.pose,
                                   (a.frame_index, b.frame_index), frame.index)
            else:
                T_p = predict_pose(self.last_pose, self.velocity, self._spacing, frame.index)
            init = self._induced(self.kfs[ref].pose, self.kfs[ref].disp, T_p)
            fl = self._flows(self.kfs[ref].prep, prep, init)
            fc_p = self.motion.check(fl[0], fl[1])
            if fc_p.ok:
                flows, fc, pred = fl, fc_p, T_p
        if not fc.ok:
            self._last_flow = None
            # relocalise against the other recent keyframes
            for k in reversed(self.window[-1 - tc.reloc_keyframes:-1]):
                flows_k, fc_k = self._try_reference(k, prep, False)
                if fc_k.ok:
                    ref, flows, fc = k, flows_k, fc_k
                    break
        if not fc.ok:
            return self._lost(frame, f"low flow confidence ({fc.valid_frac:.2f} valid)")
        f, w, fb, wb = flows
        T_ref = self.kfs[ref].pose
        inits = [T_ref.clone()] if was_lost else [pred, self.last_pose.clone(), T_ref.clone()]
        T, pinfo = self._fit_pose(ref, f, w, inits)
        if pinfo is None or not np.isfinite(pinfo.rms) or pinfo.rms > tc.lost_rms:
            return self._lost(frame, f"pose did not fit the flow (rms "
                                     f"{getattr(pinfo, 'rms', float('nan')):.2f} BA px)")
        if was_lost:
            log.info("frame %d: tracking recovered against keyframe %d after %d lost frames",
                     frame.index, ref, self.lost_count)
        self.lost_count = 0
        self._last_flow = (ref, f)
        info = {"mean_flow": fc.mean_flow, "valid": fc.valid_frac, "pose_rms": pinfo.rms}
        since_kf = float(frame.timestamp) - self.kfs[ref].timestamp
        if self.motion.is_candidate(fc, since_kf) and ref == self.window[-1]:
            if self.on_pose_estimate is not None:      # a keyframe's pose before its local BA
                self.on_pose_estimate(frame.index, float(frame.timestamp), T.cpu().numpy())
            return self._new_keyframe(frame, img, prep, ref, T, f, w, fb, wb, info)
        self._set_pose(T, frame.index)
        sf, sw = self._store_flow(f, w)
        rec = self._record(frame, ref_kf=ref, rel_pose=(se3_inverse(T_ref) @ T).cpu().numpy(),
                           ref_scale=float(self.kfs[ref].disp.mean()), flow=sf, weight=sw,
                           online_pose=T.cpu().numpy())
        self._add_pending(rec, frame, img, prep)
        return TrackStep(frame.index, float(frame.timestamp), False, None,
                         T.cpu().numpy().copy(), info=info)

    def _set_pose(self, T, index: int):
        self._spacing = (self._spacing[1], int(index))
        T = orthonormalize(T)
        # constant-velocity model in the tangent space (exp keeps it a rigid motion)
        self.velocity = se3_exp(se3_log(se3_inverse(self.last_pose) @ T))
        self.last_pose = T.clone()

    def _add_radius_edges(self, kid: int) -> None:
        """Edges to the keyframes 2 .. frontend_radius before the new one (the one
        before is connected by the tracking flow already), DIS pre-warped by the
        induced flow."""
        for k in self.window[-1 - self.tc.frontend_radius:-2]:
            if (k, kid) in self.graph:
                continue
            init_ab = self._induced(self.kfs[k].pose, self.kfs[k].disp, self.kfs[kid].pose)
            init_ba = self._induced(self.kfs[kid].pose, self.kfs[kid].disp, self.kfs[k].pose)
            f, w, fb, wb = self._flows(self.kfs[k].prep, self.kfs[kid].prep, init_ab, init_ba)
            if self.motion.check(f, w).ok:
                self.graph.add(k, kid, f, w, kind="radius")
                self.graph.add(kid, k, fb, wb, kind="radius")

    def _add_proximity_edges(self, kid: int) -> None:
        tc = self.tc
        if tc.frontend_new_edges <= 0 or len(self.window) < 3:
            return
        ids = list(self.window)
        poses, disps = self.kfs.stack(ids)
        cands = proximity_pairs(ids, poses, disps, self.intr, [kid],
                                tc.frontend_thresh * self.px_scale,
                                tc.frontend_new_edges, exclude=self.graph.pairs(),
                                min_gap=1, nms=tc.frontend_nms)
        pos = {k: n for n, k in enumerate(ids)}
        for a, b, _ in cands:
            ia = torch.tensor([pos[a], pos[b]], device=self.device)
            ib = torch.tensor([pos[b], pos[a]], device=self.device)
            uv, _valid = reproject(poses, disps, self.intr, ia, ib)
            init = uv - self.grid
            f, w, fb, wb = self._flows(self.kfs[a].prep, self.kfs[b].prep, init[0], init[1])
            fc = self.motion.check(f, w)
            if fc.valid_frac < 0.5 * max(self.motion.typical_valid_frac, tc.lost_min_valid):
                continue
            self.graph.add(a, b, f, w, kind="proximity")
            self.graph.add(b, a, fb, wb, kind="proximity")

    def _trim_window(self) -> None:
        tc = self.tc
        while len(self.window) > tc.frontend_window:
            old = self.window.pop(0)
            self.kfs.drop_prep(old)
            self.kfs.drop_image(old)
        self.graph.prune(self.window, tc.max_edge_age, tc.frontend_max_factors,
                         protect=self.window[-2:])
        for k in self.kfs.with_image():
            if k in self.published:
                self.kfs.drop_image(k)

    def _snapshot(self, ids):
        return self.kfs.snapshot(k for k in ids if k in self.published)

    def _events(self, reason: str, before) -> List[UpdateEvent]:
        ids = self.kfs.changed(before, self.tc.event_pose_thresh, self.tc.event_disp_thresh)
        return [self.kfs.update_event(self.next_seq(), reason, ids)] if ids else []

    def _local_ba(self, iters: int):
        ids = list(self.window)
        poses, disps = self.kfs.stack(ids)
        ii, jj, tgt, wgt, pairs = self.graph.gather(ids)
        if len(pairs) == 0:
            return None
        fixed = min(2, len(ids) - 1)
        t0 = time.perf_counter()
        poses, disps, infos = bundle_adjust(poses, disps, self.intr, ii, jj, tgt, wgt,
                                            iters=iters, fixed=fixed, huber=self.huber)
        self.timings["ba"] += time.perf_counter() - t0
        if self.depth_prior is not None:
            t0 = time.perf_counter()
            st = BAState(ids, poses, disps, self.intr, ii, jj, tgt, wgt,
                         {k: self.kfs[k].image for k in ids
                          if self.kfs[k].image is not None}, fixed)
            out = self.depth_prior(st)
            if out is not None:
                disps = out.to(disps)
            self.timings["dspo"] += time.perf_counter() - t0
        self.kfs.write_back(ids, poses, disps)
        self.graph.age_edges(pairs)
        return infos[-1]

    def _new_keyframe(self, frame, img, prep, ref, T, f, w, fb, wb, info,
                      force: bool = False) -> TrackStep:
        tc = self.tc
        before = self._snapshot(self.window)
        kid = self._add_keyframe(frame, img, prep, T, disparity_through_flow(
            self.kfs[ref].disp, self.grid, fb, wb, self.intr, self.kfs[ref].pose, T))
        self.kfs[kid].conf = wb.mean(-1)
        self.graph.add(ref, kid, f, w)
        self.graph.add(kid, ref, fb, wb)
        self._add_radius_edges(kid)
        self._add_proximity_edges(kid)
        self._trim_window()
        binfo = self._local_ba(tc.ba_iters)
        events = self._events("local_ba", before)
        T_new = self.kfs[kid].pose
        # keyframe threshold tau on the flow induced by the optimised estimate
        ids = [ref, kid]
        P, D = self.kfs.stack(ids)
        i0 = torch.tensor([0, 1], device=self.device)
        i1 = torch.tensor([1, 0], device=self.device)
        dist = float(induced_flow_distance(P, D, self.intr, i0, i1).mean())
        info = {**info, "kf_dist": dist, "ba_rms": binfo.rms if binfo else float("nan")}
        if dist < tc.keyframe_thresh * self.px_scale and len(self.window) > 3 and not force:
            self._drop_keyframe(kid)
            self._set_pose(T_new, frame.index)
            sf, sw = self._store_flow(f, w)
            T_ref = self.kfs[ref].pose
            rec = self._record(frame, ref_kf=ref,
                               rel_pose=(se3_inverse(T_ref) @ T_new).cpu().numpy(),
                               ref_scale=float(self.kfs[ref].disp.mean()), flow=sf, weight=sw,
                               online_pose=T_new.cpu().numpy())
            self._add_pending(rec, frame, img, prep)
            return TrackStep(frame.index, float(frame.timestamp), False, None,
                             T_new.cpu().numpy().copy(), events=events, info=info)
        self._set_pose(T_new, frame.index)
        self._record(frame, replace=force, kf_id=kid)
        self._next_keyframe_flows(kid)
        kd = self._keyframe_data(kid)
        self.published.add(kid)
        self.kfs.drop_image(kid)
        return TrackStep(frame.index, float(frame.timestamp), True, kid,
                         T_new.cpu().numpy().copy(), events=events, keyframe=kd,
                         keyframes=[kd], info=info)

    def _add_pending(self, rec: FrameRecord, frame, img, prep) -> None:
        if rec.ref_kf == self.window[-1]:
            self._pending.append((rec, prep))
        self._last_input = (frame, img, prep)

    def _next_keyframe_flows(self, kid: int) -> None:
        """Flows from the new keyframe into the non-keyframes tracked since the previous
        one (DIS started from the flow the current estimate induces), so that each is
        aligned against both neighbouring keyframes (trajectory_filler)."""
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
        for rec, prep, init in todo:
            if id(rec) in flows:
                f, w = (x.to(self.device) for x in flows[id(rec)])
            else:
                f, w, _, _ = self._flows(ks.prep, prep, init)
            if self.motion.check(f, w).valid_frac < self.tc.lost_min_valid:
                continue
            rec.ref2_kf = kid
            rec.flow2, rec.weight2 = self._store_flow(f, w)
        self._pending = []
        self.timings["next_kf_flows"] += time.perf_counter() - t0

    def _drop_keyframe(self, kid: int) -> None:
        self.graph.remove_node(kid)
        self.window.remove(kid)
        self.kfs.remove(kid)
        self.next_kf = kid          # ids stay contiguous

    # ------------------------------------------------------------ updates
    def apply_update(self, ev: UpdateEvent) -> None:
        """Apply pose/disparity changes made elsewhere (loop closure, global BA).

        Keyframes newer than the newest one in the event (the event was computed
        on an older snapshot) are moved rigidly with that keyframe's correction,
        as is the current frame pose.
        """
        ids = [int(k) for k in ev.kf_ids]
        known = [k for k in ids if k in self.kfs]
        if not known:
            return
        newest = max(known)
        corr = None
        for n, k in enumerate(ids):
            if k not in self.kfs:
                continue
            T_new = torch.as_tensor(np.asarray(ev.poses[n]), dtype=torch.float64,
                                    device=self.device)
            if k == newest:
                corr = T_new @ se3_inverse(self.kfs[k].pose)
            self.kfs[k].pose = T_new
            if ev.disparities is not None:
                self.kfs[k].disp = torch.as_tensor(np.asarray(ev.disparities[n]),
                                                dtype=torch.float32, device=self.device)
        later = [k for k in self.kfs if k > newest and k not in ids]
        if corr is not None:
            corr = orthonormalize(corr)
            for k in later:
                self.kfs[k].pose = corr @ self.kfs[k].pose
            # the current frame hangs off the newest keyframe
            self.last_pose = corr @ self.last_pose

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

    def finalize(self) -> List[UpdateEvent]:
        """End of input: initialisation if it has not happened yet (with everything
        collected), then one more local BA round on the window (loop closure / global BA
        finalisation is the loop closer's ``finalize``)."""
        if not self.initialized:
            with limit_threads(self.tc.threads):
                self._late_initialize()
        if not self.initialized or len(self.window) < 2:
            return []
        with limit_threads(self.tc.threads):
            events = self._last_frame_keyframe()
            before = self._snapshot(self.window)
            self._local_ba(self.tc.ba_iters)
            return events + self._events("local_ba", before)

    def _last_frame_keyframe(self) -> List[UpdateEvent]:
        """End of input: the last frame becomes a keyframe when it moved since the last
        one (half the motion threshold), so the frames after the last keyframe are
        aligned against a keyframe on both sides too."""
        if not self._pending or self._last_input is None:
            return []
        frame, img, prep = self._last_input
        rec = self.records[-1]
        if rec.index != frame.index or rec.kf_id is not None or rec.ref_kf != self.window[-1]:
            return []
        ref = rec.ref_kf
        T = self.kfs[ref].pose @ torch.as_tensor(rec.rel_pose, dtype=torch.float64,
                                                 device=self.device)
        init = self._induced(self.kfs[ref].pose, self.kfs[ref].disp, T)
        f, w, fb, wb = self._flows(self.kfs[ref].prep, prep, init)
        fc = self.motion.check(f, w)
        if not fc.ok or fc.mean_flow < 0.5 * self.motion.thresh:
            return []
        self._pending = [(r, p) for r, p in self._pending if r.index != frame.index]
        step = self._new_keyframe(frame, img, prep, ref, T, f, w, fb, wb, {}, force=True)
        self.final_keyframes.extend(step.keyframes)
        return list(step.events)

    # ------------------------------------------------------------ outputs
    def trajectory_keyframes(self) -> Tuple[np.ndarray, np.ndarray]:
        return self.kfs.trajectory(self.keyframe_ids())

    def keyframe_ids(self) -> List[int]:
        return [k for k in self.kfs if k in self.published]

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
