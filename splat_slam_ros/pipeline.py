"""The in-process pipeline: every stage in one process, same config and outputs as the graph.

One keyframe can be followed from image to map by reading ``SlamPipeline.process``:
tracker (flow + DBA, §3.1) -> keyframe -> proxy depth (Eq. 4-5, §3.2) -> Gaussian mapper
(Eq. 8); update events from local BA / loop closure / global BA -> proxy depth recomputed
-> map deformation (§3.2 "Map Deformation") before the next mapping step.
"""
from __future__ import annotations

import importlib
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterable, List, Optional

import numpy as np

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.io.trajectory_io import write_tum
from splat_slam_ros.mapping.mesh import map_mesh_output
from splat_slam_ros.types import Frame, Intrinsics, KeyframeData, UpdateEvent

# Which module provides each stage, and what the user loses without it.
STAGES = {
    "tracking": ("splat_slam_ros.tracking.tracker", "Tracker"),
    "loop_closure": ("splat_slam_ros.tracking.loop_closure", "LoopCloser"),
    "depth": ("splat_slam_ros.depth.proxy_depth", "ProxyDepthEstimator"),
    "mapping": ("splat_slam_ros.mapping.mapper", "Mapper"),
    "evaluation": ("splat_slam_ros.evaluation", "ate"),
}


class StageUnavailable(RuntimeError):
    """A pipeline stage that the requested mode needs is not available in this build."""


def stage(name: str):
    mod, attr = STAGES[name]
    try:
        return getattr(importlib.import_module(mod), attr)
    except (ImportError, AttributeError) as e:
        raise StageUnavailable(f"the {name} stage ({mod}.{attr}) is not available: {e}") from None


def stage_available(name: str) -> bool:
    try:
        stage(name)
        return True
    except StageUnavailable:
        return False


@dataclass
class RunResult:
    frames: int = 0
    keyframes: int = 0
    wall_s: float = 0.0
    timings: Dict[str, float] = field(default_factory=dict)
    metrics: Dict[str, object] = field(default_factory=dict)
    events: int = 0


class SlamPipeline:
    """Tracker + loop closure + proxy depth + mapper, driven frame by frame."""

    def __init__(self, cfg: SlamConfig, intrinsics: Intrinsics, mapping: bool = True):
        self.cfg = cfg
        self.tracker = stage("tracking")(cfg, intrinsics)
        self.loop = None
        if cfg.tracking.loop_closure or cfg.tracking.global_ba:
            if not getattr(self.tracker, "owns_loop_closure", False):
                # its own update seq range, as in track_sequence and the loop-closure node
                self.loop = stage("loop_closure")(cfg, intrinsics, seq_start=1_000_000_000)
        self.mapping = mapping
        self.depth = None
        self.mapper = None
        self.keyframes: Dict[int, KeyframeData] = {}
        self.mapper_kfs: set = set()     # keyframes handed to the mapper (deformable)
        self.timings: Dict[str, float] = {"tracking": 0.0, "loop_closure": 0.0, "depth": 0.0,
                                          "mapping": 0.0, "deformation": 0.0}
        self.n_events = 0

    # ----------------------------------------------------------------- stages
    def _timed(self, key: str, fn, *a, **k):
        t0 = time.perf_counter()
        out = fn(*a, **k)
        self.timings[key] += time.perf_counter() - t0
        return out

    def _ensure_mapping(self, kf: KeyframeData) -> None:
        if self.depth is None:
            self.depth = stage("depth")(self.cfg, kf.intrinsics)
        if self.mapper is None:
            self.mapper = stage("mapping")(self.cfg, kf.intrinsics)

    def _apply_events(self, events: Iterable[UpdateEvent], to_tracker: bool) -> None:
        for ev in events:
            self.n_events += 1
            if to_tracker:
                self.tracker.apply_update(ev)
            if self.loop is not None and not to_tracker:
                self.loop.apply_update(ev)
            for i, kid in enumerate(ev.kf_ids):
                if kid in self.keyframes:
                    self.keyframes[kid].pose = np.asarray(ev.poses[i])
                    if ev.disparities is not None:
                        self.keyframes[kid].disparity = np.asarray(ev.disparities[i])
            if self.mapping and self.depth is not None:
                self._deform(self._timed("depth", self.depth.apply_update, ev))

    def _deform(self, pairs) -> None:
        """Forward recomputed proxy depths (old, new) to the mapper's deformation."""
        for _old, new in pairs:
            if self.mapper is not None and new.kf_id in self.mapper_kfs:
                self._timed("deformation", self.mapper.apply_update, new.kf_id, new.pose,
                            new.depth, new.source > 0)

    def process(self, frame: Frame) -> None:
        step = self._timed("tracking", self.tracker.track, frame)
        self._apply_events(step.events, to_tracker=False)
        kfs = list(step.keyframes) or ([step.keyframe] if step.keyframe is not None else [])
        if not kfs:
            return
        for kf in kfs:
            self.keyframes[kf.kf_id] = kf
        if self.loop is not None:
            for kf in kfs:
                self.loop.add_keyframe(kf)
            loop_events = self._timed("loop_closure", self.loop.step)
            self._apply_events(loop_events, to_tracker=True)
        if self.mapping:
            self._ensure_mapping(kfs[0])
            # a burst (end of warm-up) is stored first so each keyframe sees the others
            proxies = self._timed("depth", self.depth.add_keyframes, kfs)
            self._deform(self.depth.take_refreshed())
            for kf, proxy in zip(kfs, proxies):
                self._timed("mapping", self.mapper.add_keyframe, kf.kf_id, kf.image, proxy.pose,
                            proxy.depth, proxy.source > 0)
                self.mapper_kfs.add(kf.kf_id)

    def finish(self) -> None:
        """Final global BA, deformation to the final poses, final refinement (supplementary)."""
        events = list(self._timed("tracking", self.tracker.finalize))
        self._apply_events(events, to_tracker=False)
        if self.loop is not None:
            events = self._timed("loop_closure", self.loop.finalize)
            self._apply_events(events, to_tracker=True)
        if self.mapping and self.mapper is not None:
            self._timed("mapping", self.mapper.final_refine, self.cfg.mapping.final_refine_iters)


