"""The Gaussian mapper (§3.2 "Keyframe Selection and Optimization", supplementary Method).

Per tracker keyframe (``Mapper.add_keyframe``):

1. render the map at the keyframe's pose; the keyframe is mapped only if its covisibility
   with the last mapped keyframe is low or the camera moved enough (keyframe_window.py);
2. new Gaussians are anchored from its proxy depth (map_init.py) and it joins the window;
3. ``iters_per_keyframe`` Adam iterations (``iters_first`` for the first keyframe) on the
   Eq. 11 loss summed over the window keyframes (+ a few random older ones, optimise.py);
4. every ``densify_every`` / ``prune_every`` iterations: 3DGS densification and opacity /
   size pruning; when the window is full, visibility pruning of the newest Gaussians
   (densify.py).

Pose/depth updates from BA, loop closure or global BA deform the anchored Gaussians
(``apply_update``, deformation.py) before the next mapping step. ``final_refine`` runs the
supplementary's final refinement (random single keyframes, no pruning/densification). The
keyframes' exposures and the vignetting are the camera model's (camera_model.py); the
state as arrays and back is persistence.py's.
"""
from __future__ import annotations

import time
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.mapping.budget import (Budget, final_refine_budget, keyframe_budget,
                                           steps_summary)
from splat_slam_ros.mapping.camera_model import CameraModel
from splat_slam_ros.mapping.deformation import deform_keyframe, merge_keyframe
from splat_slam_ros.mapping.densify import DensifyStrategy
from splat_slam_ros.mapping.gaussian_map import GaussianMap
from splat_slam_ros.mapping.keyframe_inputs import (MapError, MappedKeyframe,
                                                    check_keyframe_inputs, check_pose)
from splat_slam_ros.mapping.keyframe_views import history_entry
from splat_slam_ros.mapping.keyframe_window import KeyframeDecision, KeyframeWindow
from splat_slam_ros.mapping.map_init import init_gaussians, uncovered
from splat_slam_ros.mapping.optimise import lattice_steps, optimise, render_map, visible_in_map
from splat_slam_ros.mapping.ply_io import PlyError, load_gaussians_ply, save_gaussians_ply
from splat_slam_ros.mapping.rasterizer import select_backend
from splat_slam_ros.mapping.rasterizer.projection import LOW_PASS
from splat_slam_ros.runtime import resolve_device
from splat_slam_ros.types import Intrinsics


class KeyframeRender(NamedTuple):
    """One keyframe's render: colour (H, W, 3) without exposure, alpha-blended depth and the
    accumulated opacity (H, W)."""
    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor


