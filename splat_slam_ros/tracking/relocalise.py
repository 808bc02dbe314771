"""Saving a run's keyframes as a session, and localising later frames in a loaded session.

:func:`save_session` writes ``OUT/session/`` (:mod:`splat_slam_ros.io.session`) from a
finished tracker: the published keyframes' poses and BA-grid disparities, their
tracking-size images (read again from the input: the tracker drops them once published)
and a descriptor each.

:class:`Localizer` tracks a new sequence in a loaded session without changing it
(localize-only): the session's keyframes go into a :class:`Tracker`'s keyframe set,
read-only. While lost, a frame is relocalised: the stored keyframes are ranked by descriptor
similarity and the best ``k`` are tried, DIS flow keyframe -> frame and the tracker's
pose-only fit against the keyframe's stored pose and disparity, accepted under the tracker's
own loss thresholds (``tracking.lost_min_valid`` confident cells, ``tracking.lost_rms``).
Once located, each frame is tracked against the stored keyframes nearest to the last pose,
from the constant-velocity prediction; when that fails, relocalisation runs again. No
keyframe is added and no BA runs: poses stay in the session's frame.
"""
from __future__ import annotations

import logging
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from splat_slam_ros import __version__
from splat_slam_ros.config import SlamConfig
from splat_slam_ros.geometry import se3_inverse, se3_log
from splat_slam_ros.imaging import image_at, image_is_degenerate
from splat_slam_ros.io.session import (Session, SessionError, SessionKeyframes, check_camera,
                                       descriptor, descriptor_ranking,
                                       keyframe_data, map_camera, pinhole_diffs, write_session)
from splat_slam_ros.runtime import limit_threads
from splat_slam_ros.tracking.keyframe_set import KeyframeState
from splat_slam_ros.tracking.motion_filter import predict_pose
from splat_slam_ros.tracking.tracker import Tracker
from splat_slam_ros.types import Frame, Intrinsics, KeyframeData, TrackStep

log = logging.getLogger(__name__)

RELOC_CANDIDATES = 3        # keyframes tried per relocalisation (best by descriptor)
TRACK_CANDIDATES = 2        # keyframes tried per located frame (nearest to the prediction)


def _sizes(trk: Tracker) -> Tuple[List[int], List[int]]:
    return [trk.intrinsics.width, trk.intrinsics.height], [trk.w, trk.h]


