"""The in-process pipeline: every stage in one process, same protocol and outputs as the graph.

``run()`` feeds a dataset frame by frame to the :class:`~splat_slam_ros.coordinator.Coordinator`
(tracker -> loop closer -> proxy depth -> mapper, routed as the ROS graph routes them; see
docs/architecture.md for one keyframe's way from image to map), finalises it and writes
trajectory_full.txt, trajectory_keyframes.txt, map.ply, renders/ and metrics.json.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional, Sequence

import numpy as np

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.coordinator import Coordinator
from splat_slam_ros.evaluation.rendering import save_renders
from splat_slam_ros.evaluation.run import (check_lpips_config, evaluate_lpips, evaluate_map_depth,
                                           evaluate_trajectories)
from splat_slam_ros.io.session import remove_session
from splat_slam_ros.io.dataset_base import associate
from splat_slam_ros.io.trajectory_io import STAMP_TOL, write_tum
from splat_slam_ros.mapper_role import write_map_outputs, write_mesh
from splat_slam_ros.mapping.persistence import mapper_arrays
from splat_slam_ros.report.recording import WarningRecorder, keyframe_rate_text
from splat_slam_ros.tracking.relocalise import input_images, save_session, session_ids

log = logging.getLogger(__name__)


class NotInitializedError(RuntimeError):
    """The run has nothing to use: the tracker made no keyframe (no trajectory, no map), or
    a full run's map stayed empty (:func:`no_result_reason`)."""


@dataclass
class RunResult:
    frames: int = 0
    keyframes: int = 0
    wall_s: float = 0.0
    timings: Dict[str, float] = field(default_factory=dict)
    metrics: Dict[str, object] = field(default_factory=dict)
    events: int = 0


# the metrics.json entries a finished run prints, in this order (splat-slam-run, -launch)
SUMMARY_METRICS = ("ate_rmse_cm_full", "ate_rmse_cm_keyframes", "psnr", "ssim", "lpips",
                   "depth_l1_cm", "depth_l1_edges_cm", "depth_l1_surfaces_cm")


def keyframe_line(metrics: dict) -> Optional[str]:
    """The summary's keyframe line: per second of input and by cause (None without them)."""
    text = keyframe_rate_text(metrics)
    return None if text is None else f"keyframes per second of input {text}"


def frame_counts(received: int, dropped: int, posed: int, skipped: int = 0,
                 lost: int = 0) -> Dict[str, int]:
    """The frame counts of metrics.json, the same in every mode: ``frames_received`` (input
    frames that reached the tracker's intake), ``frames_dropped`` (of those, never posed:
    backlog full or unusable), ``frames_skipped`` (live input, tracker busy: posed by
    constant velocity at once and between their tracked neighbours in the trajectory),
    ``frames_lost`` (the tracker could not align them: posed between keyframes),
    ``frames_tracked`` (aligned by the tracker: received - dropped - skipped - lost) and
    ``frames_posed`` (lines of trajectory_full.txt)."""
    received, dropped, posed = int(received or 0), int(dropped or 0), int(posed or 0)
    skipped, lost = int(skipped or 0), int(lost or 0)
    return {"frames_received": received, "frames_dropped": dropped, "frames_skipped": skipped,
            "frames_lost": lost, "frames_tracked": received - dropped - skipped - lost,
            "frames_posed": posed}


def not_initialized_reason(cfg: SlamConfig, frames: int, lost: int = 0) -> str:
    """Why the tracker never initialised over ``frames`` frames: the flow was not confident
    on most of them (``lost``: little texture, blur, fast motion), or the camera moved too
    little; with the setting to try."""
    tc = cfg.tracking
    if lost and 2 * lost >= frames:
        rule = (f"fewer than tracking.lost_min_valid={tc.lost_min_valid:g} of the BA cells "
                f"had a usable flow")
        if tc.lost_rel_texture > 0:
            rule += (f", or on a view with little texture fewer than tracking.lost_rel_texture="
                     f"{tc.lost_rel_texture:g} of the cells its texture allows (and not fewer "
                     f"than {tc.lost_min_valid / 4:g} of all)")
        return (f"the tracker never initialised over {frames} frames: the flow was not "
                f"confident on {lost} of them ({rule}: little texture, "
                f"heavy blur or noise, or a motion too fast for the frame rate). For a scene "
                f"with little texture try --set tracking.lost_min_valid="
                f"{tc.lost_min_valid / 3:.2g}; otherwise give sharper input or a higher frame "
                f"rate")
    # the hint halves what is set now (suggesting the values already in use would not help)
    hint = f"--set tracking.motion_filter_thresh={tc.motion_filter_thresh / 2:g}"
    if tc.init_parallax > 0:
        hint += f" --set tracking.init_parallax={tc.init_parallax / 2:g}"
    return (f"the tracker never initialised over {frames} frames: the camera moved too little "
            f"for {tc.init_min_keyframes} keyframes with parallax (keyframe candidates need a "
            f"mean flow above tracking.motion_filter_thresh={tc.motion_filter_thresh:g} "
            f"reference BA px, initialisation a parallax of tracking.init_parallax="
            f"{tc.init_parallax:g}). Lower them (e.g. {hint}) or give a sequence with more "
            f"motion")


