"""The tracker of Splat-SLAM (paper Sec. 3.1): its state and the per-frame orchestration.

Per input frame: the image is prepared (undistort/crop/resize) and checked; before
initialisation the frame goes to the warm-up (:mod:`initialisation`), afterwards to the front
end (:mod:`frontend`: flow from the last keyframe, pose-only fit on Eq. 1, motion filter and
keyframe decision). A new keyframe joins the factor graph and the window runs dense BA with
the optional DSPO hook (:mod:`backend`, Eq. 1-2). Every frame leaves a record from which the
full trajectory is filled (:mod:`trajectory_filler`). Every change to an already published
keyframe is reported as an :class:`UpdateEvent`.

:class:`Tracker` holds the state (keyframe set, window, factor graph, motion model, records)
and combines those parts, each a class of methods on that state.

Loop closure and global BA live in :mod:`loop_closure` (their own node in the
ROS graph); their events come back through :meth:`Tracker.apply_update`.
:func:`splat_slam_ros.coordinator.track_sequence` runs tracker + loop closer over a sequence.
"""
from __future__ import annotations

import dataclasses
import itertools
import logging
import time
from collections import Counter, defaultdict
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.geometry import intr_tensor, orthonormalize, pixel_grid
from splat_slam_ros.imaging import image_is_degenerate
from splat_slam_ros.runtime import limit_threads, resolve_device
from splat_slam_ros.tracking import dense_ba
from splat_slam_ros.tracking.backend import BAState, TrackerBackend
from splat_slam_ros.tracking.factor_graph import FactorGraph
from splat_slam_ros.tracking.flow_frontend import (ImagePreprocessor, make_flow_predictor,
                                                   mapping_preprocessor)
from splat_slam_ros.tracking.frontend import TrackerFrontend
from splat_slam_ros.tracking.initialisation import TrackerInitialisation
from splat_slam_ros.tracking.keyframe_set import KEYFRAME_CAUSES, KeyframeSet, KeyframeState
from splat_slam_ros.tracking.motion_filter import flow_scale
from splat_slam_ros.tracking.rolling_shutter import (ReadoutMotion, RollingShutterError,
                                                     check_settings)
from splat_slam_ros.tracking.trajectory_filler import FrameRecord, TrajectoryRecorder
from splat_slam_ros.types import (TRACKER_SEQ_START, Frame, Intrinsics, KeyframeData, TrackStep,
                                  UpdateEvent)

log = logging.getLogger(__name__)
MIN_FRAME_INTERVAL_S = 1e-3     # camera stamps closer than this (over 1000 frames/s): a bad clock


class TrackingError(ValueError):
    """A user-facing tracking configuration/input mistake."""


