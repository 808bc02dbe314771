"""The tracker's front end (paper §3.1): what happens to each input frame once the tracker
is initialised.

Dense flow from the newest keyframe (``FlowPredictor``; DIS started from the previous frame's
flow), the pose-only Gauss-Newton fit against that keyframe's disparity (the pose block of
Eq. 1), the fallbacks when the flow is not confident (DIS pre-warped by the
constant-velocity pose, the other recent keyframes) and the keyframe decision: a
motion-filter candidate is added, and kept as a keyframe only when after its local BA the
flow its optimised estimate induces reaches ``tracking.keyframe_thresh``.

:class:`TrackerFrontend` is a part of :class:`~splat_slam_ros.tracking.tracker.Tracker`
and works on that object's state.
"""
from __future__ import annotations

import logging
import time

import numpy as np
import torch

from splat_slam_ros.geometry import (disparity_through_flow, orthonormalize, se3_exp,
                                     se3_inverse, se3_log)
from splat_slam_ros.imaging import image_is_degenerate
from splat_slam_ros.tracking.dense_ba import induced_flow_distance, pose_only_refine, reproject
from splat_slam_ros.tracking.flow_frontend import predict_both
from splat_slam_ros.tracking.keyframe_set import BUDGET_CAUSES
from splat_slam_ros.tracking.motion_filter import MotionFilter, predict_pose
from splat_slam_ros.tracking.rolling_shutter import median_depth, readout_motion, rectify
from splat_slam_ros.types import TrackStep

log = logging.getLogger(__name__)


def observed_weight(weight: torch.Tensor, conf, full_at: float) -> torch.Tensor:
    """Flow weights (h, w, 2) of a frame's pose fit against a keyframe, scaled by how well the
    keyframe's own edges observed each cell: its confidence ``conf`` (h, w), in full from
    ``full_at`` on, in proportion below (``full_at`` 0 or no ``conf``: unchanged). A new
    keyframe's cells that its edge to the previous one never saw (on fast motion, the part of
    the view that is entering, which the next frames see best) hold a disparity filled in,
    not measured; a frame's flow there is right, and fitted to that depth it bent the pose
    (a 9 cm move taken for a rotation, and the scale of every later keyframe with it)."""
    if full_at <= 0 or conf is None:
        return weight
    return weight * (conf / full_at).clamp(0.0, 1.0)[..., None].to(weight)


RS_KEEP = 256        # frames whose stamp and rectification motion are kept