def empty_map_reason(cfg: SlamConfig, keyframes: int) -> str:
    return (f"the map is empty: the tracker made {keyframes} keyframes, but their proxy depth "
            f"had no pixel that depth.mv_min_views={cfg.depth.mv_min_views} other keyframes "
            f"confirm (too few keyframes or too little parallax between them). Give a longer "
            f"sequence with more camera motion, or a mono depth model (depth.mono_model) to "
            f"fill the proxy depth")


def no_result_reason(cfg: SlamConfig, metrics: dict) -> Optional[str]:
    """Why a run produced nothing to use (no keyframe, or a full run whose map has no
    Gaussian), or None: such a run ends with an error, never as a success."""
    if not metrics.get("keyframes"):
        return not_initialized_reason(cfg, int(metrics.get("frames") or 0),
                                      int(metrics.get("frames_lost") or 0))
    if metrics.get("gaussians", 1) == 0:
        return empty_map_reason(cfg, int(metrics["keyframes"]))
    return None


def _write_json(path: Path, data: dict) -> None:
    def default(o):
        if isinstance(o, (np.floating, np.integer)):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        return str(o)
    path.write_text(json.dumps(data, indent=2, default=default))


def run(dataset, cfg: SlamConfig, out: Path, mode: str = "full", progress: bool = True,
        max_frames: Optional[int] = None, session=None,
        skip_stamps: Optional[Sequence[float]] = None) -> RunResult:
    """Run the in-process pipeline over a dataset and write the standard outputs to ``out``.

    mode: "full" (tracking + depth + mapping), "tracking" (--tracking-only),
    "gt_mapping" (--gt-poses --gt-depth: the mapper alone on ground truth), "extend" (a full
    run that continues the loaded ``session``: :mod:`splat_slam_ros.extend`).
    ``skip_stamps``: the tracker skips the frames at these timestamps as a busy live tracker
    did (a live run's ``frames_skipped.txt``): the live tracker's work, replayed in process.
    Raises :class:`NotInitializedError` (after writing metrics.json) when the tracker made no
    keyframe, an extend run never relocalised, or a full run's map has no Gaussian
    (:func:`no_result_reason`); ConfigError before any work when a configured LPIPS backbone
    file is missing or invalid; SessionError before any frame for an unusable session.
    """
    if mode != "tracking":
        check_lpips_config(cfg)
    co = None
    if mode == "extend":                # the session is checked before any output is written
        from splat_slam_ros.extend import extend_coordinator
        co = extend_coordinator(cfg, dataset.intrinsics, session)
    out.mkdir(parents=True, exist_ok=True)
    (out / "renders").mkdir(exist_ok=True)
    t_start = time.perf_counter()
    warnings = WarningRecorder()                         # logged warnings, for the report
    result = RunResult()
    metrics: Dict[str, object] = {"mode": mode, "dataset": getattr(dataset, "name", "?")}
    if mode == "gt_mapping":
        _run_gt_mapping(dataset, cfg, out, progress, max_frames, result, metrics)
    else:
        _run_slam(dataset, cfg, out, mode, progress, max_frames, result, metrics, co, session,
                  skip_stamps)
    result.wall_s = time.perf_counter() - t_start
    metrics["frames"] = result.frames
    metrics["keyframes"] = result.keyframes
    metrics["wall_s"] = round(result.wall_s, 3)
    metrics["fps"] = round(result.frames / max(result.wall_s, 1e-9), 3)
    metrics["timings_s"] = result.timings
    metrics["update_events"] = result.events
    if "error" in metrics:                               # an extend run never relocalised
        pass
    elif mode != "gt_mapping" and result.keyframes == 0:
        metrics["error"] = not_initialized_reason(cfg, result.frames,
                                                  int(metrics.get("frames_lost") or 0))
    elif mode != "gt_mapping":
        evaluate_trajectories(dataset, out, metrics)
        if mode in ("full", "extend"):
            t0 = time.perf_counter()
            evaluate_map_depth(dataset, out, cfg, metrics)
            metrics["depth_eval_s"] = round(time.perf_counter() - t0, 3)
            reason = no_result_reason(cfg, metrics)
            if reason:
                metrics["error"] = reason
    if mode != "tracking" and "error" not in metrics:
        evaluate_lpips(out, cfg, metrics)                # lpips (null without a backbone)
    metrics["warnings"] = warnings.close()
    _write_json(out / "metrics.json", metrics)
    # imported here (matplotlib): tracking does not wait for it, nor holds it in memory
    from splat_slam_ros.report.build import write_report
    write_report(out, cfg)                               # report.html, report.png, config.yaml
    if "error" in metrics:
        raise NotInitializedError(metrics["error"])
    result.metrics = metrics
    return result


