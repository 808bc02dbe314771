"""The in-process pipeline: every stage in one process, same protocol and outputs as the graph.

``run()`` feeds a dataset frame by frame to the :class:`~splat_slam_ros.coordinator.Coordinator`
(tracker -> loop closer -> proxy depth -> mapper, routed as the ROS graph routes them; see
docs/architecture.md for one keyframe's way from image to map), finalises it and writes
trajectory_full.txt, trajectory_keyframes.txt, map.ply, renders/ and metrics.json.
"""
from __future__ import annotations

import itertools
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.coordinator import Coordinator
from splat_slam_ros.evaluation import ate
from splat_slam_ros.io.session import remove_session
from splat_slam_ros.io.trajectory_io import read_trajectory, write_tum
from splat_slam_ros.mapping.map_sequence import map_sequence
from splat_slam_ros.report import WarningRecorder, write_report
from splat_slam_ros.tracking.relocalise import input_images, save_session, session_ids


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


def not_initialized_reason(cfg: SlamConfig, frames: int) -> str:
    tc = cfg.tracking
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
        return not_initialized_reason(cfg, int(metrics.get("frames") or 0))
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


def evaluate_trajectories(dataset, out: Path, metrics: dict) -> Optional[float]:
    """ATE (Sim(3), full and keyframes) when the dataset has ground truth."""
    gt = dataset.gt_trajectory() if hasattr(dataset, "gt_trajectory") else None
    if gt is None:
        return None
    write_tum(out / "groundtruth.txt", *gt)             # for the run report
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


def evaluate_map_depth(dataset, out: Path, cfg: SlamConfig, metrics: dict) -> None:
    """``depth_l1_cm``: the map's rendered depth at the estimated keyframe poses against the
    dataset's depth brought to the keyframes' camera (undistortion, ``camera.crop``, the
    processing size; nearest-neighbour), after the Sim(3) scale of the keyframe
    trajectory's ATE alignment (a monocular map has no metric scale); pixels valid in both.
    Also split by where the error is: ``depth_l1_edges_cm`` over the pixels within
    ``tracking.ba_downsample`` px (one BA cell) of a depth edge of the dataset's depth
    (:func:`evaluation.depth_edge_band`; their share ``depth_edge_band_fraction``), and
    ``depth_l1_surfaces_cm`` over the rest (pixel means over all views).
    Used for in-process runs and graph runs alike (it reads ``out``'s map.ply and
    trajectory_keyframes.txt). Nothing is added when the dataset has no depth or ground truth."""
    from splat_slam_ros import evaluation as ev
    from splat_slam_ros.mapping.mapper import Mapper
    gt = dataset.gt_trajectory() if hasattr(dataset, "gt_trajectory") else None
    kf_file, ply = out / "trajectory_keyframes.txt", out / "map.ply"
    if gt is None or not getattr(dataset, "has_gt_depth", False) or not ply.is_file() \
            or not kf_file.is_file():
        return
    ts, P = read_trajectory(kf_file)
    try:
        scale = float(ate(gt[0], gt[1], ts, P, align="sim3")["scale"])
    except ValueError as e:                             # too few keyframes to align
        metrics["depth_l1_error"] = str(e)
        return
    from splat_slam_ros.tracking.flow_frontend import mapping_preprocessor
    pre = mapping_preprocessor(cfg, dataset.intrinsics)     # the keyframes' camera
    mp = Mapper.load_ply(ply, cfg, pre.intrinsics)
    want = {round(float(t), 4): T for t, T in zip(ts, P)}
    band_px = int(cfg.tracking.ba_downsample)           # one BA cell
    errs, split = [], np.zeros((2, 2))                  # [band, surface] x [sum cm, pixels]
    for f in dataset:
        T = want.get(round(float(f.timestamp), 4))
        if T is None or f.gt_depth is None:
            continue
        gd = pre.depth(f.gt_depth)
        _, d = mp.render(T)
        try:
            errs.append(ev.depth_l1_cm(d * scale, gd))
        except ev.MetricError:                          # nothing rendered in this view
            continue
        ok = np.isfinite(d) & (d > 0) & np.isfinite(gd) & (gd > 0)
        band = ev.depth_edge_band(gd, band_px).numpy()
        e = 100.0 * np.abs(d * scale - gd)
        for i, m in enumerate((ok & band, ok & ~band)):
            split[i] += (float(e[m].sum()), int(m.sum()))
    if errs:
        metrics["depth_l1_cm"] = round(float(np.mean(errs)), 4)
        metrics["depth_l1_views"] = len(errs)
        metrics["depth_l1_sim3_scale"] = round(scale, 6)
        # where the error is: within one BA cell of a true depth edge, or on surfaces
        for key, (tot, n) in zip(("depth_l1_edges_cm", "depth_l1_surfaces_cm"), split):
            metrics[key] = round(float(tot / n), 4) if n else None
        share = split[0, 1] / max(split[:, 1].sum(), 1)
        metrics["depth_edge_band_fraction"] = round(float(share), 4)


