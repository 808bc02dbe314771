"""The mapper alone on ground-truth poses and depth (``splat-slam-run --gt-poses --gt-depth``):
the map stage checked apart from tracking and proxy depth (supplementary "Mapping")."""
from __future__ import annotations

import time
from typing import Dict, Iterable, List, Optional, Tuple

import numpy as np

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.evaluation.rendering import evaluate_map
from splat_slam_ros.mapping.mapper import MapError, Mapper
from splat_slam_ros.types import Intrinsics


def map_sequence(frames: Iterable, cfg: SlamConfig, intrinsics: Intrinsics,
                 use_gt_depth: bool = True, progress: bool = True,
                 keyframe_every: Optional[int] = None,
                 refine_iters: Optional[int] = None,
                 lpips_model=None) -> Tuple[Mapper, dict]:
    """Mapping alone on ground-truth poses and depth (``splat-slam-run --gt-poses --gt-depth``).

    Every frame is offered as a keyframe and the covisibility rules decide, or every
    ``keyframe_every``-th frame is mapped (default ``mapping.keyframe_every``; 0 = rules).
    Ends with the final refinement (``refine_iters``, default ``mapping.final_refine_iters``)
    and returns (mapper, metrics on the mapped keyframes against the ground-truth depth;
    LPIPS too when ``lpips_model`` names a backbone file, see ``evaluation.perceptual.lpips``).
    """
    from tqdm import tqdm
    if not use_gt_depth:
        raise MapError("mapping without the tracker needs depth: use ground-truth depth "
                       "(--gt-depth) or run the full pipeline for proxy depth")
    every = cfg.mapping.keyframe_every if keyframe_every is None else int(keyframe_every)
    mapper = Mapper(cfg, intrinsics)
    mapper.progress = progress
    total = len(frames) if hasattr(frames, "__len__") else None
    bar = tqdm(total=total, unit="frame", desc="mapping", disable=not progress,
               dynamic_ncols=True)
    gt_depth: Dict[int, np.ndarray] = {}
    t0 = time.perf_counter()
    map_time = 0.0
    kf_times: List[float] = []
    offered = 0
    for i, fr in enumerate(frames):
        bar.update(1)
        if every > 0 and i % every != 0:
            continue
        if fr.gt_pose is None:
            raise MapError(f"frame {fr.index} has no ground-truth pose (needed by --gt-poses)")
        if fr.gt_depth is None:
            raise MapError(f"frame {fr.index} has no ground-truth depth (needed by --gt-depth)")
        offered += 1
        t1 = time.perf_counter()
        st = mapper.add_keyframe(fr.index, fr.image, fr.gt_pose, fr.gt_depth,
                                 timestamp=fr.timestamp, force=every > 0)
        map_time += time.perf_counter() - t1        # rejected keyframes cost a render
        if st["mapped"]:
            kf_times.append(time.perf_counter() - t1)
            gt_depth[fr.index] = np.asarray(fr.gt_depth, dtype=np.float32)
        bar.set_postfix(kf=st["keyframes"], G=st["gaussians"], ms=int(st["last_ms"]))
    bar.close()
    if not mapper.keyframes:
        raise MapError("no frames to map (empty input)")
    n_kf = len(mapper.keyframes)
    ref = mapper.final_refine(refine_iters, progress=progress)
    metrics = evaluate_map(mapper, None, gt_depth=gt_depth, lpips_model=lpips_model)
    metrics.update({"keyframes": n_kf, "frames_offered": offered,
                    "mapping_s": round(map_time, 3),
                    "s_per_keyframe": round(map_time / n_kf, 3),
                    "first_keyframe_s": round(kf_times[0], 3),
                    "s_per_later_keyframe": (round(float(np.mean(kf_times[1:])), 3)
                                             if n_kf > 1 else None),
                    "iterations": mapper.iteration, **ref,
                    "total_s": round(time.perf_counter() - t0, 3)})
    return mapper, metrics