def _run_gt_mapping(dataset, cfg, out, progress, max_frames, result, metrics) -> None:
    from splat_slam_ros.evaluation.map_sequence import map_sequence   # the mapper, scipy
    frames = (f for i, f in enumerate(dataset) if max_frames is None or i < max_frames)
    mapper, m = map_sequence(frames, cfg, dataset.intrinsics, use_gt_depth=True,
                             progress=progress)
    mapper.save_ply(out / "map.ply")
    write_mesh(mapper, cfg, out, metrics, progress)
    metrics.update(m)
    save_renders(mapper, out / "renders")
    gt = dataset.gt_trajectory()
    if gt is not None:
        write_tum(out / "trajectory_full.txt", *gt)
        write_tum(out / "trajectory_keyframes.txt", *mapper.keyframe_trajectory())
    result.frames = len(dataset) if max_frames is None else min(len(dataset), max_frames)
    result.keyframes = int(m.get("keyframes", 0))


def _run_slam(dataset, cfg, out, mode, progress, max_frames, result, metrics, co=None,
              session=None, skip_stamps=None) -> None:
    """``co``: the coordinator of an extend run (:func:`extend.extend_coordinator`)."""
    from splat_slam_ros import extend
    remove_session(out)                # an earlier run's session must not outlive its outputs
    if co is None:
        co = Coordinator(cfg, dataset.intrinsics, mapping=(mode == "full"))
    skip = None
    if skip_stamps is not None:
        listed, replayed = np.sort(np.asarray(skip_stamps, dtype=np.float64)), []

        def skip(frame) -> bool:
            if associate([frame.timestamp], listed, STAMP_TOL)[0] is not None:
                replayed.append(frame.index)
                return True
            return False
    # without the dataset's depth: only the evaluation reads it, for the keyframes
    result.frames = co.run(dataset.iter_frames(depth=False), progress=progress,
                           total=len(dataset), max_frames=max_frames, skip=skip)
    if skip is not None:
        metrics["skips_replayed"] = len(replayed)
        if len(replayed) < len(skip_stamps):
            log.warning("%d of the %d skipped frames listed match no frame of the input",
                        len(skip_stamps) - len(replayed), len(skip_stamps))
    trk = co.tracker.tracker
    result.keyframes = len(trk.published)
    if mode == "extend":
        metrics["extend"] = extend.extend_metrics(co, session)
        if trk.relocalised_frame is None:
            metrics["error"] = extend.never_relocalised(result.frames, len(trk.loaded_ids))
            for stale in ("trajectory_full.txt", "trajectory_keyframes.txt", "map.ply"):
                (out / stale).unlink(missing_ok=True)
            return
    if result.keyframes == 0:               # never initialised: nothing posed (why: run())
        metrics.update(frame_counts(result.frames, 0, 0, skipped=trk.n_skipped,
                                    lost=trk.n_lost))
        return
    ts_full, poses_full = trk.trajectory_full()
    write_tum(out / "trajectory_full.txt", ts_full, poses_full)
    metrics.update(frame_counts(result.frames, 0, len(ts_full), skipped=trk.n_skipped,
                                lost=trk.n_lost))
    metrics.update(trk.keyframe_summary())
    write_tum(out / "trajectory_keyframes.txt", *trk.trajectory_keyframes())
    timings = {k: co.timings.get(k, 0.0) for k in ("tracking", "loop_closure", "depth",
                                                    "mapping")}
    if co.mapper is not None:
        timings["deformation"] = co.mapper.timings["deformation"]
        timings["refine"] = co.mapper.timings["refine"]
    result.timings = {k: round(v, 3) for k, v in timings.items()}
    result.events = len(co.updates)
    mp = co.mapper.mapper if co.mapper is not None else None
    if mp is not None:
        metrics.update(write_map_outputs(mp, cfg, out, progress))
    # the session a later run loads (--load-map OUT --localize): after map.ply, which it sums
    ids = session_ids(trk)
    images = input_images(trk, dataset.frames_at(trk.kfs[k].frame_index for k in ids), ids)
    save_session(trk, images, cfg, dataset.intrinsics, out,
                 None if mp is None else (*mapper_arrays(mp), mp.K),
                 co.loop.loop if co.loop is not None else None)