def _write_json(path: Path, data: dict) -> None:
    def default(o):
        if isinstance(o, (np.floating, np.integer)):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        return str(o)
    path.write_text(json.dumps(data, indent=2, default=default))


def evaluate_trajectories(dataset, out: Path, metrics: dict) -> Optional[float]:
    """ATE (Sim(3), full and keyframes) when the dataset has ground truth."""
    gt = dataset.gt_trajectory() if hasattr(dataset, "gt_trajectory") else None
    if gt is None:
        return None
    ate = stage("evaluation")
    from splat_slam_ros.io.trajectory_io import read_trajectory
    scale = None
    for name in ("full", "keyframes"):
        f = out / f"trajectory_{name}.txt"
        if not f.is_file():
            continue
        try:
            ts, P = read_trajectory(f)
            r = ate(gt[0], gt[1], ts, P, align="sim3")
        except ValueError as e:  # MetricError: too few / degenerate poses to align
            metrics[f"ate_error_{name}"] = str(e)
            print(f"warning: no ATE for the {name} trajectory: {e}", file=sys.stderr)
            continue
        metrics[f"ate_rmse_cm_{name}"] = r["rmse_cm"]
        if name == "full":
            scale = r.get("scale")
    return scale


def run(dataset, cfg: SlamConfig, out: Path, mode: str = "full", progress: bool = True,
        max_frames: Optional[int] = None) -> RunResult:
    """Run the in-process pipeline over a dataset and write the standard outputs to ``out``.

    mode: "full" (tracking + depth + mapping), "tracking" (--tracking-only),
    "gt_mapping" (--gt-poses --gt-depth: the mapper alone on ground truth).
    """
    from tqdm import tqdm
    out.mkdir(parents=True, exist_ok=True)
    (out / "renders").mkdir(exist_ok=True)
    t_start = time.perf_counter()
    result = RunResult()
    metrics: Dict[str, object] = {"mode": mode, "dataset": getattr(dataset, "name", "?")}
    n_total = len(dataset) if max_frames is None else min(len(dataset), max_frames)

    if mode == "gt_mapping":
        from splat_slam_ros.mapping.mapper import map_sequence
        frames = (f for i, f in enumerate(dataset) if max_frames is None or i < max_frames)
        mapper, m = map_sequence(frames, cfg, dataset.intrinsics, use_gt_depth=True,
                                 progress=progress)
        mapper.save_ply(out / "map.ply")
        if cfg.mapping.mesh:
            metrics["mesh"] = map_mesh_output(mapper, out / "map_mesh.ply", progress)
        metrics.update(m)
        if hasattr(mapper, "save_renders"):
            mapper.save_renders(out / "renders")
        gt = dataset.gt_trajectory()
        if gt is not None:
            write_tum(out / "trajectory_full.txt", *gt)
            write_tum(out / "trajectory_keyframes.txt", *mapper.keyframe_trajectory())
        result.frames = n_total
        result.keyframes = int(m.get("keyframes", 0))
    else:
        pipe = SlamPipeline(cfg, dataset.intrinsics, mapping=(mode == "full"))
        bar = tqdm(total=n_total, unit="frame", disable=not progress, dynamic_ncols=True)
        for i, frame in enumerate(dataset):
            if max_frames is not None and i >= max_frames:
                break
            pipe.process(frame)
            result.frames += 1
            bar.update(1)
            bar.set_postfix(kf=len(pipe.keyframes),
                            fps=f"{result.frames / (time.perf_counter() - t_start):.2f}")
        bar.close()
        pipe.finish()
        result.keyframes = len(pipe.keyframes)
        write_tum(out / "trajectory_full.txt", *pipe.tracker.trajectory_full())
        write_tum(out / "trajectory_keyframes.txt", *pipe.tracker.trajectory_keyframes())
        result.timings = {k: round(v, 3) for k, v in pipe.timings.items()}
        result.events = pipe.n_events
        if pipe.mapper is not None:
            pipe.mapper.save_ply(out / "map.ply")
            if cfg.mapping.mesh:
                metrics["mesh"] = map_mesh_output(pipe.mapper, out / "map_mesh.ply", progress)
            metrics.update(pipe.mapper.evaluate_keyframes(out / "renders"))
            metrics["map"] = pipe.mapper.stats()
    result.wall_s = time.perf_counter() - t_start
    metrics["frames"] = result.frames
    metrics["keyframes"] = result.keyframes
    metrics["wall_s"] = round(result.wall_s, 3)
    metrics["fps"] = round(result.frames / max(result.wall_s, 1e-9), 3)
    metrics["timings_s"] = result.timings
    metrics["update_events"] = result.events
    if mode != "gt_mapping":
        evaluate_trajectories(dataset, out, metrics)
    _write_json(out / "metrics.json", metrics)
    result.metrics = metrics
    return result