def _lpips_files(cfg: SlamConfig):
    """(backbone, weights or None) paths of ``evaluation.lpips_backbone`` / ``lpips_weights``."""
    ec = cfg.evaluation
    return (Path(ec.lpips_backbone).expanduser(),
            Path(ec.lpips_weights).expanduser() if ec.lpips_weights else None)


def check_lpips_config(cfg: SlamConfig) -> None:
    """ConfigError before a run when ``evaluation.lpips_backbone`` / ``lpips_weights`` name
    a file that is missing or is no backbone / weights file (the run's LPIPS would fail)."""
    from splat_slam_ros import evaluation as ev
    from splat_slam_ros.config import ConfigError
    ec = cfg.evaluation
    if not ec.lpips_backbone:
        if ec.lpips_weights:
            raise ConfigError("evaluation.lpips_weights is set but evaluation.lpips_backbone "
                              "is not (the weights belong to a backbone)")
        return
    try:
        ev.check_lpips(*_lpips_files(cfg))
    except ev.MetricError as e:
        raise ConfigError(f"evaluation.lpips_backbone / lpips_weights: {e}") from None


def _keyframe_lpips(renders: Path, cfg: SlamConfig) -> float:
    import cv2
    from splat_slam_ros import evaluation as ev
    from splat_slam_ros.mapping.keyframe_views import KEYFRAMES_JSON
    backbone, weights = _lpips_files(cfg)
    try:
        ids = [int(k["kf_id"]) for k in
               json.loads((renders / KEYFRAMES_JSON).read_text())["keyframes"]]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ev.MetricError(f"no keyframe views in {renders} ({type(e).__name__})") from None
    values = []
    for k in ids:
        names = [renders / f"kf_{k:05d}{s}.png" for s in ("", "_input")]
        pair = [cv2.imread(str(n), cv2.IMREAD_COLOR) for n in names]
        if pair[0] is None or pair[1] is None:
            raise ev.MetricError(f"cannot read {names[0].name} / {names[1].name} in {renders}")
        values.append(ev.lpips(pair[0][..., ::-1], pair[1][..., ::-1], backbone, weights))
    if not values:
        raise ev.MetricError(f"no keyframe views in {renders}")
    return float(np.mean(values))


def evaluate_lpips(out: Path, cfg: SlamConfig, metrics: dict) -> None:
    """``lpips``: mean LPIPS over the mapped keyframes, each keyframe's render
    (renders/kf_<id>.png) against its input image (kf_<id>_input.png), the pairs PSNR and
    SSIM compare, with the backbone file ``evaluation.lpips_backbone`` (:func:`evaluation.lpips`).
    None when no backbone is configured. When one is and LPIPS fails (a file gone or not a
    backbone, a backbone that fails on the images): None, ``lpips_error`` says why, and an
    ``error:`` line goes to stderr. Used for in-process and graph runs alike (it reads
    ``out``'s renders/)."""
    from splat_slam_ros import evaluation as ev
    metrics["lpips"] = None
    if not cfg.evaluation.lpips_backbone:
        return
    try:
        metrics["lpips"] = round(_keyframe_lpips(out / "renders", cfg), 6)
    except ev.MetricError as e:
        metrics["lpips_error"] = str(e)
        print(f"error: no LPIPS in metrics.json: {e}", file=sys.stderr)
    finally:
        ev.release_lpips()


