"""The tracker's back end (paper §3.1): the factor graph over the keyframe window and its
optimisation.

A new keyframe gets flow edges to the keyframes up to ``frontend_radius`` before it and to
nearby window keyframes by induced flow (:func:`factor_graph.proximity_pairs`); the window
is trimmed to ``frontend_window`` keyframes; local dense BA (Eq. 1) runs over it, followed
by the ``depth_prior`` hook (DSPO, Eq. 2, :mod:`dspo`) that sees a :class:`BAState`. Changes
to published keyframes become update events; the updates of loop closure and global BA come
back through :meth:`TrackerBackend.apply_update`.

:class:`TrackerBackend` is a part of :class:`~splat_slam_ros.tracking.tracker.Tracker` and
works on that object's state.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Dict, List

import numpy as np
import torch

from splat_slam_ros.geometry import orthonormalize, se3_inverse
from splat_slam_ros.tracking.dense_ba import bundle_adjust, reproject
from splat_slam_ros.tracking.dspo import make_depth_prior
from splat_slam_ros.tracking.factor_graph import proximity_pairs
from splat_slam_ros.types import UpdateEvent


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


class TrackerBackend:
    """Factor graph window, local BA with the DSPO hook and keyframe updates of the tracker."""

    def _default_prior(self, intrinsics):
        if not (self.cfg.depth.mono_model and self.tc.dspo):
            return None
        return make_depth_prior(self.cfg, self.map_intrinsics)   # Eq. 2 (DSPO); errors propagate

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
            if self.motion.check(f, w, self._ref_tex(k)).ok:
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
            tex = self._ref_tex(a)
            fc = self.motion.check(f, w, tex)
            if fc.valid_frac < 0.5 * max(self.motion.typical_valid_frac,
                                         self.motion.min_valid(tex)):
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

    def _drop_keyframe(self, kid: int) -> None:
        self.graph.remove_node(kid)
        self.window.remove(kid)
        self.kfs.remove(kid)
        self.next_kf = kid          # ids stay contiguous

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