def _ba_state(trk: Tracker, ids: List[int]) -> Tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) float64 poses and (N, h, w) float32 disparities of keyframes ``ids`` now."""
    if not ids:
        return np.zeros((0, 4, 4)), np.zeros((0, trk.h, trk.w), np.float32)
    return (np.stack([trk.kfs[k].pose.cpu().numpy() for k in ids]).astype(np.float64),
            np.stack([trk.kfs[k].disp.cpu().numpy() for k in ids]).astype(np.float32))


def input_images(trk: Tracker, frames, ids: List[int]) -> Dict[int, np.ndarray]:
    """The tracking-size images of keyframes ``ids``, read again from the run's input
    (``frames``, iterated once more: the tracker drops keyframe images once published)."""
    by_frame = {trk.kfs[k].frame_index: k for k in ids}
    images = {}
    for f in frames:
        if f.index in by_frame:
            img = trk.pre(f.image)
            images[by_frame[f.index]] = img if img.ndim == 3 else np.repeat(img[..., None], 3, -1)
        if len(images) == len(ids):
            break
    return images


def published_images(trk: Tracker, images: Dict[int, np.ndarray]) -> Dict[int, np.ndarray]:
    """Tracking-size images from the keyframes' published (mapping-size) images: a node
    keeps what it published, the input is gone."""
    return {k: image_at(im, trk.intrinsics.width, trk.intrinsics.height)
            for k, im in images.items()}


def session_keyframes(trk: Tracker, images: Dict[int, np.ndarray],
                      ids: Optional[List[int]] = None) -> SessionKeyframes:
    """The tracker's published keyframes (or ``ids`` of them) that ``images`` holds (kf id ->
    tracking-size RGB), as session arrays."""
    ids = [k for k in (trk.keyframe_ids() if ids is None else ids) if k in images]
    imgs = np.stack([images[k] for k in ids]) if ids else \
        np.zeros((0, trk.intrinsics.height, trk.intrinsics.width, 3), np.uint8)
    poses, disps = _ba_state(trk, ids)
    return SessionKeyframes(
        kf_ids=np.array(ids, np.int64),
        frame_indices=np.array([trk.kfs[k].frame_index for k in ids], np.int64),
        timestamps=np.array([trk.kfs[k].timestamp for k in ids], np.float64),
        poses=poses, disparities=disps, images=imgs.astype(np.uint8, copy=False),
        descriptors=np.stack([descriptor(i) for i in imgs]) if ids else
        np.zeros((0, 192), np.float32))


def session_ids(trk: Tracker) -> List[int]:
    """The keyframes whose images a session of ``trk`` needs (an extend run's loaded ones
    come with the loaded session)."""
    return trk.new_keyframe_ids() if isinstance(trk, ExtendTracker) else trk.keyframe_ids()


def save_session(trk: Tracker, images: Dict[int, np.ndarray], cfg: SlamConfig,
                 camera: Intrinsics, out, map_state=None, loop=None) -> None:
    """Write the tracker's part of ``out/session/`` (``images``: kf id -> tracking-size RGB
    of :func:`session_ids`) and, with a ``map_state`` (the mapper's arrays, metadata and
    camera), the map's state (after ``out/map.ply``), with a ``loop`` closer its graph. An
    :class:`ExtendTracker`'s session holds the loaded keyframes (as they are now) and the
    new ones: a map extended again and again."""
    kfs = session_keyframes(trk, images, session_ids(trk))
    if isinstance(trk, ExtendTracker):
        kfs = concat_keyframes(trk.loaded_keyframes(), kfs)
    if len(kfs):
        write_session(out, kfs, camera, *_sizes(trk), cfg.to_dict(), __version__, map_state,
                      loop.graph_summary() if loop is not None else None)


def concat_keyframes(a: SessionKeyframes, b: SessionKeyframes) -> SessionKeyframes:
    return SessionKeyframes(**{k: np.concatenate([getattr(a, k), getattr(b, k)])
                               for k in SessionKeyframes.__dataclass_fields__})


def add_session_keyframes(trk: Tracker, session: Session,
                          camera: Intrinsics) -> Tuple[List[int], np.ndarray]:
    """Put the session's keyframes (pose, disparity, prepared image) into ``trk``'s keyframe
    set after checking that ``camera`` and the tracker's sizes are the session's
    (SessionError); returns their ids and descriptors (rows in the same order)."""
    check_camera(session, camera, *_sizes(trk))
    s = session.keyframes
    ids = [int(k) for k in s.kf_ids]
    for n, k in enumerate(ids):
        trk.kfs.add(k, KeyframeState(
            torch.as_tensor(s.poses[n], dtype=torch.float64, device=trk.device),
            torch.as_tensor(s.disparities[n], dtype=torch.float32, device=trk.device),
            int(s.frame_indices[n]), float(s.timestamps[n]),
            prep=trk.flow.prepare(s.images[n]), cause="loaded"))
    return ids, s.descriptors.astype(np.float32)


def match_keyframe(trk: Tracker, ref: int, prep, inits, init_flow=None):
    """(pose, rms) of a frame against keyframe ``ref``: DIS flow ref -> frame and the
    tracker's pose-only fit from the best of ``inits``; None when the flow or the fit fails
    the tracker's loss thresholds (``tracking.lost_min_valid``, ``tracking.lost_rms``)."""
    f, w, _, _ = trk._flows(trk.kfs[ref].prep, prep, init_flow)
    if trk.motion.confident_fraction(w) < trk.motion.min_valid(trk._ref_tex(ref)):
        return None
    T, info = trk._fit_pose(ref, f, w, inits)
    if info is None or not np.isfinite(info.rms) or info.rms > trk.tc.lost_rms:
        return None
    return T, float(info.rms)


def relocalise(trk: Tracker, ids: List[int], desc: np.ndarray, img, prep):
    """(keyframe id, (pose, rms)) of the best match among the ``RELOC_CANDIDATES`` keyframes
    of ``ids`` most similar by descriptor (rows of ``desc``), or None."""
    best = None
    for i in descriptor_ranking(desc, descriptor(img))[:RELOC_CANDIDATES]:
        k = ids[int(i)]
        r = match_keyframe(trk, k, prep, [trk.kfs[k].pose.clone()])
        if r is not None and (best is None or r[1] < best[1][1]):
            best = (k, r)
    return best


