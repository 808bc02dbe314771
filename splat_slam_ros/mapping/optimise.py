"""Rendering the Gaussian map and the mapping optimisation (§3.2, Eq. 11).

Functional pieces: :func:`viewmat` / :func:`render_map` (rasterise the map at a
camera-to-world pose; :func:`visible_in_map`: only its visible set), :func:`view_loss` and
:func:`isotropy` (the Eq. 11 terms;
:func:`fused_view_loss`: ``view_loss`` in C++, what the CPU backend's steps use),
:func:`pick_views` (the window keyframes of one step, plus random older ones) and
:func:`optimise`: Adam steps on the Eq. 11 loss summed over the window keyframes, each step
followed by the densify / prune schedule of the mapper's :class:`DensifyStrategy`.
A step may render each view on a random pixel lattice (:func:`lattice`, ``subsample`` > 1):
1/n^2 of the pixels, point-sampled, so the loss is the full-resolution one in expectation.
"""
from __future__ import annotations

import time
from typing import Callable, Dict, List, Optional

import numpy as np
import torch

from splat_slam_ros.geometry import se3_inverse
from splat_slam_ros.mapping.keyframe_inputs import MappedKeyframe, lattice_view
from splat_slam_ros.mapping.rasterizer import rasterize, visible_gaussians
from splat_slam_ros.mapping.rasterizer.kernel import ViewLossCpp
from splat_slam_ros.mapping.rasterizer.projection import LOW_PASS


def viewmat(pose_c2w: np.ndarray, device) -> torch.Tensor:
    """World-to-camera 4x4 (float32 on ``device``) of a camera-to-world pose."""
    T = torch.as_tensor(np.asarray(pose_c2w, dtype=np.float64))
    return se3_inverse(T).to(device=device, dtype=torch.float32)


def activated(g):
    """(quaternions, scales, opacities) of the map ``g``: computed once per step, shared by
    its views (their gradients meet there, not in one copy per view). The quaternions are
    the stored ones: every projection normalises them (its gradient is the normalisation's)."""
    return g.params["quats"], g.scales(), g.opacities()


def render_map(g, pose, intr, width: int, height: int, backend: str, device, attrs=None,
               low_pass: float = LOW_PASS):
    """Rasterise the Gaussian map ``g`` at a camera-to-world pose (``attrs``: :func:`activated`
    of ``g``, computed here when not given; ``low_pass``: the rasterizer's screen-space
    filter)."""
    quats, scales, opacities = activated(g) if attrs is None else attrs
    return rasterize(g.means, quats, scales, opacities, g.colors, viewmat(pose, device), intr,
                     int(width), int(height), backend=backend, low_pass=low_pass)


def visible_in_map(g, pose, intr, width: int, height: int, backend: str, device) -> torch.Tensor:
    """(N,) bool: the Gaussians of ``g`` that :func:`render_map` at ``pose`` would flag
    visible (composited while T >= 0.5), without rendering the image."""
    quats, scales, opacities = activated(g)
    return visible_gaussians(g.means, quats, scales, opacities, viewmat(pose, device), intr,
                             int(width), int(height), backend=backend)


def view_loss(kf: MappedKeyframe, out, expose: Callable, lam: float) -> torch.Tensor:
    """Eq. 11 data terms per keyframe: lambda/N |aC+b - C_gt|_1 + (1-lambda)/N |D^r - D|_1."""
    gt = kf.image.to(torch.float32) / 255.0
    l_rgb = (expose(out.rgb, kf) - gt).abs().mean()
    n_pix = kf.depth.numel()
    w = kf.valid if kf.weight is None else kf.weight
    l_depth = ((out.depth - kf.depth).abs() * w).sum() / n_pix
    return lam * l_rgb + (1 - lam) * l_depth


def fused_view_loss(kf: MappedKeyframe, out, camera, intr, lam: float) -> torch.Tensor:
    """:func:`view_loss` through the camera model ``camera`` (intrinsics ``intr``) in one C++
    pass each way (``kernel.ViewLossCpp``; CPU float32 renders): the same value and
    gradients, without a dozen image-sized temporaries per view."""
    h, w = out.depth.shape
    r2 = camera.r2(h, w, intr) if camera.mcfg.vignetting else None
    weight = kf.valid if kf.weight is None else kf.weight
    return ViewLossCpp.apply(out.rgb, out.depth, kf.exposure, camera.vignette, kf.image,
                             kf.depth, weight, r2, lam)


def isotropy(s: torch.Tensor) -> torch.Tensor:
    """Eq. 11 regulariser: 1/|G| sum_i |s_i - mean(s_i)|_1 of the scales ``s`` (N, 3; not
    log-scales)."""
    return (s - s.mean(1, keepdim=True)).abs().sum(1).mean()