class Tracker(TrackerInitialisation, TrackerFrontend, TrackerBackend, TrajectoryRecorder):
    """Frame-by-frame tracker. ``Tracker(cfg, intrinsics)``; see module docstring."""

    def __init__(self, cfg: SlamConfig, intrinsics: Intrinsics, flow_predictor=None,
                 depth_prior: Optional[Callable[[BAState], Optional[torch.Tensor]]] = None,
                 seq_start: int = TRACKER_SEQ_START):
        self.cfg = cfg
        tc = self.tc = cfg.tracking
        self.device = resolve_device(tc.device, "tracking.device")
        dense_ba.use_backend(tc.ba_backend, self.device)
        cam = cfg.camera
        W0, H0 = intrinsics.width - 2 * cam.crop, intrinsics.height - 2 * cam.crop
        w, h = tc.processing_size(cam, W0, H0)               # tracking size (0x0: input)
        self.pre = ImagePreprocessor(intrinsics, tc.ba_downsample, w, h, cam.crop, cam.undistort)
        try:
            check_settings(cam.rolling_shutter_ms, cam.rolling_shutter_stamp_row)
        except RollingShutterError as e:
            raise TrackingError(str(e)) from None
        self.rs_readout = float(cam.rolling_shutter_ms) * 1e-3      # s (0: global shutter)
        self.rs_stamp_row = float(cam.rolling_shutter_stamp_row)
        self._stamps: Dict[int, float] = {}    # tracked frames' stamps (the velocity's dt)
        self._rs_motion: Dict[int, Optional[ReadoutMotion]] = {}   # a frame's rectification
        self._rs_raw: Dict[int, np.ndarray] = {}     # warm-up keyframes' unrectified images
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
        # (index, stamp) of every frame skipped on arrival, in order, bridges included (a live
        # run's frames_skipped.txt: splat-slam-run --skip-frames replays them)
        self.skipped_at: List[Tuple[int, float]] = []
        if tc.bridge_frames < 0:
            raise TrackingError(f"tracking.bridge_frames must be >= 0, got {tc.bridge_frames}")
        self._gap: List[Frame] = []     # skipped frames since the last tracked one (bridges)
        self._bridged_steps: List[TrackStep] = []   # skipped frames tracked after all ...
        self.n_bridged = 0                          # ... (a bridge, TrackerFrontend._bridge)
        self._announced = None          # the frame whose predicted pose went out before a bridge
        self.n_segments = 1             # initialisations (a new one after a long loss)
        self._anchor = self._before_loss = None   # a new segment's start; the motion at a loss
        # (index, stamp, pose) before a keyframe's local BA, or before a bridge (its prediction)
        self.on_pose_estimate: Optional[Callable] = None
        self._last_flow = None          # (ref kf, flow ref -> previous frame): DIS init
        self._warm_best = None          # warm-up: the frame that moved most since the last kf
        # non-keyframes tracked against the newest keyframe: (record, prepared image); they
        # are aligned against the next keyframe too once it exists (_next_keyframe_flows)
        self._pending: List[Tuple[FrameRecord, object]] = []
        self._last_input = None         # (frame, image, prep) of the newest non-keyframe
        self.final_keyframes: List[KeyframeData] = []   # published by a late initialisation
        self.timings: Dict[str, float] = defaultdict(float)
        self._last_stamp: Optional[float] = None      # the stamps' check (_check_stamp)
        self._stamp_warned = False
        self.depth_prior = depth_prior if depth_prior is not None else self._default_prior(
            intrinsics)

    def next_seq(self) -> int:
        return next(self._seq)

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

    def track(self, frame: Frame) -> TrackStep:
        self._check_stamp(frame)
        with limit_threads(self.tc.threads):
            return self._track_frame(frame)

    def _check_stamp(self, frame: Frame) -> None:
        """Camera stamps that do not advance (a clock in the wrong unit, a driver that stamps
        every frame alike) leave the keyframe rate bound, which counts camera seconds, with
        no keyframe after the warm-up: said once."""
        t, prev = float(frame.timestamp), self._last_stamp
        self._last_stamp = t
        if prev is not None and t - prev < MIN_FRAME_INTERVAL_S and not self._stamp_warned:
            self._stamp_warned = True
            log.warning("frame %d is stamped %.6f s after the frame before it: the keyframe "
                        "rate bound (tracking.max_keyframe_rate, min_keyframe_interval) counts "
                        "camera seconds; check the camera's clock", frame.index, t - prev)

    def _track_frame(self, frame: Frame) -> TrackStep:
        t0 = time.perf_counter()
        try:
            img = self._rectified(frame, self.pre(frame.image))
        except ValueError as e:
            raise TrackingError(str(e)) from None
        gap = [g for g in self._gap if g.index < frame.index]   # (unskip: not itself)
        self._gap = []
        if image_is_degenerate(img):
            step = self._lost(frame, "degenerate image (black/uniform)")
        else:
            prep = self.flow.prepare(img)
            if self.initialized and 0 < self.tc.reinit_after <= self.lost_count:
                self._new_segment(frame.index)
            if not self.initialized:
                step = self._warmup(frame, img, prep)
            else:
                step = self._track(frame, img, prep, gap)
        if self._bridged_steps:
            step = self._with_bridged(step)
        self.timings["track"] += time.perf_counter() - t0
        self.timings["frames"] += 1
        return step

    def _with_bridged(self, step: TrackStep) -> TrackStep:
        """``step`` with the steps of other frames made while tracking it (skipped frames
        tracked after all: bridges; the frame before, promoted to a keyframe): their
        keyframes published after every update of this step, so those keyframes carry their
        current pose and disparity and the updates name only keyframes already published."""
        steps, self._bridged_steps = self._bridged_steps + [step], []
        kfs = [kd for s in steps for kd in s.keyframes]
        new = {kd.kf_id for kd in kfs}
        events = []
        for ev in (ev for s in steps for ev in s.events):
            ids = [k for k in ev.kf_ids if k not in new and k in self.kfs]
            if ids:
                events.append(self.kfs.update_event(ev.seq, ev.reason, ids))
        for kd in kfs:
            if kd.kf_id in self.kfs:
                ks = self.kfs[kd.kf_id]
                kd.pose = ks.pose.cpu().numpy().copy()
                kd.disparity = ks.disp.cpu().numpy().astype(np.float32)
        info = {**step.info, "bridged": sum(not s.info.get("promoted") for s in steps[:-1])}
        return dataclasses.replace(step, events=events, keyframes=kfs,
                                   keyframe=kfs[-1] if kfs else None, info=info)

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

    def _add_keyframe(self, frame, img, prep, pose, disp) -> int:
        kid = self._new_kf_id()
        if self.rs_readout > 0 and not self.initialized:   # rectified at the initialisation
            self._rs_raw[kid] = img
        if self.map_pre is not None:         # the image handed on: at the mapping size
            img = self._rectified(frame, self.map_pre(frame.image), self.map_intrinsics)
        self.kfs.add(kid, KeyframeState(
            orthonormalize(pose.to(self.device, torch.float64)), disp.to(self.device, torch.float32),
            frame.index, float(frame.timestamp), prep=prep, image=img,
            conf=torch.ones(self.h, self.w, device=self.device)))
        self.window.append(kid)
        return kid

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

    def keyframe_ids(self) -> List[int]:
        return [k for k in self.kfs if k in self.published]

    def keyframe_summary(self) -> Dict[str, object]:
        """``keyframes_per_s`` (keyframes made from this input per second of it, first to
        last frame; a loaded session's are not counted; None for a single frame) and
        ``keyframe_causes`` (how many each cause made, ``KeyframeState.cause``, over the
        published keyframes): what the depth stage and the mapper pay for; ``ba_backend``:
        what built the BA terms, and why (``tracking.ba_backend``)."""
        causes = Counter(self.kfs[k].cause for k in self.keyframe_ids())
        made = sum(n for c, n in causes.items() if c != "loaded")
        span = self.records[-1].timestamp - self.records[0].timestamp \
            if len(self.records) > 1 else 0.0
        return {"ba_backend": dense_ba.backend_in_use(self.device),
                "keyframes_per_s": round(made / span, 3) if span > 0 else None,
                "keyframe_causes": {c: causes[c] for c in KEYFRAME_CAUSES if causes[c]}}