def nearest_keyframes(trk: Tracker, ids: List[int], T: torch.Tensor) -> List[int]:
    """``ids`` by distance to the pose ``T``: translation in units of the keyframe's mean
    depth plus the rotation angle (rad)."""
    d = []
    for k in ids:
        ks = trk.kfs[k]
        rel = se3_log(se3_inverse(ks.pose) @ T)
        depth = 1.0 / max(float(ks.disp.mean()), 1e-6)
        d.append(float(rel[:3].norm()) / depth + float(rel[3:].norm()))
    return [ids[i] for i in np.argsort(d, kind="stable")]


class Localizer:
    """Localize-only tracking in a loaded :class:`Session` (see module docstring)."""

    def __init__(self, cfg: SlamConfig, intrinsics: Intrinsics, session: Session,
                 flow_predictor=None):
        # no BA runs here: a no-op depth prior keeps a configured mono model unloaded
        self.trk = trk = Tracker(cfg, intrinsics, flow_predictor=flow_predictor,
                                 depth_prior=lambda _state: None)
        self.ids, self.desc = add_session_keyframes(trk, session, intrinsics)
        self.located = False
        self.relocalised_frame: Optional[int] = None
        self.relocalised_keyframe: Optional[int] = None
        self.stamps: List[float] = []
        self.poses: List[np.ndarray] = []
        self.n_lost = 0
        self.n_relocalisations = 0

    def _follow(self, frame: Frame, prep):
        trk = self.trk
        pred = predict_pose(trk.last_pose, trk.velocity, trk._spacing, frame.index)
        for k in nearest_keyframes(trk, self.ids, pred)[:TRACK_CANDIDATES]:
            ks = trk.kfs[k]
            r = match_keyframe(trk, k, prep, [pred, trk.last_pose.clone()],
                               trk._induced(ks.pose, ks.disp, pred))
            if r is not None:
                return k, r
        return None

    # ------------------------------------------------------------ per frame
    def track(self, frame: Frame) -> Optional[np.ndarray]:
        """The frame's camera-to-world pose in the session's frame, or None (lost)."""
        with limit_threads(self.trk.tc.threads):
            return self._track(frame)

    def _track(self, frame: Frame) -> Optional[np.ndarray]:
        trk = self.trk
        img = trk.pre(frame.image)
        if image_is_degenerate(img):
            return self._lose(frame, "degenerate image")
        prep = trk.flow.prepare(img)
        hit = self._follow(frame, prep) if self.located else None
        if hit is None:
            hit = relocalise(trk, self.ids, self.desc, img, prep)
            if hit is None:
                return self._lose(frame, "no stored keyframe matched")
            self.n_relocalisations += 1
            trk.velocity = torch.eye(4, dtype=torch.float64, device=trk.device)
            trk._spacing = (None, None)
            trk.last_pose = hit[1][0].clone()
            if self.relocalised_frame is None:
                self.relocalised_frame, self.relocalised_keyframe = int(frame.index), hit[0]
                log.info("relocalised at frame %d against keyframe %d", frame.index, hit[0])
        self.located = True
        trk._set_pose(hit[1][0], frame.index)
        T = trk.last_pose.cpu().numpy().copy()
        self.stamps.append(float(frame.timestamp))
        self.poses.append(T)
        return T

    def _lose(self, frame: Frame, why: str) -> None:
        if self.located:
            log.warning("frame %d: lost in the loaded map (%s); relocalising", frame.index, why)
        self.located = False
        self.n_lost += 1
        return None

    def trajectory(self) -> Tuple[np.ndarray, np.ndarray]:
        return (np.array(self.stamps, np.float64),
                np.stack(self.poses) if self.poses else np.zeros((0, 4, 4)))

    # what a graph's tracker node reads of its tracker (localize.LocalizeRole)
    trajectory_full = trajectory
    published: frozenset = frozenset()  # no keyframe is ever added
    timings: dict = {}
    on_pose_estimate = None

    @property
    def initialized(self) -> bool:      # located in the loaded map (now)
        return self.located

    @property
    def intrinsics(self) -> Intrinsics:
        return self.trk.intrinsics

    @property
    def last_pose(self) -> torch.Tensor:
        return self.trk.last_pose

    def predict(self) -> np.ndarray:
        return self.trk.predict()

    def skip(self, index: int, timestamp: float, frame=None) -> None:
        """A frame the busy node did not track: not posed (no keyframe to place it by)."""

    def keyframe_ids(self) -> List[int]:
        return list(self.ids)

    def keyframe_summary(self) -> dict:
        """No keyframe is made here (the tracker surface): nothing to count."""
        return {}

    def trajectory_keyframes(self) -> Tuple[np.ndarray, np.ndarray]:
        """The loaded map's keyframes (markers of the map the frames are posed in)."""
        return self.trk.kfs.trajectory(self.ids)


