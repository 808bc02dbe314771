"""The Gaussian mapper (§3.2 "Keyframe Selection and Optimization", supplementary Method).

Per tracker keyframe (``Mapper.add_keyframe``):

1. render the map at the keyframe's pose; the keyframe is mapped only if its covisibility
   with the last mapped keyframe is low or the camera moved enough (keyframe_window.py);
2. new Gaussians are anchored from its proxy depth (map_init.py) and it joins the window;
3. ``iters_per_keyframe`` Adam iterations (``iters_first`` for the first keyframe) on the
   Eq. 11 loss summed over the window keyframes (+ a few random older ones);
4. every ``densify_every`` / ``prune_every`` iterations: 3DGS densification and opacity /
   size pruning; when the window is full, visibility pruning of the newest Gaussians.

Pose/depth updates from BA, loop closure or global BA deform the anchored Gaussians
(``apply_update``, deformation.py) before the next mapping step. ``final_refine`` runs the
supplementary's final refinement (random single keyframes, no pruning/densification).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np
import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.mapping.budget import (Budget, final_refine_budget, keyframe_budget,
                                           steps_summary)
from splat_slam_ros.mapping.deformation import deform_gaussians
from splat_slam_ros.mapping.gaussian_map import GaussianMap
from splat_slam_ros.mapping.keyframe_inputs import (MapError, MappedKeyframe,
                                                    check_keyframe_inputs, check_pose)
from splat_slam_ros.geometry import project, quat_to_matrix, se3_inverse, transform_points
from splat_slam_ros.mapping.keyframe_views import history_entry, write_keyframe_views
from splat_slam_ros.mapping.keyframe_window import KeyframeDecision, KeyframeWindow
from splat_slam_ros.mapping.map_init import init_gaussians, uncovered
from splat_slam_ros.mapping.ply_io import PlyError, load_gaussians_ply, save_gaussians_ply
from splat_slam_ros.mapping.rasterizer import rasterize, select_backend
from splat_slam_ros.runtime import resolve_device
from splat_slam_ros.types import Intrinsics


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
        if not 0.0 <= m.ba_depth_weight <= 1.0:
            raise MapError(f"mapping.ba_depth_weight must be in [0, 1], got {m.ba_depth_weight}")
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
        self._exp_opt: Optional[torch.optim.Optimizer] = None
        self.vignette = torch.zeros(2, device=self.device, requires_grad=m.vignetting)  # v1, v2
        self._r2: Dict[tuple, torch.Tensor] = {}        # (H, W, cx, cy) -> r^2 map
        self.gen = torch.Generator().manual_seed(int(m.seed))
        self.rng = np.random.default_rng(int(m.seed))
        self.iteration = 0
        self.settled_uid = 0            # opacity pruning spares uids below (a loaded map's)
        self.n_deformations = 0
        self.n_deformed_gaussians = 0
        self.counts = {"cloned": 0, "split": 0, "pruned_opacity": 0, "pruned_size": 0,
                       "pruned_visibility": 0, "merged_keyframes": 0}
        self._next_index = 0           # MappedKeyframe.index of the next mapped keyframe
        self.last_ms = 0.0
        self.skipped_iters = 0         # steps a wall-clock budget cut (mapping.time_budget)
        self.background_iters = 0      # steps between keyframes (live: mapping.background_steps)
        self.refine_info: Dict[str, float] = {}   # the final refinement's steps (final_refine)
        self._last_mapped_ts: Optional[float] = None
        self.last_loss = float("nan")
        self._scene_depth = 0.0
        self.raster = select_backend(m.raster_backend, self.device, announce=True)  # logs it
        self.progress = False          # tqdm bar for long optimisations (first keyframe)
        self.history: List[dict] = []  # one entry per add_keyframe (the run report's map size)

    # ================================================================ render
    def _viewmat(self, pose_c2w: np.ndarray) -> torch.Tensor:
        T = torch.as_tensor(np.asarray(pose_c2w, dtype=np.float64))
        return se3_inverse(T).to(device=self.device, dtype=torch.float32)

    def _raster(self, pose, intr=None, width=None, height=None, means=None):
        g = self.map
        return rasterize(
            g.means if means is None else means, g.normalized_quats(), g.scales(),
            g.opacities(), g.colors, self._viewmat(pose), intr or self.intr,
            int(width or self.W), int(height or self.H), backend=self.raster.name)

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
        out = self._raster(pose, intr, W, H)
        rgb = out.rgb
        if kf_id is not None and kf_id in self.keyframes:
            rgb = self._expose(rgb, self.keyframes[kf_id], intr)
        rgb = (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        return rgb, out.depth.float().cpu().numpy()

    @torch.no_grad()
    def coverage(self, pose) -> float:
        """Fraction of the image the map covers at ``pose`` (accumulated opacity > 0.5)."""
        if len(self.map) == 0:
            return 0.0
        return float((self._raster(check_pose(pose)).alpha > 0.5).float().mean())

    def _expose(self, rgb: torch.Tensor, kf: MappedKeyframe, intr=None) -> torch.Tensor:
        """The camera's response to rendered colour: a_k V C_k + b_k (Eq. 11's exposure, with
        the learned vignetting V when ``mapping.vignetting``)."""
        if self.mcfg.vignetting:
            rgb = rgb * self._vignetting(rgb.shape[0], rgb.shape[1], intr or self.intr)
        return rgb * kf.exposure[0].exp() + kf.exposure[1]      # a_k C_k + b_k (Eq. 11)

    def _vignetting(self, H: int, W: int, intr) -> torch.Tensor:
        """(H, W, 1) radial falloff 1 + v1 r^2 + v2 r^4, r = distance from the principal
        point / half the image diagonal (the same at any render size)."""
        key = (H, W, *intr[2:])
        r2 = self._r2.get(key)
        if r2 is None:
            ys = torch.arange(H, dtype=torch.float32, device=self.device)[:, None]
            xs = torch.arange(W, dtype=torch.float32, device=self.device)[None, :]
            r2 = ((xs - intr[2]) ** 2 + (ys - intr[3]) ** 2) / (0.25 * (W * W + H * H))
            r2 = self._r2.setdefault(key, r2[..., None])
        v = self.vignette
        return (1.0 + v[0] * r2 + v[1] * r2 * r2).clamp_min(0.1)

    # ============================================================ keyframes
    @torch.no_grad()
    def decide(self, pose, depth, valid=None) -> KeyframeDecision:
        """Would a keyframe at ``pose`` be mapped? (covisibility / translation rules)."""
        pose = check_pose(pose)
        if self.window.last is None or len(self.map) == 0:
            return KeyframeDecision(True, "first", 0.0, 0.0, 0.0)
        out = self._raster(pose)
        vis = self.map.uid[out.visible]
        d = np.asarray(depth, dtype=np.float32)
        ok = np.isfinite(d) & (d > 0)
        if valid is not None:
            ok &= np.asarray(valid, bool)
        med = float(np.median(d[ok])) if ok.any() else float(out.depth[out.alpha > 0.5].median()
                                                            if (out.alpha > 0.5).any() else 0)
        poses = {k: kf.pose for k, kf in self.keyframes.items()}
        return self.window.decide(vis, pose, med, poses)

    def add_keyframe(self, kf_id: int, image, pose, depth, valid=None,
                     timestamp: Optional[float] = None, force: bool = False,
                     yield_to: Optional[Callable[[], bool]] = None) -> dict:
        """Offer a tracker keyframe to the map. Returns statistics of this step.

        image (H,W,3) uint8 RGB; pose 4x4 camera-to-world; depth (H,W) float32 metres (proxy
        depth, 0 = missing); valid (H,W) bool, or float depth-loss weights in [0, 1] (0 = no
        depth), or None. ``force`` maps it regardless of the covisibility rules; ``yield_to``
        (live input) cuts the steps when input waits (not the first keyframe's)."""
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
        else:
            with torch.no_grad():
                out = self._raster(pose)
            vis = self.map.uid[out.visible]
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

        kf = MappedKeyframe(kf_id, self._next_index,
                            float(kf_id if timestamp is None else timestamp), pose, img_t,
                            depth_t, valid_t, torch.zeros(2, device=self.device), weight_t)
        self._add_keyframe_record(kf)
        if self._scene_depth <= 0 and bool(valid_t.any()):   # the first keyframe with depth
            self._scene_depth = float(depth_t[valid_t].median())

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
                             self.mcfg.init_opacity, self.gen, self.device)
        n_new = int(new["means"].shape[0])
        self.map.add(new["means"], new["colors"], new["log_scales"], new["quats"],
                     new["opacity_logits"], kf_id=kf_id, created=kf.index, born=self.iteration)
        removed = self.window.add(kf_id, vis, {k: k2.pose for k, k2 in self.keyframes.items()})

        b = self.keyframe_budget(empty, kf.timestamp)
        done = self._optimize(b.steps, densify=True, progress=self.progress and b.steps >= 200,
                              budget_s=b.wall_s, min_iters=b.min_steps,
                              yield_to=None if empty else yield_to)
        self._last_mapped_ts = kf.timestamp
        n_vis_pruned = self._visibility_prune() if self._enough_views() else 0
        self.last_ms = 1000 * (time.perf_counter() - t0)
        stats.update({"steps": done, "steps_skipped": b.steps - done, "new_gaussians": n_new,
                      "left_window": removed, "visibility_pruned": n_vis_pruned,
                      "loss": round(self.last_loss, 5), **self.stats()})
        self.history.append(history_entry(stats, timestamp))
        return stats

    def keyframe_budget(self, first: bool, timestamp: float) -> Budget:
        """The steps (and, with ``mapping.time_budget``, wall seconds) of one keyframe's
        optimisation (mapping/budget.py): paced by the stream time since the last mapped
        keyframe, so the mapping time follows the input's duration (it drops steps, never
        keyframes)."""
        last = self._last_mapped_ts
        dt = None if first or last is None or not timestamp > last else timestamp - last
        return keyframe_budget(self.mcfg, first, dt)

    def final_refine_budget(self) -> Budget:
        """The final refinement's steps (and wall cap with ``mapping.time_budget``)."""
        return final_refine_budget(self.mcfg, len(self.keyframes))

    def _add_keyframe_record(self, kf: MappedKeyframe) -> None:
        """Store a mapped keyframe; its exposure (Eq. 11 affine a, b) joins the exposure
        optimiser except for the first keyframe, which fixes the gauge (a = 1, b = 0)."""
        if kf.index > 0:
            kf.exposure.requires_grad_(True)
            grp = {"params": [kf.exposure], "lr": self.mcfg.lr_exposure}
            if self._exp_opt is None:                 # the vignetting needs two views too
                vig = [{"params": [self.vignette], "lr": self.mcfg.lr_vignetting}] \
                    if self.mcfg.vignetting else []
                self._exp_opt = torch.optim.Adam([grp] + vig, lr=self.mcfg.lr_exposure)
            else:
                self._exp_opt.add_param_group(grp)
        self.keyframes[kf.kf_id] = kf
        self._next_index = max(self._next_index, kf.index + 1)

    # =========================================================== optimisation
    def _pick_views(self, single_random: bool) -> List[int]:
        ids = list(self.keyframes)
        if single_random:
            return [ids[int(self.rng.integers(len(ids)))]]
        win = list(self.window.window)
        k = self.mcfg.window_views_per_iter
        if 0 < k < len(win):           # newest always, the rest sampled
            rest = list(self.rng.choice(win[1:], size=k - 1, replace=False)) if k > 1 else []
            win = [win[0]] + [int(x) for x in rest]
        others = [i for i in ids if i not in self.window.window]
        r = min(self.mcfg.random_views_per_iter, len(others))
        if r > 0:
            win += [int(x) for x in self.rng.choice(others, size=r, replace=False)]
        return win

    def _view_loss(self, kf: MappedKeyframe, out) -> torch.Tensor:
        """Eq. 11 data terms per keyframe: lambda/N |aC+b - C_gt|_1 + (1-lambda)/N |D^r - D|_1."""
        lam = self.mcfg.rgb_weight
        gt = kf.image.to(torch.float32) / 255.0
        l_rgb = (self._expose(out.rgb, kf) - gt).abs().mean()
        n_pix = kf.depth.numel()
        w = kf.valid if kf.weight is None else kf.weight
        l_depth = ((out.depth - kf.depth).abs() * w).sum() / n_pix
        return lam * l_rgb + (1 - lam) * l_depth

    def _isotropy(self) -> torch.Tensor:
        """Eq. 11 regulariser: 1/|G| sum_i |s_i - mean(s_i)|_1 (scales, not log-scales)."""
        s = self.map.scales()
        return (s - s.mean(1, keepdim=True)).abs().sum(1).mean()

    def _optimize(self, iters: int, densify: bool = True, single_random: bool = False,
                  progress: bool = False, budget_s: float = 0.0, min_iters: int = 0,
                  yield_to: Optional[Callable[[], bool]] = None) -> int:
        """Up to ``iters`` Adam steps (returns the number run); after ``min_iters`` they stop
        before one would end past ``budget_s`` (> 0) and, live, once ``yield_to()`` is true."""
        if iters <= 0 or len(self.map) == 0:
            return 0
        m = self.mcfg
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=iters, desc="refine" if single_random else "optimise", unit="it",
                       dynamic_ncols=True, leave=False)
        t0 = time.perf_counter()
        done = 0
        for done in range(iters + 1):
            spent = time.perf_counter() - t0
            if done == iters or (budget_s > 0 and done >= max(min_iters, 1)
                                 and spent * (done + 1) / done > budget_s):
                break
            if yield_to is not None and m.time_budget and done >= min_iters and yield_to():
                break
            views = self._pick_views(single_random)
            self.map.zero_grad()
            if self._exp_opt is not None:
                self._exp_opt.zero_grad(set_to_none=True)
            loss = 0.0
            tracked = []
            for kid in views:
                kf = self.keyframes[kid]
                mv = None
                if densify:            # per-view copy of the means: its grad is this view's
                    mv = self.map.means * 1.0
                    mv.retain_grad()
                out = self._raster(kf.pose, means=mv)
                m2 = out.means2d if densify else None
                if m2 is not None and m2.requires_grad:
                    m2.retain_grad()
                loss = loss + self._view_loss(kf, out)
                tracked.append((kf, mv, m2, out.radii, out.visible))
            loss = loss + m.isotropy_weight * self._isotropy()
            loss.backward()
            self.last_loss = float(loss.detach())
            with torch.no_grad():
                for kf, mv, m2, radii, visible in tracked:
                    if kf.kf_id in self.window.window:
                        self.window.set_visibility(kf.kf_id, self.map.uid[visible])
                    if m2 is not None and m2.grad is not None:
                        self._accumulate_densify_stats(kf, radii, grad2d=m2.grad)
                    elif mv is not None and mv.grad is not None:
                        self._accumulate_densify_stats(kf, radii, grad3d=mv.grad)
            self.map.step()
            if self._exp_opt is not None:
                self._exp_opt.step()
            self.iteration += 1
            if densify:
                changed = False
                if m.densify_every > 0 and self.iteration % m.densify_every == 0:
                    self._densify()
                    changed = True
                if m.prune_every > 0 and self.iteration % m.prune_every == 0:
                    self._prune()
                    changed = True
                if changed:
                    self.map.reset_densify_stats()
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{self.last_loss:.4f}")
        if bar is not None:
            bar.close()
        self.skipped_iters += iters - done
        return done

    # ================================================== pruning / densification
    def scene_extent(self) -> float:
        """Spatial scale for the 3DGS size thresholds: camera spread, at least the depth."""
        if self.mcfg.scene_extent > 0:
            return float(self.mcfg.scene_extent)
        c = np.stack([kf.pose[:3, 3] for kf in self.keyframes.values()]) if self.keyframes \
            else np.zeros((1, 3))
        radius = 1.1 * float(np.linalg.norm(c - c.mean(0), axis=1).max())
        return max(radius, self._scene_depth, 1e-3)

    @torch.no_grad()
    def _accumulate_densify_stats(self, kf: MappedKeyframe, radii: torch.Tensor,
                                  grad2d: Optional[torch.Tensor] = None,
                                  grad3d: Optional[torch.Tensor] = None) -> None:
        """3DGS view-space positional gradient of one view, in NDC units (pixel x W/2).

        From the projected centres' gradient when the rasterizer exposes it; otherwise from
        the 3D mean gradient: a pixel shift (du, dv) of the centre is the camera-frame move
        (du z / fx, dv z / fy, 0), so dL/du = (z / fx) (R_cw dL/dmu)_x."""
        if grad2d is not None:
            gu, gv = grad2d[:, 0], grad2d[:, 1]
        else:
            V = self._viewmat(kf.pose)
            R, t = V[:3, :3], V[:3, 3]
            z = (self.map.means.detach() @ R.T + t)[:, 2].clamp_min(1e-6)
            g = grad3d @ R.T
            gu = g[:, 0] * z / self.intr[0]
            gv = g[:, 1] * z / self.intr[1]
        gu = gu * 0.5 * self.W
        gv = gv * 0.5 * self.H
        seen = radii > 0
        self.map.grad_accum += torch.where(seen, torch.sqrt(gu * gu + gv * gv),
                                           torch.zeros_like(gu))
        self.map.grad_count += seen.to(self.map.grad_count.dtype)
        self.map.max_radii = torch.maximum(self.map.max_radii, radii.to(self.map.max_radii.dtype))

    @torch.no_grad()
    def _densify(self) -> Tuple[int, int]:
        """3DGS: clone small / split large Gaussians whose mean view-space gradient is high."""
        g = self.map
        n = len(g)
        if n == 0:
            return 0, 0
        grad = g.grad_accum / g.grad_count.clamp_min(1)
        sel = (grad >= self.mcfg.densify_grad_thresh) & (g.grad_count > 0)
        scales = g.scales()
        smax = scales.max(1).values
        limit = self.mcfg.percent_dense * self.scene_extent()
        if self.mcfg.densify_max_per_view > 0:
            sel = self._within_view_budget(sel, grad)
        clone = (sel & (smax <= limit)).nonzero()[:, 0]
        split = (sel & (smax > limit)).nonzero()[:, 0]
        t = g.tensors()
        if len(clone):
            g.add(t["means"][clone], t["colors"][clone], t["log_scales"][clone],
                  t["quats"][clone], t["opacity_logits"][clone], kf_id=t["kf_id"][clone],
                  created=t["created"][clone], born=self.iteration)
        if len(split):
            k = 2
            idx = split.repeat(k)
            s = scales[idx]
            offs = torch.randn(s.shape, generator=self.gen).to(s) * s
            R = quat_to_matrix(t["quats"][idx])
            means = t["means"][idx] + (R @ offs[..., None])[..., 0]
            g.add(means, t["colors"][idx], (s / (0.8 * k)).log(), t["quats"][idx],
                  t["opacity_logits"][idx], kf_id=t["kf_id"][idx], created=t["created"][idx],
                  born=self.iteration)
            rm = torch.zeros(len(g), dtype=torch.bool, device=g.device)
            rm[split] = True
            g.remove(rm)
        self.counts["cloned"] += len(clone)
        self.counts["split"] += len(split)
        return len(clone), len(split)

    def _within_view_budget(self, sel: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
        """``sel`` limited, per anchor keyframe, to the highest-gradient Gaussians that keep
        its count within ``densify_max_per_view`` x the Gaussians a keyframe anchors when
        mapped (a clone or a split adds one)."""
        g, m = self.map, self.mcfg
        out = torch.zeros_like(sel)
        for k in torch.unique(g.kf_id[sel]).tolist():
            kf = self.keyframes.get(int(k))
            ds = m.downsample_first if kf is not None and kf.index == 0 else m.downsample
            room = int(m.densify_max_per_view * self.H * self.W / max(ds, 1)) - \
                int((g.kf_id == k).sum())
            if room <= 0:
                continue
            idx = (sel & (g.kf_id == k)).nonzero()[:, 0]
            out[idx[torch.argsort(grad[idx], descending=True)[:room]]] = True
        return out

    @torch.no_grad()
    def _prune(self) -> int:
        """Remove low-opacity (old enough, not a loaded map's: ``settled_uid``) and oversized
        Gaussians (supplementary)."""
        g, m = self.map, self.mcfg
        if len(g) == 0:
            return 0
        low = (g.opacities() < m.prune_opacity) & ((self.iteration - g.born) >= m.prune_min_age) \
            & (g.uid >= self.settled_uid)
        big = torch.zeros_like(low)
        if m.prune_max_screen_px > 0:
            big |= g.max_radii > m.prune_max_screen_px
        if m.prune_max_scale_frac > 0:
            big |= g.scales().max(1).values > m.prune_max_scale_frac * self.scene_extent()
        rm = low | big
        if bool(rm.all()):
            return 0                   # never wipe the map
        self.counts["pruned_opacity"] += int(low.sum())
        self.counts["pruned_size"] += int((big & ~low).sum())
        return g.remove(rm)

    def _enough_views(self) -> bool:
        """Visibility pruning needs enough views to judge (MonoGS: a full window). In a
        revisited room merged keyframes keep the window from ever filling: there it also
        runs once the window holds every mapped keyframe, more than prune_covis_min of them."""
        w = self.window
        return w.full or (self.counts["merged_keyframes"] > 0 and
                          len(w) == len(self.keyframes) > self.mcfg.prune_covis_min)

    @torch.no_grad()
    def _visibility_prune(self) -> int:
        """New Gaussians (last ``prune_recent_kfs`` keyframes) seen by fewer than
        ``prune_covis_min`` other window keyframes are removed (only when the window is full)."""
        m = self.mcfg
        g = self.map
        if m.prune_covis_min <= 0 or len(g) == 0:
            return 0
        cand = g.created >= self._next_index - m.prune_recent_kfs
        count = torch.zeros(len(g), dtype=torch.long, device=g.device)
        for j in self.window.window:
            vis = self.window.visibility.get(j)
            if vis is None or vis.numel() == 0:
                continue
            count += (torch.isin(g.uid, vis) & (g.kf_id != j)).long()
        n = g.remove(cand & (count < m.prune_covis_min))
        self.counts["pruned_visibility"] += n
        return n

    # ============================================================ deformation
    @torch.no_grad()
    def apply_update(self, kf_id: int, pose, depth=None, valid=None) -> int:
        """A keyframe's pose (and proxy depth) changed: deform its Gaussians (Eq. 12), then
        store the new pose/depth. Returns the number of Gaussians moved (0 for a keyframe
        that was never mapped). Without ``depth`` the keyframe's Gaussians move rigidly."""
        kf = self.keyframes.get(int(kf_id))
        if kf is None:
            return 0
        pose = check_pose(pose)
        new_depth = new_valid = new_weight = None
        if depth is not None:
            _, new_depth, new_valid, new_weight = check_keyframe_inputs(
                np.zeros((self.H, self.W, 3), np.uint8), depth, valid, self.W, self.H, self.device)
        sel = (self.map.kf_id == kf.kf_id).nonzero()[:, 0]
        if len(sel):
            g = self.map
            d = deform_gaussians(g.means[sel], g.quats[sel], g.log_scales[sel], kf.pose, pose,
                                 self.intr, kf.depth if new_depth is not None else None,
                                 new_depth, kf.valid, new_valid)
            g.set_rows(sel, means=d.means, quats=d.quats, log_scales=d.log_scales)
        kf.pose = pose
        if new_depth is not None:
            kf.depth, kf.valid, kf.weight = new_depth, new_valid, new_weight
        self.n_deformations += 1
        self.n_deformed_gaussians += int(len(sel))
        return int(len(sel))

    @torch.no_grad()
    def merge_keyframe(self, kf_id: int, into: int) -> Tuple[int, int]:
        """A mapped keyframe whose view an older one (``into``) already has leaves the map's
        keyframes (a bounded map in a revisited room), as if it had been recognised as a
        revisit when it arrived: its Gaussians inside the older keyframe's view duplicate
        that view's and are removed; the rest (what only it saw) are anchored to ``into``
        and follow its deformations (Eq. 12). Its view leaves the window and the optimiser.
        Returns (Gaussians removed, Gaussians re-anchored). The first keyframe (exposure
        gauge) stays."""
        kf_id, into = int(kf_id), int(into)
        kf, keep = self.keyframes.get(kf_id), self.keyframes.get(into)
        if kf is None or keep is None or kf_id == into:
            raise MapError(f"cannot merge keyframe {kf_id} into {into}: both must be mapped")
        if kf.index == 0:
            raise MapError(f"keyframe {kf_id} fixes the exposure gauge and cannot be merged")
        own = self.map.kf_id == kf_id
        seen = own & self._in_view(self.map.means, keep.pose)
        self.map.kf_id[own & ~seen] = into
        n_moved = int((own & ~seen).sum())
        n_removed = self.map.remove(seen)
        # densification statistics gathered while its view sat at a wrong (uncorrected) pose
        # say nothing about missing detail: reset for what that view covers
        stale = self._in_view(self.map.means, kf.pose)
        self.map.grad_accum[stale] = 0
        self.map.grad_count[stale] = 0
        if self._exp_opt is not None:           # its exposure leaves the optimiser
            self._exp_opt.param_groups = [g for g in self._exp_opt.param_groups
                                          if g["params"][0] is not kf.exposure]
            self._exp_opt.state.pop(kf.exposure, None)
        self.window.drop(kf_id, into)
        del self.keyframes[kf_id]
        self.counts["merged_keyframes"] += 1
        return n_removed, n_moved

    def _in_view(self, means: torch.Tensor, pose) -> torch.Tensor:
        """Which points project inside the image of a camera at ``pose`` (in front of it)."""
        X = transform_points(self._viewmat(pose), means)
        uv = project(X, torch.tensor(self.intr, dtype=X.dtype, device=X.device))
        return (X[:, 2] > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < self.W) & (uv[:, 1] >= 0) & \
            (uv[:, 1] < self.H)

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
        done = self._optimize(int(iters), densify=True, yield_to=yield_to) if self.keyframes else 0
        self.background_iters += done
        return done

    # ============================================================== refinement
    def final_refine(self, iters: Optional[int] = None, progress: bool = False) -> dict:
        """Supplementary "Final Refinement": beta iterations on random single keyframes,
        same loss, no pruning or densification."""
        t0 = time.perf_counter()
        budget = 0.0
        if iters is None:
            iters, budget, _ = self.final_refine_budget()
        done = 0
        if self.keyframes:
            done = self._optimize(int(iters), densify=False, single_random=True,
                                  progress=progress, budget_s=budget)
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

    # ================================================================ state
    def state_dict(self) -> Tuple[Dict[str, np.ndarray], Dict]:
        """(arrays, JSON metadata) that :meth:`load_state_dict` turns back into an equal map:
        Gaussians with kf_id/created/born/uid, mapped keyframes with pose and exposure, the
        window and its visibility sets, counters. Adam moments are not kept (they restart at
        zero, as for new Gaussians). Keyframe images and depths are not included: the caller
        stores them per keyframe, so a snapshot costs O(map), not O(keyframes x image)."""
        g = self.map
        arrays = {k: v.detach().cpu().numpy() for k, v in g.tensors().items()}
        ids = sorted(self.keyframes)
        kfs = [self.keyframes[k] for k in ids]
        arrays["kf_ids"] = np.array(ids, np.int64)
        arrays["kf_index"] = np.array([k.index for k in kfs], np.int64)
        arrays["kf_timestamp"] = np.array([k.timestamp for k in kfs], np.float64)
        arrays["kf_pose"] = np.stack([k.pose for k in kfs]) if kfs else np.zeros((0, 4, 4))
        arrays["kf_exposure"] = (np.stack([k.exposure.detach().cpu().numpy() for k in kfs])
                                 if kfs else np.zeros((0, 2), np.float32))
        win = self.window
        vis = {str(k): v.detach().cpu().numpy().tolist() for k, v in win.visibility.items()}
        meta = {"window": list(win.window), "last": win.last, "visibility": vis,
                "next_uid": g.next_uid, "settled_uid": int(self.settled_uid),
                "iteration": int(self.iteration), "n_deformations": int(self.n_deformations),
                "n_deformed_gaussians": int(self.n_deformed_gaussians),
                "scene_depth": float(self._scene_depth), "next_index": int(self._next_index),
                "counts": dict(self.counts),
                "vignette": [float(x) for x in self.vignette.detach().cpu()]}
        return arrays, meta

    def load_state_dict(self, arrays: Dict[str, np.ndarray], meta: Dict, image_of,
                        depth_of) -> None:
        """Restore :meth:`state_dict` output into this (fresh) mapper. ``image_of(kf_id)``
        returns the keyframe's H x W x 3 uint8 image, ``depth_of(kf_id)`` a dict with the
        proxy ``depth`` (float32), its validity mask bit-packed along rows (``valid``,
        ``np.packbits(mask, axis=-1)``), the image ``width`` and, when the keyframe's depth
        loss is weighted, its ``weight`` (float16)."""
        if self.keyframes or len(self.map):
            raise MapError("load_state_dict needs a fresh mapper (no keyframes, no Gaussians)")
        dev = self.device
        self.map.load_tensors({k: torch.from_numpy(np.asarray(arrays[k])) for k in
                               ("means", "colors", "log_scales", "quats", "opacity_logits",
                                "kf_id", "created", "born", "uid")},
                              meta.get("next_uid"))
        for i, k in enumerate(np.asarray(arrays["kf_ids"]).tolist()):
            img = np.ascontiguousarray(np.asarray(image_of(int(k)), np.uint8))
            d = depth_of(int(k))
            W = int(d["width"])
            valid = np.unpackbits(np.asarray(d["valid"]), axis=-1)[..., :W].astype(bool)
            weight = d.get("weight")
            self._add_keyframe_record(MappedKeyframe(
                int(k), int(arrays["kf_index"][i]), float(arrays["kf_timestamp"][i]),
                np.asarray(arrays["kf_pose"][i], np.float64), torch.from_numpy(img).to(dev),
                torch.from_numpy(np.asarray(d["depth"], np.float32)).to(dev),
                torch.from_numpy(valid.copy()).to(dev),
                torch.from_numpy(np.asarray(arrays["kf_exposure"][i], np.float32)).to(dev),
                None if weight is None else torch.from_numpy(np.asarray(weight, np.float32)).to(dev)))
        win = self.window
        win.window = [int(x) for x in meta.get("window", [])]
        win.last = meta.get("last")
        win.visibility = {int(k): torch.tensor(v, dtype=torch.long, device=dev)
                          for k, v in (meta.get("visibility") or {}).items()}
        self.iteration, self.settled_uid = (int(meta.get(k, 0)) for k in ("iteration",
                                                                           "settled_uid"))
        self.n_deformations = int(meta.get("n_deformations", 0))
        self.n_deformed_gaussians = int(meta.get("n_deformed_gaussians", 0))
        self._scene_depth = float(meta.get("scene_depth", 0.0))
        self._next_index = max(self._next_index, int(meta.get("next_index", 0)))
        self.counts.update({k: int(v) for k, v in (meta.get("counts") or {}).items()})
        with torch.no_grad():
            self.vignette.copy_(torch.tensor(meta.get("vignette", [0.0, 0.0])))

    def save_renders(self, folder, depth_scale: float = 1000.0) -> int:
        """Write ``kf_<id>.png`` (rendered colour with the keyframe's exposure) and
        ``kf_<id>_depth.png`` (16-bit, ``depth_scale`` units per metre) per keyframe."""
        import cv2
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        for k, kf in sorted(self.keyframes.items()):
            rgb, depth = self.render(kf.pose, kf_id=k)
            cv2.imwrite(str(folder / f"kf_{k:05d}.png"), rgb[..., ::-1])
            d = np.clip(depth * depth_scale, 0, 65535).astype(np.uint16)
            cv2.imwrite(str(folder / f"kf_{k:05d}_depth.png"), d)
        write_keyframe_views(self, folder, depth_scale=depth_scale)   # for the run report
        return len(self.keyframes)

    # ============================================================ evaluation
    def evaluate(self, frames: Optional[Iterable] = None, gt_depth=None,
                 poses: Optional[Sequence[np.ndarray]] = None, render_dir=None,
                 lpips_model=None, lpips_weights=None) -> dict:
        """Rendering metrics (PSNR, SSIM, LPIPS with a backbone file, depth L1 in cm).

        ``frames=None``: the mapped keyframes, each with its learned exposure (as the
        reference evaluates); ``gt_depth`` then maps kf_id -> sensor depth (H,W metres).
        Otherwise ``frames`` are :class:`~splat_slam_ros.types.Frame` objects rendered at
        ``poses`` (default: their ``gt_pose``) against ``frame.image`` / ``frame.gt_depth``.
        Also reports the Gaussian count and map size (MB)."""
        from splat_slam_ros import evaluation as ev
        views = []
        if frames is None:
            for k, kf in sorted(self.keyframes.items()):
                gd = None
                if gt_depth is not None:
                    gd = gt_depth.get(k) if isinstance(gt_depth, dict) else gt_depth[kf.index]
                views.append((f"kf_{k:05d}", kf.pose, kf.image.cpu().numpy(), gd, k))
        else:
            for i, fr in enumerate(frames):
                pose = poses[i] if poses is not None else fr.gt_pose
                if pose is None:
                    raise MapError(f"frame {fr.index} has no pose to render from")
                views.append((f"frame_{fr.index:05d}", pose, np.asarray(fr.image),
                              fr.gt_depth, None))
        per_view = []
        for name, pose, ref, gd, kid in views:
            H, W = ref.shape[:2]
            rgb, depth = self.render(pose, W, H, kf_id=kid)
            m = {"psnr": ev.psnr(rgb, ref), "ssim": ev.ssim(rgb, ref)}
            if lpips_model is not None:
                m["lpips"] = ev.lpips(rgb, ref, lpips_model, lpips_weights)
            if gd is not None:
                m["depth_l1_cm"] = ev.depth_l1_cm(depth, gd)
            per_view.append(m)
            if render_dir is not None:
                import cv2
                Path(render_dir).mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(Path(render_dir) / f"{name}.png"), rgb[..., ::-1])
        out = ev.summarize(per_view) if per_view else {}
        out.update({"views": len(per_view), "gaussians": len(self.map),
                    "map_mb": round(self.map.nbytes() / 2 ** 20, 4)})
        return out

    def evaluate_keyframes(self, render_dir=None, gt_depth=None) -> dict:
        """Keyframe metrics (what the pipeline reports), renders written to ``render_dir``."""
        out = self.evaluate(None, gt_depth=gt_depth, render_dir=render_dir)
        if render_dir is not None:                     # per-keyframe views for the report
            write_keyframe_views(self, render_dir, gt_depth)
        return out