class TrackerFrontend:
    """Frame-to-keyframe flow, pose fit and keyframe decision of the tracker."""

    def _motion_filter(self) -> MotionFilter:
        tc = self.tc
        return MotionFilter(tc.motion_filter_thresh * self.px_scale,
                            min_valid_frac=tc.lost_min_valid, max_rate=tc.max_keyframe_rate,
                            min_interval=tc.min_keyframe_interval,
                            urgent_flow=tc.keyframe_urgent_flow,
                            urgent_valid=tc.keyframe_urgent_valid,
                            rel_texture=tc.lost_rel_texture)

    def _ref_tex(self, ref):
        """Keyframe ``ref``'s texture factor per BA cell for the loss test (None when the
        flow predictor keeps none: the learned one)."""
        return getattr(self.kfs[ref].prep, "tex", None)

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

    def _predicted_flow(self, ref, index: int) -> torch.Tensor:
        """Flow keyframe ``ref`` -> frame ``index`` that the constant-velocity pose induces."""
        return self._induced(self.kfs[ref].pose, self.kfs[ref].disp, self._predict_at(index))

    def _store_flow(self, f, w):
        return f.detach().to("cpu", torch.float16), w.detach().to("cpu", torch.float16)

    def _try_reference(self, ref, prep, use_last: bool = True, index=None):
        """Flows keyframe ``ref`` <-> the frame, their check, and whether DIS started from
        the predicted motion. DIS starts from the previous frame's measured flow to the same
        keyframe (temporal propagation; image-based, so a wrong disparity cannot corrupt it);
        without one (the first frame after a keyframe), from the flow that frame ``index``'s
        constant-velocity pose induces (``index`` None: from zero)."""
        init = self._last_flow[1] if use_last and self._last_flow is not None and \
            self._last_flow[0] == ref else None
        predicted = init is None and index is not None
        if predicted:
            init = self._predicted_flow(ref, index)
        f, w, fb, wb = self._flows(self.kfs[ref].prep, prep, init)
        return (f, w, fb, wb), self.motion.check(f, w, self._ref_tex(ref)), predicted

    def _gate_by_prediction(self, ref, f, w, index):
        """Cells whose flow lies more than ``tracking.flow_pred_gate`` (reference BA px) from
        the flow frame ``index``'s constant-velocity pose induces get no weight, when at least
        ``flow_pred_agree`` of the confident weight agrees with that flow (a wrong period of a
        repetitive texture; a motion the prediction missed leaves the weights as they are)."""
        gate = self.tc.flow_pred_gate * self.px_scale
        if gate <= 0:
            return w
        near = ((f - self._predicted_flow(ref, index)).norm(dim=-1) < gate).to(w.dtype)
        conf = w.mean(-1)
        conf = conf * (conf > self.motion.cell_weight)
        total = float(conf.sum())
        if total <= 0 or float((conf * near).sum()) < self.tc.flow_pred_agree * total:
            return w
        return w * near[..., None]

    def _fit_pose(self, ref, f, w, inits):
        """Pose-only fit of the frame against the flow ref -> frame; best of ``inits``."""
        best = None
        t0 = time.perf_counter()
        w = observed_weight(w, self.kfs[ref].conf, self.tc.pose_ref_conf)
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

    def _track(self, frame, img, prep, gap=(), bridged: bool = False):
        """Track ``frame`` against the newest keyframe. ``gap``: frames skipped since the
        last tracked one (live input, :meth:`skip`), in order, to bridge a motion too large
        for the flow (:meth:`_bridge`). ``bridged``: the frame is such a skipped frame, tracked
        after all: None instead of a lost step when it cannot be aligned."""
        tc = self.tc
        ref = self.window[-1]
        was_lost = self.lost_count > 0
        pred = self.last_pose @ self.velocity
        # predicted, 1: the flow was started from the prediction (the first frame after a
        # keyframe, or the retry below)
        flows, fc, predicted = self._try_reference(
            ref, prep, not was_lost,
            frame.index if not was_lost and self.tc.predict_first_flow else None)
        predicted = float(predicted)
        if not fc.ok and not was_lost and not predicted:
            # a large motion since the last tracked frame (skipped frames on live input, fast
            # motion): DIS again, pre-warped by the flow the constant-velocity pose induces
            T_p = self._predict_at(frame.index)
            init = self._induced(self.kfs[ref].pose, self.kfs[ref].disp, T_p)
            fl = self._flows(self.kfs[ref].prep, prep, init)
            fc_p = self.motion.check(fl[0], fl[1], self._ref_tex(ref))
            if fc_p.ok:
                flows, fc, pred, predicted = fl, fc_p, T_p, 1.0
        # a gap of skipped frames and a flow that failed or is weak: a skipped frame between
        if gap and not was_lost and (not fc.ok or self._weak_flow(fc)):
            if self.on_pose_estimate is not None and not bridged and \
                    self._announced != frame.index:
                # the bridge takes a few frames' tracking: the predicted pose goes out first
                self._announced = frame.index
                self.on_pose_estimate(frame.index, float(frame.timestamp),
                                      self._predict_at(frame.index).cpu().numpy())
            rest = self._bridge(gap)
            if rest is not None:                    # tracked again from a nearer frame
                return self._track(frame, img, prep, rest, bridged)
        if not fc.ok and bridged:
            return None
        if not fc.ok and not was_lost and self._retreat():
            return self._track(frame, img, prep, (), bridged)
        if not fc.ok:
            self._last_flow = None
            # relocalise against the other recent keyframes
            for k in reversed(self.window[-1 - tc.reloc_keyframes:-1]):
                flows_k, fc_k, _ = self._try_reference(k, prep, False)
                if fc_k.ok:
                    ref, flows, fc = k, flows_k, fc_k
                    break
        if not fc.ok:
            return self._lost(frame, f"low flow confidence ({fc.valid_frac:.2f} valid)")
        f, w, fb, wb = flows
        T_ref = self.kfs[ref].pose
        inits = [T_ref.clone()] if was_lost else [pred, self.last_pose.clone(), T_ref.clone()]
        T, pinfo = self._fit_pose(ref, f, w, inits)
        gated = 0.0
        if not was_lost and pinfo is not None and \
                pinfo.rms * tc.ba_downsample > tc.flow_pred_rms_px:
            # a poor fit: without the cells far from the predicted flow (a wrong period)
            w_g = self._gate_by_prediction(ref, f, w, frame.index)
            if w_g is not w:
                T_g, p_g = self._fit_pose(ref, f, w_g, inits)
                if p_g is not None and np.isfinite(p_g.rms):
                    T, pinfo, w, gated = T_g, p_g, w_g, 1.0
        if pinfo is None or not np.isfinite(pinfo.rms) or pinfo.rms > tc.lost_rms:
            if bridged:
                return None
            return self._lost(frame, f"pose did not fit the flow (rms "
                                     f"{getattr(pinfo, 'rms', float('nan')):.2f} BA px)")
        if was_lost:
            log.info("frame %d: tracking recovered against keyframe %d after %d lost frames",
                     frame.index, ref, self.lost_count)
        self.lost_count = 0
        self._last_flow = (ref, f)
        info = {"mean_flow": fc.mean_flow, "valid": fc.valid_frac, "pose_rms": pinfo.rms,
                "predicted": predicted, "pred_gated": gated}
        since_kf = float(frame.timestamp) - self.kfs[ref].timestamp
        cause = self.motion.candidate(fc, since_kf, self._recent_keyframes(frame))
        if cause is not None and ref == self.window[-1]:
            # a keyframe's pose before its local BA (not a bridged frame's: its pose was
            # published when it arrived, and a robot reads the newest frame's)
            if self.on_pose_estimate is not None and not bridged:
                self.on_pose_estimate(frame.index, float(frame.timestamp), T.cpu().numpy())
            return self._new_keyframe(frame, img, prep, ref, T, f, w, fb, wb, info,
                                      cause=cause)
        self._set_pose(T, frame.index)
        sf, sw = self._store_flow(f, w)
        rec = self._record(frame, ref_kf=ref, rel_pose=(se3_inverse(T_ref) @ T).cpu().numpy(),
                           ref_scale=float(self.kfs[ref].disp.mean()), flow=sf, weight=sw,
                           online_pose=T.cpu().numpy())
        self._add_pending(rec, frame, img, prep)
        return TrackStep(frame.index, float(frame.timestamp), False, None,
                         T.cpu().numpy().copy(), info=info)

    def _predict_at(self, index: int) -> torch.Tensor:
        """Constant-velocity pose of frame ``index``, the motion scaled to the frames since
        the last tracked one (right after the initialisation or a loss: the last two
        keyframes' motion)."""
        if self._spacing[0] is None and len(self.window) > 1:   # no step since init / loss
            a, b = self.kfs[self.window[-2]], self.kfs[self.window[-1]]
            return predict_pose(b.pose, se3_inverse(a.pose) @ b.pose,
                                (a.frame_index, b.frame_index), index)
        return predict_pose(self.last_pose, self.velocity, self._spacing, index)

    def _recent_keyframes(self, frame) -> int:
        """Keyframes of the window made in the second of input before ``frame`` (the rate
        bound's count; the warm-up's and the fast ones are not counted)."""
        t = float(frame.timestamp)
        return sum(self.kfs[k].cause in BUDGET_CAUSES and t - self.kfs[k].timestamp < 1.0 - 1e-3
                   for k in self.window)

    def _weak_flow(self, fc) -> bool:
        """A flow that passed the check but holds only as far as when the view is leaving the
        keyframe (confident cells below ``keyframe_urgent_valid`` x their typical fraction):
        after a large motion it is partly wrong, and a keyframe made from it corrupts the
        window's depth (a V1_02 render live: 67 cm after such a keyframe, 0.53 cm bridged)."""
        m = self.motion
        return fc.ok and fc.valid_frac < m.urgent_valid * m.typical_valid_frac

    def _bridge(self, gap):
        """Frames skipped since the last tracked one (live input, a busy tracker) bridge a
        motion too large for the flow: the one in the middle of ``gap`` is tracked first
        (itself bridged by the frames before it), so the frame that needed it is aligned
        against a nearer pose and keyframe. Its step joins ``_bridged_steps`` and its record
        replaces its skipped one. Returns the frames of ``gap`` after it, or None when no
        frame of the gap could be tracked."""
        mid = len(gap) // 2
        f = gap[mid]
        n_before = self.n_bridged
        pos, skipped = self._take_skipped(f.index)
        n0 = len(self.records)
        img = self._rectified(f, self.pre(f.image))
        step = None
        if not image_is_degenerate(img):
            step = self._track(f, img, self.flow.prepare(img), gap[:mid], bridged=True)
        if step is None:                    # not aligned: it stays a skipped frame
            self.records.insert(pos, skipped)
            self.n_skipped += 1
        else:
            self._move_record(f.index, n0, pos)
            self.n_bridged += 1
            self._bridged_steps.append(step)
        return list(gap[mid + 1:]) if self.n_bridged > n_before else None

    def _retreat(self) -> bool:
        """The flow to the newest keyframe failed, and the frame before this one was tracked
        against it and moved at least half the motion threshold: that frame becomes a
        keyframe ("promoted", past the interval and the rate bound) and this one is tracked
        against it. A motion too fast for the keyframe interval (a 15-Hz camera on a drone:
        two frames apart the view has moved too far) does not lose the track. The
        keyframe's step goes out with this frame's (as a bridged one's); the motion model
        stays that of the frames before."""
        velocity, spacing = self.velocity, self._spacing
        step = self._promote_last_input("promoted")
        if step is None:
            return False
        self.velocity, self._spacing = velocity, spacing
        step.info["promoted"] = 1.0
        self._bridged_steps.append(step)
        return True

    def _readout_motion(self):
        """The motion model's motion for the rolling-shutter rectification: its last tracked
        step, or, right after the initialisation or a relocalisation, the last two keyframes'
        motion; at the newest keyframe's median depth. None when unknown (warm-up, lost)."""
        i0, i1 = self._spacing
        depth = median_depth(self.kfs[self.window[-1]].disp) if self.window else 0.0
        if i0 is not None and i1 is not None and i0 in self._stamps and i1 in self._stamps:
            return readout_motion(self.velocity.cpu().numpy(),
                                  self._stamps[i1] - self._stamps[i0], depth)
        if self.initialized and self.lost_count == 0 and len(self.window) > 1:
            a, b = self.kfs[self.window[-2]], self.kfs[self.window[-1]]
            return readout_motion((se3_inverse(a.pose) @ b.pose).cpu().numpy(),
                                  b.timestamp - a.timestamp, depth)
        return None

    def _rectified(self, frame, img, intrinsics=None):
        """``img``, an image of ``frame`` (the tracking image; ``intrinsics``: another one's,
        the mapping image), rectified for the rolling shutter (camera.rolling_shutter_ms) at
        the motion model's motion when the frame first came: every image of a frame the same
        way."""
        if self.rs_readout <= 0:
            return img
        i = int(frame.index)
        self._stamps[i] = float(frame.timestamp)
        if i not in self._rs_motion:
            self._rs_motion[i] = self._readout_motion()
            if len(self._stamps) > 2 * RS_KEEP:          # only recent frames are needed
                for d in (self._stamps, self._rs_motion):
                    for k in [k for k in d if k < i - RS_KEEP]:
                        del d[k]
        return rectify(img, self.intrinsics if intrinsics is None else intrinsics,
                       self._rs_motion[i], self.rs_readout, self.rs_stamp_row)

    def _set_pose(self, T, index: int):
        self._spacing = (self._spacing[1], int(index))
        T = orthonormalize(T)
        # constant-velocity model in the tangent space (exp keeps it a rigid motion)
        self.velocity = se3_exp(se3_log(se3_inverse(self.last_pose) @ T))
        self.last_pose = T.clone()

    def _new_keyframe(self, frame, img, prep, ref, T, f, w, fb, wb, info,
                      cause: str, force: bool = False) -> TrackStep:
        tc = self.tc
        before = self._snapshot(self.window)
        kid = self._add_keyframe(frame, img, prep, T, disparity_through_flow(
            self.kfs[ref].disp, self.grid, fb, wb, self.intr, self.kfs[ref].pose, T))
        self.kfs[kid].conf = wb.mean(-1)
        self.kfs[kid].cause = cause
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
