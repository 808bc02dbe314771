"""Proxy depth (paper §3.2 "Map Initialization", Eq. 10): the depth map of each keyframe
that the mapper supervises with, composed from the multi-view filtered BA depth and its fill.

For every keyframe the tracker hands on a disparity map at BA resolution (1/8 of the tracking
image). The mapper needs a depth map at the tracking resolution that it can trust:

1. Multi-view filter (Eq. 4-6, :func:`splat_slam_ros.tracking.multiview.multiview_filter`,
   shared with DSPO): a pixel of keyframe i keeps its depth when it reprojects consistently
   into ``>= n_c`` other keyframes and its depth is ``<= 3x`` the median valid depth. Only
   views with parallax count (baseline >= tan(``mv_min_parallax_deg``) x median depth,
   :func:`~splat_slam_ros.tracking.multiview.parallax_pairs`): without it every depth
   reprojects consistently. Done at BA resolution (the disparity carries no finer
   information), batched over (target, view) pairs.
2. Upsampling (:mod:`upsample`, :func:`upsample_disparity`) to the tracking resolution: bilinear in
   disparity (exact for planes) inside a 2x2 BA cell whose 4 pixels are valid and either
   within ``1 + upsample_disc`` of each other or continuous with the neighbouring cells
   (steep planes, creases: :func:`smooth_cells`); otherwise one corner's value is copied:
   the corner that best explains the pixel's colour (``depth.upsample_guided``, the depth
   edge then follows the image edge) or the nearest one, and the pixel is empty when that
   corner is. Across a depth discontinuity no intermediate ("flying") depth is produced.
   Then (``depth.dense_views`` > 0; off by default) the dense depth of :mod:`dense_depth`
   (per-pixel triangulation from DIS flow to neighbouring keyframes with the BA poses, kept
   where ``dense_min_views`` views agree) replaces it, and fills its holes where
   ``dense_fill_views`` agree.
3. Fill (:func:`~splat_slam_ros.depth.compose.compose_proxy_depth`, Eq. 10):
   - with a mono model: invalid pixels take the mono depth mapped by a least-squares
     scale/shift fitted on the valid pixels (Eq. 3, in depth as §3.2 says, or in disparity
     for disparity-output models, ``depth.mono_fit_space``); fitted values outside
     (0, 3x median] stay empty;
   - without (``depth.fill_holes_from_ba``, default on): the holes take the tracker's BA
     depth, upsampled the same way over every BA cell (source 3). It is coarser than the
     multi-view depth (on realistic fr2/desk renders about 15 cm mean error in the holes,
     against 3 cm where the filter keeps a pixel) but a map left without supervision
     there fills the holes with foreground Gaussians (30 cm, nearly all too close).
     With the option off holes stay holes (the mapper ignores them). Optionally
     (``depth.fill_small_holes`` > 0 px) enclosed holes up to that size are filled with the
     plane fitted (in disparity) to their 1-pixel rim, only when that rim is planar within
     ``fill_plane_tol``; holes across discontinuities, at the border or bigger stay empty.

``source`` codes: 0 empty, 1 multi-view (including its bilinear upsampling and plane-filled
small holes, both interpolations of multi-view depth), 2 mono, 3 BA depth in a hole.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np
import torch

from splat_slam_ros.config import ConfigError, SlamConfig
from splat_slam_ros.depth.compose import compose_proxy_depth, disp_to_depth, fit_mono
from splat_slam_ros.depth.dense_depth import DenseProxy
from splat_slam_ros.depth.upsample import corner_preference, upsample_disparity
from splat_slam_ros.imaging import image_at, to_gray
from splat_slam_ros.runtime import resolve_device
from splat_slam_ros.tracking.multiview import multiview_filter, sample_at_grid
from splat_slam_ros.types import Intrinsics, KeyframeData, UpdateEvent


class ProxyDepthError(ValueError):
    """Inconsistent inputs to the proxy depth stage (e.g. a disparity of the wrong size)."""


@dataclass
class ProxyDepthResult:
    """Proxy depth of one keyframe, what the mapper consumes (``splat_slam_msgs/ProxyDepth``)."""
    kf_id: int
    depth: np.ndarray          # (H, W) float32 metres (map scale), 0 = no depth
    source: np.ndarray         # (H, W) uint8: SOURCE_EMPTY / _MULTIVIEW / _MONO / _BA
    pose: np.ndarray           # 4x4 float64 camera-to-world used to compute it
    update_seq: int            # PoseGraphUpdate.seq it reflects (0 = first depth of a new KF)
    mono_scale: float = float("nan")   # fitted theta (nan: no mono fill)
    mono_shift: float = float("nan")   # fitted gamma
    n_views: int = 0           # other keyframes used by the multi-view filter

    @property
    def valid(self) -> np.ndarray:
        return self.source > 0




# --------------------------------------------------------------- estimator
def check_settings(dc) -> None:
    """ConfigError for depth settings out of range (before any keyframe arrives)."""
    if (dc.mono_fit_space or "auto").lower() not in ("auto", "depth", "disparity"):
        raise ConfigError(f"depth.mono_fit_space must be auto, depth or disparity, "
                          f"got {dc.mono_fit_space!r}")
    if not float(dc.update_tol) >= 0:
        raise ConfigError(f"depth.update_tol must be >= 0 (0: every change recomputes), "
                          f"got {dc.update_tol}")


@dataclass
class _KfState:
    kf_id: int
    pose: np.ndarray                 # 4x4 float64 c2w
    disparity: np.ndarray            # (h, w) float32
    mono: Optional[np.ndarray]       # (H, W) float16 relative depth (0 = none) or None
    guide: Optional[torch.Tensor] = None   # (H, W) uint8 corner preference (upsampling)
    result: Optional[ProxyDepthResult] = None
    n_views: int = 0                 # views used when ``result`` was computed
    grey: Optional[np.ndarray] = None   # (H, W) uint8 image for the dense depth
    ref_pose: Optional[np.ndarray] = None   # pose and disparity ``result`` was computed from
    ref_disparity: Optional[np.ndarray] = None


class ProxyDepthEstimator:
    """Stateful proxy depth for the depth node and the in-process pipeline.

    Keeps the pose, BA disparity, mono depth (float16), colour guide and last result of
    each keyframe (up to ``tracking.keyframe_buffer``; about 0.6 MB per keyframe at
    320x240 with a mono model); the other views of keyframe i in Eq. 6 are the
    ``depth.mv_neighbors`` stored keyframes nearest to i in keyframe id.
    """

    def __init__(self, cfg: SlamConfig, intrinsics: Intrinsics, mono_model=None):
        self.cfg = cfg
        self.dc = cfg.depth
        self.intr = intrinsics
        self.device = resolve_device(self.dc.device, "depth.device")
        self.capacity = max(2, int(getattr(cfg.tracking, "keyframe_buffer", 512)))
        self._kfs: "OrderedDict[int, _KfState]" = OrderedDict()
        self._refreshed: List[Tuple[ProxyDepthResult, ProxyDepthResult]] = []
        self.dirty: set = set()        # moved by deferred updates, not recomputed yet
        self.exact: set = set()        # ... of them, by the loop closer (update_tol not applied)
        self.followers: set = set()    # merged by the loop closer: they follow a kept keyframe
        self.last_seq = 0
        self._flush_seq = 0
        self.mono = mono_model
        self.mono_kind = getattr(mono_model, "kind", "depth")
        self._mono_path = None
        if self.mono is None and self.dc.mono_model:
            # the file and its sidecar are checked now; the network itself is loaded the
            # first time a keyframe arrives without ``mono_depth`` (the tracker may already
            # have run it for DSPO and passed the result along)
            from pathlib import Path

            from splat_slam_ros.tracking.mono_depth import check_mono_model
            self.mono_kind = check_mono_model(self.dc.mono_model).output   # MonoDepthError
            self._mono_path = Path(self.dc.mono_model).expanduser()
        check_settings(self.dc)
        fs = (self.dc.mono_fit_space or "auto").lower()
        self.fit_space = self.mono_kind if fs == "auto" else fs
        self.timings: Dict[str, float] = {"filter_ms": 0.0, "mono_ms": 0.0, "dense_ms": 0.0,
                                          "n": 0}
        # flows (kf, view) of the dense depth, reused when BA updates recompute a keyframe
        self.dense = DenseProxy(self.dc, self.intr)

    # ------------------------------------------------------------ queries
    def get(self, kf_id: int) -> Optional[ProxyDepthResult]:
        st = self._kfs.get(int(kf_id))
        return None if st is None else st.result

    def __len__(self) -> int:
        return len(self._kfs)

    def __contains__(self, kf_id) -> bool:
        return int(kf_id) in self._kfs

    def neighbours(self, kf_id: int) -> List[int]:
        """The other keyframes used for ``kf_id`` in Eq. 6 (nearest kf ids, older first on ties)."""
        others = [k for k in self._kfs if k != kf_id and k not in self.followers]
        others.sort(key=lambda k: (abs(k - kf_id), k))
        return sorted(others[: max(0, int(self.dc.mv_neighbors))])

    # ------------------------------------------------------------ updates
    def add_keyframe(self, kf: KeyframeData) -> ProxyDepthResult:
        """Store ``kf`` (running the mono model if configured) and return its proxy depth."""
        return self.add_keyframes([kf])[0]

    def add_keyframes(self, kfs: Sequence[KeyframeData]) -> List[ProxyDepthResult]:
        """Store several keyframes first, then compute them (e.g. the tracker's warm-up
        burst): each then sees the others as views, not only the older ones."""
        ids = []
        for kf in kfs:
            self._store(kf)
            ids.append(int(kf.kf_id))
        self._evict()
        ids = [k for k in ids if k in self._kfs]
        new = self._compute(ids, seq=0)
        # earlier keyframes computed with fewer views than configured gain the new ones
        want = max(0, int(self.dc.mv_neighbors))
        stale = [k for k, st in self._kfs.items() if k not in ids and st.result is not None
                 and k not in self.followers
                 and st.n_views < min(want, len(self._kfs) - 1)
                 and any(n in ids for n in self.neighbours(k))]
        if stale:
            olds = {k: self._kfs[k].result for k in stale}
            res = self._compute(stale, seq=None)
            for k in stale:
                if _differs(olds[k], res[k]):
                    self._refreshed.append((olds[k], res[k]))
        return [new[k] for k in ids]

    def take_refreshed(self) -> List[Tuple[ProxyDepthResult, ProxyDepthResult]]:
        """(old, new) proxy depths of earlier keyframes recomputed because a new keyframe
        gave them a view they lacked (only the first ``mv_neighbors`` keyframes); the caller
        forwards them to the mapper like update results. Clears the queue."""
        out, self._refreshed = self._refreshed, []
        return out

    def apply_update(self, ev: UpdateEvent, defer: bool = False, follow: bool = False
                     ) -> List[Tuple[ProxyDepthResult, ProxyDepthResult]]:
        """Apply a BA / loop-closure / global-BA update.

        Recomputes the keyframes whose pose or disparity changed and every stored keyframe
        that uses one of them as a view. Returns (old, new) for each keyframe whose pose,
        depth or source changed (what the mapper's deformation needs). ``defer``: only store
        the new poses / disparities (a newer update is already waiting; :meth:`flush` or the
        next update without ``defer`` recomputes everything moved since). ``follow``: the
        keyframes are ones the loop closer merged, moving rigidly with a kept keyframe (its
        poses-only updates; see :meth:`_follow`).
        """
        self.last_seq = max(self.last_seq, int(ev.seq))
        self._flush_seq = int(ev.seq)           # the results carry the newest update's seq
        poses = np.asarray(ev.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(poses) != len(ev.kf_ids):
            raise ProxyDepthError(f"update {ev.seq}: {len(ev.kf_ids)} kf_ids but "
                                  f"{len(poses)} poses")
        disps = None if ev.disparities is None else np.asarray(ev.disparities, np.float32)
        if follow:
            return self._follow(ev, poses) + ([] if defer else self.flush())
        for i, k in enumerate(ev.kf_ids):
            st = self._kfs.get(int(k))
            if st is None or int(k) in self.followers:
                continue
            moved = not np.array_equal(st.pose, poses[i])
            if moved:
                st.pose = poses[i].copy()
            if disps is not None:
                if disps[i].shape != st.disparity.shape:
                    raise ProxyDepthError(f"update {ev.seq}: disparity of kf {k} has shape "
                                          f"{disps[i].shape}, expected {st.disparity.shape}")
                if not np.array_equal(st.disparity, disps[i]):
                    st.disparity = disps[i].copy()
                    moved = True
            if moved:
                self.dirty.add(int(k))
                if ev.reason != "local_ba":
                    self.exact.add(int(k))
        return [] if defer else self.flush()

    def _follow(self, ev: UpdateEvent, poses: np.ndarray
                ) -> List[Tuple[ProxyDepthResult, ProxyDepthResult]]:
        """A poses-only update moves keyframes the loop closer merged into older views: each
        follows its kept keyframe rigidly, so its proxy depth (camera frame) stays and only
        its pose changes; it is not recomputed, it no longer serves as another keyframe's
        view (the kept one has that view), and its images are released. The
        depth stage's work and memory then follow the distinct views, not the keyframe
        count."""
        out = []
        for i, k in enumerate(ev.kf_ids):
            k = int(k)
            st = self._kfs.get(k)
            if st is None:
                continue
            self.followers.add(k)
            st.pose = poses[i].copy()
            if k in self.dirty or st.result is None:    # recomputed by the next flush
                continue
            st.guide = st.grey = st.mono = None
            self.dense.drop(k)
            out += self._repose(st, int(ev.seq))
        return out

    @staticmethod
    def _repose(st: _KfState, seq: int) -> List[Tuple[ProxyDepthResult, ProxyDepthResult]]:
        """``st``'s result at its new pose with the same depth (camera frame): [(old, new)],
        or [] when the pose did not change."""
        old = st.result
        if np.array_equal(old.pose, st.pose):
            return []
        st.result = replace(old, pose=st.pose.copy(), update_seq=seq)
        return [(old, st.result)]

    def flush(self) -> List[Tuple[ProxyDepthResult, ProxyDepthResult]]:
        """Recompute what the updates since the last flush moved (see :meth:`apply_update`):
        the keyframes that the loop closer moved (loop closure, global BA, final) or that
        local BA moved more than ``depth.update_tol`` since their proxy depth was computed,
        and every keyframe that uses one of them as a view. A keyframe that local BA moved
        less keeps its depth (camera frame) and only takes the new pose, as the loop
        closer's followers do: most local BA updates shift the older window keyframes by a
        few hundredths of a degree, and recomputing them for that made most of the depth
        stage's cost."""
        cset = {k for k in self.dirty if k in self._kfs}
        exact = self.exact
        self.dirty, self.exact = set(), set()
        if not cset:
            return []
        moved = {k for k in cset if k in exact or self._moved(self._kfs[k])}
        recompute = [k for k in self._kfs if k in moved or (
            k not in self.followers and any(n in moved for n in self.neighbours(k)))]
        olds = {k: self._kfs[k].result for k in recompute}
        new = self._compute(recompute, seq=self._flush_seq)
        out = []
        for k in recompute:
            old = olds[k]
            if old is None or k in cset or _differs(old, new[k]):
                out.append((old, new[k]))
        for k in sorted(cset - set(recompute)):        # moved less than update_tol: pose only
            out += self._repose(self._kfs[k], self._flush_seq)
        return out

    def _moved(self, st: _KfState) -> bool:
        """Whether ``st`` moved more than ``depth.update_tol`` since its proxy depth was
        computed: the camera by more than that fraction of its median depth (translation
        plus rotation angle x median depth) or its disparity by more than that relative
        change (the median over the cells valid in both; a region that changes much under a
        steady median is left to the loop closer's updates, which always recompute)."""
        tol = float(self.dc.update_tol)
        if tol <= 0 or st.result is None or st.ref_pose is None:
            return True
        d, d0 = st.disparity, st.ref_disparity
        both = (d > 0) & (d0 > 0)
        if not both.any():
            return True
        if float(np.median(np.abs(d[both] - d0[both]) / d0[both])) > tol:
            return True
        rel = np.linalg.inv(st.ref_pose) @ st.pose       # the motion in the old camera frame
        cos = np.clip((np.trace(rel[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
        depth = 1.0 / float(np.median(d[d > 0]))
        return float(np.linalg.norm(rel[:3, 3])) + float(np.arccos(cos)) * depth > tol * depth

    # ------------------------------------------------------------ internals
    def _store(self, kf: KeyframeData) -> None:
        disp = np.asarray(kf.disparity, np.float32)
        if disp.ndim != 2:
            raise ProxyDepthError(f"keyframe {kf.kf_id}: disparity must be 2-D, got {disp.shape}")
        for st in self._kfs.values():
            if st.disparity.shape != disp.shape:
                raise ProxyDepthError(f"keyframe {kf.kf_id}: disparity {disp.shape} differs "
                                      f"from earlier keyframes {st.disparity.shape}")
            break
        H, W = self.intr.height, self.intr.width
        mono = None
        if kf.mono_depth is not None:
            mono = np.asarray(kf.mono_depth, np.float32)
        elif self.mono is not None or self._mono_path is not None:
            import time
            if self.mono is None:
                from splat_slam_ros.tracking.mono_depth import load_mono_depth
                self.mono = load_mono_depth(self._mono_path, self.dc.mono_provider)
            t0 = time.perf_counter()
            mono = self.mono.predict(np.asarray(kf.image))
            self.timings["mono_ms"] += 1e3 * (time.perf_counter() - t0)
        if mono is not None and mono.shape != (H, W):
            mono = cv2.resize(mono, (W, H), interpolation=cv2.INTER_LINEAR)
        if mono is not None:       # kept for recomputations; relative depth: 1e-3 is plenty
            mono = np.where(np.isfinite(mono) & (mono > 0), mono, 0).astype(np.float16)
        guide = grey = None
        img = np.asarray(kf.image) if kf.image is not None else None
        if img is not None and img.ndim in (2, 3):
            img = image_at(img, W, H)
        if self.dc.upsample_guided and img is not None and img.ndim == 3:
            guide = corner_preference(img, disp.shape[0], disp.shape[1])
        if self.dc.dense_views > 0 and img is not None and img.ndim in (2, 3):
            grey = to_gray(img).astype(np.uint8, copy=False)
        old = self._kfs.pop(int(kf.kf_id), None)
        self._kfs[int(kf.kf_id)] = _KfState(int(kf.kf_id), np.asarray(kf.pose, np.float64).copy(),
                                            disp.copy(), mono, guide,
                                            old.result if old is not None else None,
                                            grey=grey)
        self.dense.drop(int(kf.kf_id))               # a new image: its old flows are stale
        # keep insertion order == kf id order for neighbour lookups
        if len(self._kfs) > 1 and list(self._kfs)[-2] > int(kf.kf_id):
            self._kfs = OrderedDict(sorted(self._kfs.items()))

    def _evict(self) -> None:
        while len(self._kfs) > self.capacity:
            k, _ = self._kfs.popitem(last=False)
            self.dense.drop(k)

    def _compute(self, ids: Sequence[int], seq: Optional[int]) -> Dict[int, ProxyDepthResult]:
        import time
        if not ids:
            return {}
        t0 = time.perf_counter()
        nb = {k: self.neighbours(k) for k in ids}
        used = sorted(set(ids).union(*[set(v) for v in nb.values()]))
        index = {k: i for i, k in enumerate(used)}
        dev = self.device
        disp = torch.from_numpy(np.stack([self._kfs[k].disparity for k in used])).to(dev)
        poses = torch.from_numpy(np.stack([self._kfs[k].pose for k in used])).to(dev)
        h, w = disp.shape[1:]
        intr_ba = self.intr.resized(w, h)      # the (h, w) BA grid
        pairs = torch.tensor([(index[k], index[n]) for k in ids for n in nb[k]],
                             dtype=torch.long, device=dev).reshape(-1, 2)
        depth_ba = disp_to_depth(disp)
        valid_ba, _ = multiview_filter(depth_ba, poses, intr_ba, self.dc.mv_eta,
                                       self.dc.mv_min_views, self.dc.mv_max_depth_ratio,
                                       pairs=pairs,
                                       min_parallax_deg=self.dc.mv_min_parallax_deg)
        self.timings["filter_ms"] += 1e3 * (time.perf_counter() - t0)
        self.timings["n"] += len(ids)
        H, W = self.intr.height, self.intr.width
        out = {}
        for k in ids:
            i = index[k]
            st = self._kfs[k]
            dup, vup = upsample_disparity(disp[i], valid_ba[i], (H, W), self.dc.upsample_disc,
                                          st.guide)
            mv_depth = disp_to_depth(dup)
            mono = None if st.mono is None else torch.from_numpy(st.mono).to(dev).float()
            fit = None
            if mono is not None:   # Eq. 3 at BA resolution (multi-view depth not interpolated)
                fit = fit_mono(sample_at_grid(mono, h, w), depth_ba[i], valid_ba[i],
                               self.fit_space)
            mv_valid = vup & (mv_depth > 0)
            mv_depth, mv_valid = self._densify(k, nb[k], mv_depth, mv_valid, depth_ba[i],
                                               valid_ba[i])
            ba_depth = None
            if mono is None and self.dc.fill_holes_from_ba:     # every BA cell, same upsampling
                dall, vall = upsample_disparity(disp[i], disp[i] > 0, (H, W),
                                                self.dc.upsample_disc, st.guide)
                ba_depth = torch.where(vall, disp_to_depth(dall), torch.zeros_like(dall))
            depth, source, th, ga = compose_proxy_depth(
                mv_depth, mv_valid, mono, self.fit_space,
                int(self.dc.fill_small_holes), self.dc.fill_plane_tol,
                self.dc.mv_max_depth_ratio, scale_shift=fit, ba_depth=ba_depth)
            s = seq if seq is not None else (st.result.update_seq if st.result else 0)
            res = ProxyDepthResult(k, depth, source, st.pose.copy(), int(s), th, ga, len(nb[k]))
            st.result = res
            st.n_views = len(nb[k])
            st.ref_pose, st.ref_disparity = st.pose.copy(), st.disparity.copy()
            out[k] = res
        return out


    def _densify(self, k: int, nb: Sequence[int], mv_depth: torch.Tensor,
                 mv_valid: torch.Tensor, depth_ba: torch.Tensor, valid_ba: torch.Tensor
                 ) -> Tuple[torch.Tensor, torch.Tensor]:
        """Dense multi-view depth over the BA-grid depth (:class:`DenseProxy`)."""
        import time
        st = self._kfs[k]
        if self.dc.dense_views <= 0 or st.grey is None:
            return mv_depth, mv_valid
        t0 = time.perf_counter()
        ok = valid_ba if bool(valid_ba.any()) else depth_ba > 0
        med = float(depth_ba[ok].median()) if bool(ok.any()) else 0.0
        cands = [(n, self._kfs[n].grey, self._kfs[n].pose) for n in nb
                 if self._kfs[n].grey is not None]
        out = self.dense.apply(k, st.grey, st.pose, cands, med, mv_depth, mv_valid)
        self.timings["dense_ms"] += 1e3 * (time.perf_counter() - t0)
        return out


def _differs(a: ProxyDepthResult, b: ProxyDepthResult) -> bool:
    return (not np.array_equal(a.pose, b.pose) or not np.array_equal(a.source, b.source)
            or not np.array_equal(a.depth, b.depth))