class ExtendTracker(Tracker):
    """The tracker of an extend run (``--load-map RUN`` without ``--localize``): the loaded
    session's keyframes are in its keyframe set, fixed, as keyframes published before.

    It starts lost: no warm-up, no initialisation of its own (which would start a map in
    another frame and scale). Each frame is relocalised (:func:`relocalise`) until one
    matches a stored keyframe; that keyframe and the stored one nearest to it become the
    window, oldest first, so local BA holds them fixed (the gauge and the scale of the
    loaded map) while new keyframes join with their flow edges. Frames before the first
    relocalisation are lost and not posed. After a loss mid-run (``tracking.reinit_after``)
    relocalisation is tried first on every frame; the new segment's warm-up (anchored by
    the motion before the loss) runs beside it and is dropped when a frame relocalises."""

    def __init__(self, cfg: SlamConfig, intrinsics: Intrinsics, session: Session,
                 flow_predictor=None):
        super().__init__(cfg, intrinsics, flow_predictor=flow_predictor)
        self.loaded_ids, self.desc = add_session_keyframes(self, session, intrinsics)
        diffs = pinhole_diffs(map_camera(session).to_dict(), self.map_intrinsics.to_dict())
        if diffs:
            raise SessionError(f"the map in {session.path.parent} was made at another mapping "
                               f"size (saved vs this configuration): {', '.join(diffs)}; use "
                               f"the camera.* settings of the run that made it")
        self.session_kfs = session.keyframes
        self.published.update(self.loaded_ids)
        # new ids continue loop_time_gap after the loaded ones: to loop detection, every
        # loaded keyframe is old enough for a loop from the first new one on
        self.next_kf = max(self.loaded_ids) + 1 + self.tc.loop_time_gap
        self.relocalised_frame: Optional[int] = None
        self.relocalised_keyframe: Optional[int] = None
        self.n_relocalisations = 0
        self.n_unplaced = 0             # frames before the first relocalisation (not posed)

    def new_keyframe_ids(self) -> List[int]:
        loaded = set(self.loaded_ids)
        return [k for k in self.keyframe_ids() if k not in loaded]

    def loaded_keyframes(self) -> SessionKeyframes:
        """The loaded session's keyframes with their current poses and disparities."""
        s = self.session_kfs
        poses, disps = _ba_state(self, self.loaded_ids)
        return SessionKeyframes(
            kf_ids=s.kf_ids, frame_indices=s.frame_indices, timestamps=s.timestamps,
            poses=poses, disparities=disps, images=s.images, descriptors=s.descriptors)

    def loaded_keyframe_data(self) -> List[KeyframeData]:
        """The loaded keyframes as the other stages take keyframes (tracking-size images)."""
        return keyframe_data(self.loaded_keyframes(), self.intrinsics)

    def _warmup(self, frame, img, prep) -> TrackStep:
        hit = relocalise(self, self.loaded_ids, self.desc, img, prep)
        if hit is not None:
            return self._relocalised(frame, img, prep, *hit)
        if self.relocalised_frame is not None:       # lost mid-run: a new segment meanwhile
            return super()._warmup(frame, img, prep)
        self.n_lost += 1
        self.n_unplaced += 1
        if self.n_unplaced == 1 or self.n_unplaced % 30 == 0:
            log.warning("frame %d: not relocalised in the loaded map yet (%d frames)",
                        frame.index, self.n_unplaced)
        return TrackStep(frame.index, float(frame.timestamp), False, None,
                         self.last_pose.cpu().numpy().copy(), lost=True, initialized=False,
                         info={"why": "not relocalised in the loaded map"})

    def _relocalised(self, frame, img, prep, k: int, fit) -> TrackStep:
        T = fit[0]
        self._reset()                   # a new segment's unfinished warm-up is dropped
        near = [j for j in nearest_keyframes(self, self.loaded_ids, T) if j != k][:1]
        self.window = near + [k]
        self.initialized = True
        self._anchor = self._before_loss = self._last_flow = None
        self.last_pose = T.clone()
        self.velocity = torch.eye(4, dtype=torch.float64, device=self.device)
        self._spacing = (None, None)
        self.n_relocalisations += 1
        if self.relocalised_frame is None:
            self.relocalised_frame, self.relocalised_keyframe = int(frame.index), int(k)
        log.info("frame %d: relocalised in the loaded map against keyframe %d", frame.index, k)
        return self._track(frame, img, prep)
