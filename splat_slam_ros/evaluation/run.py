"""Run-level evaluation: the metrics.json entries of a finished run against the dataset's
ground truth (ATE of the written trajectories, depth L1 of the map, LPIPS of the keyframe
views) and the check of the configured LPIPS files before a run. The in-process pipeline and
the ROS launcher use the same functions: they read the run directory, not the run's objects.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import numpy as np

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.evaluation.depth import depth_edge_band, depth_l1_cm
from splat_slam_ros.evaluation.inputs import MetricError
from splat_slam_ros.evaluation.perceptual import check_lpips, lpips, release_lpips
from splat_slam_ros.io.dataset_base import stamp_key
from splat_slam_ros.evaluation.trajectory import ate
from splat_slam_ros.io.trajectory_io import read_trajectory, write_tum


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
    (:func:`.depth.depth_edge_band`; their share ``depth_edge_band_fraction``), and
    ``depth_l1_surfaces_cm`` over the rest (pixel means over all views).
    Used for in-process runs and graph runs alike (it reads ``out``'s map.ply and
    trajectory_keyframes.txt). Nothing is added when the dataset has no depth or ground truth."""
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
    want = {stamp_key(t): T for t, T in zip(ts, P)}
    band_px = int(cfg.tracking.ba_downsample)           # one BA cell
    errs, split = [], np.zeros((2, 2))                  # [band, surface] x [sum cm, pixels]
    for f in dataset.frames_at_stamps(want):          # the keyframes' frames only
        T = want.get(stamp_key(f.timestamp))
        if T is None or f.gt_depth is None:
            continue
        gd = pre.depth(f.gt_depth)
        _, d = mp.render(T)
        try:
            errs.append(depth_l1_cm(d * scale, gd))
        except MetricError:                             # nothing rendered in this view
            continue
        ok = np.isfinite(d) & (d > 0) & np.isfinite(gd) & (gd > 0)
        band = depth_edge_band(gd, band_px).numpy()
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
    from splat_slam_ros.config import ConfigError
    ec = cfg.evaluation
    if not ec.lpips_backbone:
        if ec.lpips_weights:
            raise ConfigError("evaluation.lpips_weights is set but evaluation.lpips_backbone "
                              "is not (the weights belong to a backbone)")
        return
    try:
        check_lpips(*_lpips_files(cfg))
    except MetricError as e:
        raise ConfigError(f"evaluation.lpips_backbone / lpips_weights: {e}") from None


def _keyframe_lpips(renders: Path, cfg: SlamConfig) -> float:
    import cv2
    from splat_slam_ros.mapping.keyframe_views import KEYFRAMES_JSON
    backbone, weights = _lpips_files(cfg)
    try:
        ids = [int(k["kf_id"]) for k in
               json.loads((renders / KEYFRAMES_JSON).read_text())["keyframes"]]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise MetricError(f"no keyframe views in {renders} ({type(e).__name__})") from None
    values = []
    for k in ids:
        names = [renders / f"kf_{k:05d}{s}.png" for s in ("", "_input")]
        pair = [cv2.imread(str(n), cv2.IMREAD_COLOR) for n in names]
        if pair[0] is None or pair[1] is None:
            raise MetricError(f"cannot read {names[0].name} / {names[1].name} in {renders}")
        values.append(lpips(pair[0][..., ::-1], pair[1][..., ::-1], backbone, weights))
    if not values:
        raise MetricError(f"no keyframe views in {renders}")
    return float(np.mean(values))


def evaluate_lpips(out: Path, cfg: SlamConfig, metrics: dict) -> None:
    """``lpips``: mean LPIPS over the mapped keyframes, each keyframe's render
    (renders/kf_<id>.png) against its input image (kf_<id>_input.png), the pairs PSNR and
    SSIM compare, with the backbone file ``evaluation.lpips_backbone`` (:func:`.perceptual.lpips`).
    None when no backbone is configured. When one is and LPIPS fails (a file gone or not a
    backbone, a backbone that fails on the images): None, ``lpips_error`` says why, and an
    ``error:`` line goes to stderr. Used for in-process and graph runs alike (it reads
    ``out``'s renders/)."""
    metrics["lpips"] = None
    if not cfg.evaluation.lpips_backbone:
        return
    try:
        metrics["lpips"] = round(_keyframe_lpips(out / "renders", cfg), 6)
    except MetricError as e:
        metrics["lpips_error"] = str(e)
        print(f"error: no LPIPS in metrics.json: {e}", file=sys.stderr)
    finally:
        release_lpips()