def run(dataset, cfg: SlamConfig, out: Path, mode: str = "full", progress: bool = True,
        max_frames: Optional[int] = None, session=None) -> RunResult:
    """Run the in-process pipeline over a dataset and write the standard outputs to ``out``.

    mode: "full" (tracking + depth + mapping), "tracking" (--tracking-only),
    "gt_mapping" (--gt-poses --gt-depth: the mapper alone on ground truth), "extend" (a full
    run that continues the loaded ``session``: :mod:`splat_slam_ros.extend`).
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
        _run_slam(dataset, cfg, out, mode, progress, max_frames, result, metrics, co, session)
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
        metrics["error"] = not_initialized_reason(cfg, result.frames)
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
    write_report(out, cfg)                               # report.html, report.png, config.yaml
    if "error" in metrics:
        raise NotInitializedError(metrics["error"])
    result.metrics = metrics
    return result


def _mesh(mapper, cfg, out: Path, progress: bool, metrics: dict) -> None:
    if cfg.mapping.mesh:
        # Open3D takes 1.5 s to import: loaded when a mesh is written (not for tracking only)
        from splat_slam_ros.mapping.mesh import map_mesh_output
        metrics["mesh"] = map_mesh_output(mapper, out / "map_mesh.ply", progress)


def _run_gt_mapping(dataset, cfg, out, progress, max_frames, result, metrics) -> None:
    frames = (f for i, f in enumerate(dataset) if max_frames is None or i < max_frames)
    mapper, m = map_sequence(frames, cfg, dataset.intrinsics, use_gt_depth=True,
                             progress=progress)
    mapper.save_ply(out / "map.ply")
    _mesh(mapper, cfg, out, progress, metrics)
    metrics.update(m)
    mapper.save_renders(out / "renders")
    gt = dataset.gt_trajectory()
    if gt is not None:
        write_tum(out / "trajectory_full.txt", *gt)
        write_tum(out / "trajectory_keyframes.txt", *mapper.keyframe_trajectory())
    result.frames = len(dataset) if max_frames is None else min(len(dataset), max_frames)
    result.keyframes = int(m.get("keyframes", 0))


def _run_slam(dataset, cfg, out, mode, progress, max_frames, result, metrics, co=None,
              session=None) -> None:
    """``co``: the coordinator of an extend run (:func:`extend.extend_coordinator`)."""
    from splat_slam_ros import extend
    remove_session(out)                # an earlier run's session must not outlive its outputs
    if co is None:
        co = Coordinator(cfg, dataset.intrinsics, mapping=(mode == "full"))
    result.frames = co.run(dataset, progress=progress, total=len(dataset), max_frames=max_frames)
    trk = co.tracker.tracker
    result.keyframes = len(trk.published)
    if mode == "extend":
        metrics["extend"] = extend.extend_metrics(co, session)
        if trk.relocalised_frame is None:
            metrics["error"] = extend.never_relocalised(result.frames, len(trk.loaded_ids))
            for stale in ("trajectory_full.txt", "trajectory_keyframes.txt", "map.ply"):
                (out / stale).unlink(missing_ok=True)
            return
    if result.keyframes == 0:
        return
    ts_full, poses_full = trk.trajectory_full()
    write_tum(out / "trajectory_full.txt", ts_full, poses_full)
    metrics.update(frame_counts(result.frames, 0, len(ts_full), lost=trk.n_lost))
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
        mp.save_ply(out / "map.ply")
        _mesh(mp, cfg, out, progress, metrics)
        metrics.update(mp.evaluate_keyframes(out / "renders"))
        metrics["map"] = mp.stats()
    # the session a later run loads (--load-map OUT --localize): after map.ply, which it sums
    images = input_images(trk, itertools.islice(dataset, max_frames), session_ids(trk))
    save_session(trk, images, cfg, dataset.intrinsics, out, mp,
                 co.loop.loop if co.loop is not None else None)