class Mapper:
    """Deformable 3D Gaussian map built from keyframes with poses and proxy depth."""

    def __init__(self, cfg: SlamConfig, intrinsics: Intrinsics, device=None):
        self.cfg = cfg
        m = self.mcfg = cfg.mapping
        if intrinsics.fx <= 0 or intrinsics.fy <= 0:
            raise MapError(f"mapper needs positive focal lengths (fx={intrinsics.fx}, "
                           f"fy={intrinsics.fy}); open the data with datasets.open_dataset, "
                           "which converts negative-focal (ICL-NUIM) cameras")
        if m.window_size < 1 or m.downsample < 1 or m.downsample_first < 1:
            raise MapError("mapping.window_size and mapping.downsample* must be >= 1")
        if not (1 <= m.step_subsample <= 8 and 1 <= m.refine_subsample <= 8
                and 0 <= m.step_subsample_newest <= 8):
            raise MapError(f"mapping.step_subsample and mapping.refine_subsample must be 1..8, "
                           f"mapping.step_subsample_newest 0..8 (render 1/n of the pixels per "
                           f"axis), got {m.step_subsample}, {m.refine_subsample} and "
                           f"{m.step_subsample_newest}")
        if not 0.0 <= m.ba_depth_weight <= 1.0:
            raise MapError(f"mapping.ba_depth_weight must be in [0, 1], got {m.ba_depth_weight}")
        if not m.init_scale > 0:
            raise MapError(f"mapping.init_scale must be > 0, got {m.init_scale}")
        self.device = resolve_device(device or m.device, "mapping.device")
        self.K = intrinsics
        self.W, self.H = int(intrinsics.width), int(intrinsics.height)
        self.intr = (float(intrinsics.fx), float(intrinsics.fy), float(intrinsics.cx),
                     float(intrinsics.cy))
        self.map = GaussianMap(self.device, {
            "means": m.lr_means, "quats": m.lr_rotations, "log_scales": m.lr_scales,
            "opacity_logits": m.lr_opacity, "colors": m.lr_colors})
        self.window = KeyframeWindow(m.window_size, m.kf_covisibility, m.kf_translation,
                                     m.kf_cutoff)
        self.keyframes: Dict[int, MappedKeyframe] = {}
        self.camera = CameraModel(m, self.device)    # exposures a_k, b_k and vignetting
        self.gen = torch.Generator().manual_seed(int(m.seed))
        self.rng = np.random.default_rng(int(m.seed))
        self.iteration = 0
        self.seedings = 0               # keyframes that seeded Gaussians (visible sets' stamp)
        self.settled_uid = 0            # opacity pruning spares uids below (a loaded map's)
        self.n_deformations = 0
        self.n_deformed_gaussians = 0
        self.strategy = DensifyStrategy(m)           # densify / prune and their counts
        self.next_index = 0            # MappedKeyframe.index of the next mapped keyframe
        self.pruned_at = 0             # next_index at the last visibility pruning
        self.last_ms = 0.0
        self.skipped_iters = 0         # steps a wall-clock budget cut (mapping.time_budget)
        self.background_iters = 0      # steps between keyframes (live: mapping.background_steps)
        self.refine_info: Dict[str, float] = {}   # the final refinement's steps (final_refine)
        self.last_mapped_ts: Optional[float] = None
        self.last_loss = float("nan")
        self.scene_depth = 0.0
        self.raster = select_backend(m.raster_backend, self.device, announce=True)  # logs it
        self.progress = False          # tqdm bar for long optimisations (first keyframe)
        self.history: List[dict] = []  # one entry per add_keyframe (the run report's map size)

    @property
    def counts(self) -> Dict[str, int]:
        """What densification, pruning and merging added and removed (the strategy's)."""
        return self.strategy.counts

    @property
    def vignette(self) -> torch.Tensor:
        """The learned vignetting (v1, v2) of the camera model."""
        return self.camera.vignette

    # ================================================================ render
    def _raster(self, pose, intr=None, width=None, height=None, attrs=None,
                low_pass: float = LOW_PASS):
        return render_map(self.map, pose, intr or self.intr, width or self.W, height or self.H,
                          self.raster.name, self.device, attrs=attrs, low_pass=low_pass)

    @torch.no_grad()
    def visible_uids(self, pose) -> torch.Tensor:
        """Uids of the Gaussians a render at ``pose`` composites while T >= 0.5 (the
        covisibility sets), without rendering the image."""
        if len(self.map) == 0:
            return self.map.uid[:0]
        vis = visible_in_map(self.map, pose, self.intr, self.W, self.H, self.raster.name,
                             self.device)
        return self.map.uid[vis]

    @torch.no_grad()
    def render(self, pose, width: Optional[int] = None, height: Optional[int] = None,
               kf_id: Optional[int] = None,
               intrinsics: Optional[Sequence[float]] = None) -> Tuple[np.ndarray, np.ndarray]:
        """Render (rgb uint8 HxWx3, depth float32 HxW metres) at a camera-to-world pose.

        ``width``/``height`` rescale the mapper's intrinsics unless ``intrinsics``
        (fx, fy, cx, cy) for that size are given; ``kf_id`` applies that keyframe's learned
        exposure (a * C + b)."""
        W, H = int(width or self.W), int(height or self.H)
        intr = self.intr
        if intrinsics is not None:
            intr = tuple(float(x) for x in intrinsics)
            if len(intr) != 4 or intr[0] <= 0 or intr[1] <= 0:
                raise MapError(f"render intrinsics must be (fx, fy, cx, cy) with positive "
                               f"focal lengths, got {intrinsics}")
        elif (W, H) != (self.W, self.H):
            k = self.K.scaled(W / self.W, H / self.H)
            intr = (k.fx, k.fy, k.cx, k.cy)
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (4, 4):
            raise MapError(f"render pose must be 4x4, got {pose.shape}")
        if len(self.map) == 0:
            return np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.float32)
        return self.exposed(self._raster(pose, intr, W, H), kf_id, intr)

    @torch.no_grad()
    def exposed(self, out, kf_id: Optional[int] = None,
                intr=None) -> Tuple[np.ndarray, np.ndarray]:
        """(rgb uint8, depth float32) of a render ``out`` (its rgb and depth), through keyframe
        ``kf_id``'s exposure when given (intrinsics ``intr``: the mapper's by default)."""
        rgb = out.rgb
        if kf_id is not None and kf_id in self.keyframes:
            rgb = self.expose(rgb, self.keyframes[kf_id], intr)
        rgb = (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        return rgb, out.depth.float().cpu().numpy()

    @torch.no_grad()
    def keyframe_renders(self) -> Dict[int, KeyframeRender]:
        """Every mapped keyframe rendered once at its pose (the mapper's size, no exposure):
        the end of a run's keyframe metrics and mesh share them."""
        if len(self.map) == 0:              # as render(): an empty map renders empty
            z = torch.zeros(self.H, self.W, device=self.device)
            empty = KeyframeRender(torch.zeros(self.H, self.W, 3, device=self.device), z, z)
            return {k: empty for k in sorted(self.keyframes)}
        renders = {}
        for k, kf in sorted(self.keyframes.items()):
            out = self._raster(kf.pose)
            renders[k] = KeyframeRender(out.rgb, out.depth, out.alpha)
        return renders

    @torch.no_grad()
    def coverage(self, pose) -> float:
        """Fraction of the image the map covers at ``pose`` (accumulated opacity > 0.5)."""
        if len(self.map) == 0:
            return 0.0
        return float((self._raster(check_pose(pose)).alpha > 0.5).float().mean())

    def expose(self, rgb: torch.Tensor, kf: MappedKeyframe, intr=None) -> torch.Tensor:
        """Rendered colour through keyframe ``kf``'s exposure and the vignetting (Eq. 11),
        at the mapper's intrinsics unless ``intr`` (fx, fy, cx, cy) are given."""
        return self.camera.expose(rgb, kf, intr or self.intr)

    # ============================================================ keyframes
    @torch.no_grad()
    def decide(self, pose, depth, valid=None) -> KeyframeDecision:
        """Would a keyframe at ``pose`` be mapped? (covisibility / translation rules)."""
        pose = check_pose(pose)
        if self.window.last is None or len(self.map) == 0:
            return KeyframeDecision(True, "first", 0.0, 0.0, 0.0)
        vis = self.visible_uids(pose)
        d = np.asarray(depth, dtype=np.float32)
        ok = np.isfinite(d) & (d > 0)
        if valid is not None:
            ok &= np.asarray(valid, bool)
        if ok.any():
            med = float(np.median(d[ok]))
        else:                                   # no depth: the map's, where it covers
            out = self._raster(pose)
            med = float(out.depth[out.alpha > 0.5].median()) if (out.alpha > 0.5).any() else 0.0
        poses = {k: kf.pose for k, kf in self.keyframes.items()}
        return self.window.decide(vis, pose, med, poses)

    def add_keyframe(self, kf_id: int, image, pose, depth, valid=None,
                     timestamp: Optional[float] = None, force: bool = False,
                     yield_to: Optional[Callable[[], bool]] = None,
                     min_steps: Optional[int] = None) -> dict:
        """Offer a tracker keyframe to the map. Returns statistics of this step.

        image (H,W,3) uint8 RGB; pose 4x4 camera-to-world; depth (H,W) float32 metres (proxy
        depth, 0 = missing); valid (H,W) bool, or float depth-loss weights in [0, 1] (0 = no
        depth), or None. ``force`` maps it regardless of the covisibility rules; ``yield_to``
        (live input) cuts the steps when input waits (not the first keyframe's), after
        ``min_steps`` (default ``mapping.min_iters_per_keyframe``)."""
        t0 = time.perf_counter()
        kf_id = int(kf_id)
        if kf_id in self.keyframes:
            raise MapError(f"keyframe {kf_id} is already mapped; use apply_update to change it")
        pose = check_pose(pose)
        img_t, depth_t, valid_t, weight_t = check_keyframe_inputs(image, depth, valid, self.W,
                                                                   self.H, self.device)
        first = len(self.keyframes) == 0
        if first:
            dec = KeyframeDecision(True, "first", 0.0, 0.0, 0.0)
            vis = self.map.uid[:0]
        elif self.mcfg.seed_uncovered:          # the render's alpha and depth seed below
            with torch.no_grad():
                out = self._raster(pose)
            vis = self.map.uid[out.visible]
        else:
            vis = self.visible_uids(pose)
        if not first:
            med = float(depth_t[valid_t].median()) if bool(valid_t.any()) else 1.0
            dec = self.window.decide(vis, pose, med,
                                     {k: kf.pose for k, kf in self.keyframes.items()})
            if force and not dec.mapped:
                dec = KeyframeDecision(True, "forced", dec.iou, dec.translation, dec.threshold)
        stats = {"kf_id": kf_id, "mapped": dec.mapped, "reason": dec.reason,
                 "iou": round(dec.iou, 4), "translation": round(dec.translation, 4)}
        if not dec.mapped:
            self.last_ms = 1000 * (time.perf_counter() - t0)
            stats.update(self.stats())
            self.history.append(history_entry(stats, timestamp))
            return stats

        kf = MappedKeyframe(kf_id, self.next_index,
                            float(kf_id if timestamp is None else timestamp), pose, img_t,
                            depth_t, valid_t, torch.zeros(2, device=self.device), weight_t)
        self.add_keyframe_record(kf)
        if self.scene_depth <= 0 and bool(valid_t.any()):   # the first keyframe with depth
            self.scene_depth = float(depth_t[valid_t].median())

        # supplementary "Map Initialization": anchor new Gaussians from the proxy depth
        # ("first" settings while the map is still empty, e.g. a first keyframe without depth)
        empty = len(self.map) == 0
        # Gaussians are seeded where the depth has full weight; down-weighted pixels (BA depth
        # in multi-view holes) only supervise (seeding them cost 0.5 dB PSNR on fr2/desk)
        seed = valid_t if weight_t is None else weight_t >= 1
        if self.mcfg.seed_uncovered and not first:      # a loaded map grows where it lacks
            seed = seed & uncovered(out.alpha, out.depth, depth_t, self.mcfg.seed_depth_tol)
        new = init_gaussians(img_t, depth_t, seed, pose, self.intr,
                             self.mcfg.downsample_first if empty else self.mcfg.downsample,
                             self.mcfg.init_opacity, self.gen, self.device,
                             scale=self.mcfg.init_scale)
        n_new = int(new["means"].shape[0])
        self.map.add(new["means"], new["colors"], new["log_scales"], new["quats"],
                     new["opacity_logits"], kf_id=kf_id, created=kf.index, born=self.iteration)
        seen_at = self.seedings            # vis was rendered before these Gaussians existed
        self.seedings += 1
        removed = self.window.add(kf_id, vis, {k: k2.pose for k, k2 in self.keyframes.items()},
                                  at=seen_at)

        b = self.keyframe_budget(empty, kf.timestamp)
        done = optimise(self, b.steps, densify=True, progress=self.progress and b.steps >= 200,
                        budget_s=b.wall_s,
                        min_iters=b.min_steps if min_steps is None else int(min_steps),
                        yield_to=None if empty else yield_to,
                        subsample=self.mcfg.step_subsample,
                        subsample_first=self.mcfg.step_subsample_newest)
        if lattice_steps(self.mcfg):         # lattice views set no visible set
            self.refresh_visibility([kf_id])
        self.last_mapped_ts = kf.timestamp
        # a keyframe mapped without a step (live input waiting) changed no Gaussian but its
        # own: its pruning (which renders every stale window view first) waits for a later
        # keyframe, up to prune_recent_kfs - 1 of them, whose pruning still judges these
        # Gaussians (its candidates are the newest prune_recent_kfs keyframes')
        prune = done > 0 or self.next_index - self.pruned_at >= self.mcfg.prune_recent_kfs
        n_vis_pruned = 0
        if prune and self.strategy.enough_views(self):
            n_vis_pruned = self.strategy.visibility_prune(self)
            self.pruned_at = self.next_index
        self.last_ms = 1000 * (time.perf_counter() - t0)
        stats.update({"steps": done, "steps_skipped": b.steps - done, "new_gaussians": n_new,
                      "left_window": removed, "visibility_pruned": n_vis_pruned,
                      "loss": round(self.last_loss, 5), **self.stats()})
        self.history.append(history_entry(stats, timestamp))
        return stats

    @torch.no_grad()
    def refresh_visibility(self, kf_ids: Sequence[int]) -> None:
        """Render keyframes ``kf_ids`` in full: their visible sets (keyframe selection, window
        membership, visibility pruning) as the map is now."""
        for j in kf_ids:
            self.window.set_visibility(j, self.visible_uids(self.keyframes[j].pose),
                                       self.seedings)

    def keyframe_budget(self, first: bool, timestamp: float) -> Budget:
        """The steps (and, with ``mapping.time_budget``, wall seconds) of one keyframe's
        optimisation (mapping/budget.py): paced by the stream time since the last mapped
        keyframe, so the mapping time follows the input's duration (it drops steps, never
        keyframes)."""
        last = self.last_mapped_ts
        dt = None if first or last is None or not timestamp > last else timestamp - last
        return keyframe_budget(self.mcfg, first, dt)

    def final_refine_budget(self, since_input_s: float = 0.0) -> Budget:
        """The final refinement's steps (and wall cap with ``mapping.time_budget``;
        ``since_input_s``: wall seconds since the input ended)."""
        return final_refine_budget(self.mcfg, len(self.keyframes), since_input_s)

    def add_keyframe_record(self, kf: MappedKeyframe) -> None:
        """Store a mapped keyframe; its exposure joins the camera model's optimiser."""
        self.camera.add_keyframe(kf)
        self.keyframes[kf.kf_id] = kf
        self.next_index = max(self.next_index, kf.index + 1)

    # ================================================== pruning / densification
    def scene_extent(self) -> float:
        """Spatial scale for the 3DGS size thresholds: camera spread, at least the depth."""
        if self.mcfg.scene_extent > 0:
            return float(self.mcfg.scene_extent)
        c = np.stack([kf.pose[:3, 3] for kf in self.keyframes.values()]) if self.keyframes \
            else np.zeros((1, 3))
        radius = 1.1 * float(np.linalg.norm(c - c.mean(0), axis=1).max())
        return max(radius, self.scene_depth, 1e-3)

    # ============================================================ deformation
    def apply_update(self, kf_id: int, pose, depth=None, valid=None) -> int:
        """A keyframe's pose (and proxy depth) changed: deform its Gaussians (Eq. 12), then
        store the new pose/depth. Returns the number of Gaussians moved (0 for a keyframe
        that was never mapped). Without ``depth`` the keyframe's Gaussians move rigidly."""
        return deform_keyframe(self, kf_id, pose, depth, valid)

    def merge_keyframe(self, kf_id: int, into: int) -> Tuple[int, int]:
        """Keyframe ``kf_id`` leaves the map's keyframes, its Gaussians removed where
        ``into`` sees them, else anchored to ``into`` (deformation.merge_keyframe).
        Returns (Gaussians removed, Gaussians re-anchored)."""
        return merge_keyframe(self, kf_id, into)

    def apply_updates(self, kf_ids: Sequence[int], poses, depths=None, valids=None) -> int:
        """Several keyframes of one update event (see :meth:`apply_update`)."""
        total = 0
        for i, k in enumerate(kf_ids):
            total += self.apply_update(k, poses[i], None if depths is None else depths[i],
                                       None if valids is None else valids[i])
        return total

    def background(self, iters: int, yield_to: Optional[Callable[[], bool]] = None) -> int:
        """Live input, while no keyframe waits: ``iters`` more steps of the keyframe
        optimisation (window + random views, densify / prune on schedule), cut by ``yield_to``."""
        done = optimise(self, int(iters), densify=True, yield_to=yield_to,
                        subsample=self.mcfg.step_subsample,
                        subsample_first=self.mcfg.step_subsample_newest) if self.keyframes else 0
        self.background_iters += done
        return done

    # ============================================================== refinement
    def final_refine(self, iters: Optional[int] = None, progress: bool = False,
                     since_input_s: float = 0.0) -> dict:
        """Supplementary "Final Refinement": beta iterations on random single keyframes,
        same loss, no pruning or densification (``since_input_s``: wall seconds since the
        input ended, for ``mapping.final_deadline_s``)."""
        t0 = time.perf_counter()
        budget = 0.0
        if iters is None:
            iters, budget, _ = self.final_refine_budget(since_input_s)
        done = 0
        if self.keyframes:
            done = optimise(self, int(iters), densify=False, single_random=True,
                            progress=progress, budget_s=budget,
                            subsample=self.mcfg.refine_subsample)
        self.refine_info = {"refine_iters": done, "refine_skipped": int(iters) - done,
                            "refine_s": round(time.perf_counter() - t0, 3)}
        return dict(self.refine_info)

    # ================================================================ output
    def stats(self) -> dict:
        return {"gaussians": len(self.map), "keyframes": len(self.keyframes),
                "window": list(self.window.window),
                "map_mb": round(self.map.nbytes() / 2 ** 20, 4),
                "last_ms": round(self.last_ms, 2), "deformations": self.n_deformations,
                "deformed_gaussians": self.n_deformed_gaussians, "iterations": self.iteration,
                "skipped_iterations": self.skipped_iters,
                "background_iterations": self.background_iters,
                "raster_backend": self.raster.name, "raster_backend_reason": self.raster.reason,
                "budget": "time" if self.mcfg.time_budget else "steps",
                "steps_per_keyframe": steps_summary(self.history),
                **{k: v for k, v in self.refine_info.items() if k != "refine_s"},
                "vignette": [round(float(x), 4) for x in self.vignette.detach().cpu()],
                **self.counts}

    def keyframe_trajectory(self) -> Tuple[np.ndarray, np.ndarray]:
        """(timestamps, camera-to-world poses) of the mapped keyframes, by kf id."""
        ks = sorted(self.keyframes)
        if not ks:
            return np.zeros(0), np.zeros((0, 4, 4))
        return (np.array([self.keyframes[k].timestamp for k in ks]),
                np.stack([self.keyframes[k].pose for k in ks]))

    def save_ply(self, path) -> None:
        """Standard 3DGS PLY (binary little-endian) + a kf_id property."""
        g = self.map
        save_gaussians_ply(path, g.means, g.normalized_quats(), g.log_scales,
                           g.opacity_logits, g.colors, g.kf_id)

    @classmethod
    def load_ply(cls, path, cfg: SlamConfig, intrinsics: Intrinsics) -> "Mapper":
        """A mapper holding the Gaussians of a PLY file (no keyframes): render/evaluate it."""
        try:
            d = load_gaussians_ply(path)
        except PlyError as e:
            raise MapError(str(e)) from None
        mp = cls(cfg, intrinsics)
        t = {k: torch.from_numpy(v) for k, v in d.items()}
        mp.map.add(t["means"], t["colors"], t["log_scales"], t["quats"], t["opacity_logits"],
                   kf_id=t["kf_id"], created=0, born=0)
        return mp