def pick_views(keyframes: Dict[int, MappedKeyframe], window: List[int], rng, mcfg,
               single_random: bool) -> List[int]:
    """The keyframes of one step: one random keyframe (``single_random``), else the window
    (newest always, ``window_views_per_iter`` of it) + ``random_views_per_iter`` older ones."""
    ids = list(keyframes)
    if single_random:
        return [ids[int(rng.integers(len(ids)))]]
    win = list(window)
    k = mcfg.window_views_per_iter
    if 0 < k < len(win):           # newest always, the rest sampled
        rest = list(rng.choice(win[1:], size=k - 1, replace=False)) if k > 1 else []
        win = [win[0]] + [int(x) for x in rest]
    others = [i for i in ids if i not in window]
    r = min(mcfg.random_views_per_iter, len(others))
    if r > 0:
        win += [int(x) for x in rng.choice(others, size=r, replace=False)]
    return win


def lattice(intr, W: int, H: int, n: int, dx: int, dy: int):
    """Intrinsics and size of the render whose pixel (i, j) is pixel (n i + dx, n j + dy) of
    a W x H view with intrinsics ``intr`` (pixel centres at integer coordinates)."""
    fx, fy, cx, cy = intr
    return (fx / n, fy / n, (cx - dx) / n, (cy - dy) / n), (W - dx + n - 1) // n, \
        (H - dy + n - 1) // n


def lattice_steps(mcfg) -> bool:
    """Whether keyframe steps render some views on a lattice (``mapping.step_subsample`` /
    ``step_subsample_newest``): those set no visible sets, full renders must."""
    return mcfg.step_subsample > 1 or mcfg.step_subsample_newest > 1


def _step(mp, views: List[int], densify: bool, subsample: int = 1,
          subsample_first: int = 0) -> None:
    """One Adam step of the map and the camera model on the Eq. 11 loss of ``views``, each
    rendered at full resolution or (``subsample`` n > 1) on a random 1/n pixel lattice; the
    first view (a keyframe step's newest keyframe) with ``subsample_first`` when > 0."""
    m = mp.mcfg
    mp.map.zero_grad()
    mp.camera.zero_grad()
    loss = 0.0
    tracked = []
    attrs = activated(mp.map)
    fused = mp.raster.name == "cpp"           # CPU float32 renders: the C++ loss
    for vi, kid in enumerate(views):
        kf = mp.keyframes[kid]
        n = subsample_first if vi == 0 and subsample_first > 0 else subsample
        intr = mp.intr
        if n > 1:
            dx, dy = (int(x) for x in mp.rng.integers(n, size=2))
            intr, w, h = lattice(mp.intr, mp.W, mp.H, n, dx, dy)
            # the full image's screen-space filter: LOW_PASS full pixels^2
            out = mp._raster(kf.pose, intr, w, h, attrs=attrs, low_pass=LOW_PASS / n ** 2)
            target = lattice_view(kf, n, dx, dy)
        else:
            out = mp._raster(kf.pose, attrs=attrs)
            target = kf
        if fused:
            loss = loss + fused_view_loss(target, out, mp.camera, intr, m.rgb_weight)
        else:
            loss = loss + view_loss(target, out, lambda rgb, k, _i=intr: mp.expose(rgb, k, _i),
                                    m.rgb_weight)
        m2 = out.means2d if densify else None     # its grad: the densification statistic
        if m2 is not None:
            m2.retain_grad()
        tracked.append((kf, m2, out.radii, out.visible, n))
    loss = loss + m.isotropy_weight * isotropy(attrs[1])
    loss.backward()
    mp.last_loss = float(loss.detach())
    with torch.no_grad():
        for kf, m2, radii, visible, n in tracked:
            if n == 1 and kf.kf_id in mp.window.window:   # a lattice misses some
                mp.window.set_visibility(kf.kf_id, mp.map.uid[visible], mp.seedings)
            if m2 is not None and m2.grad is not None:   # lattice pixels are n full ones
                mp.strategy.accumulate(mp, radii * n, m2.grad / n)
    mp.map.step()
    mp.camera.step()
    mp.iteration += 1
    if densify:
        mp.strategy.step_post_optimiser(mp)


def optimise(mp, iters: int, densify: bool = True, single_random: bool = False,
             progress: bool = False, budget_s: float = 0.0, min_iters: int = 0,
             yield_to: Optional[Callable[[], bool]] = None, subsample: int = 1,
             subsample_first: int = 0) -> int:
    """Up to ``iters`` Adam steps of the mapper ``mp`` (returns the number run); after
    ``min_iters`` they stop before one would end past ``budget_s`` (> 0) and, live, once
    ``yield_to()`` is true. ``subsample``: views rendered on a random 1/n pixel lattice
    (``subsample_first`` > 0: the first view of a step on its own)."""
    if iters <= 0 or len(mp.map) == 0:
        return 0
    m = mp.mcfg
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
        _step(mp, pick_views(mp.keyframes, mp.window.window, mp.rng, m, single_random),
              densify, subsample, subsample_first)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{mp.last_loss:.4f}")
    if bar is not None:
        bar.close()
    mp.skipped_iters += iters - done
    return done
