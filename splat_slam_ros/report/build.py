"""Building the run report: ``report.html`` + ``report.png`` from a run directory's files only.

A run directory (``splat-slam-run`` / ``splat-slam-launch`` / ``./run.sh demo`` output) holds
``metrics.json``, ``trajectory_full.txt``, ``trajectory_keyframes.txt``, ``groundtruth.txt``
(when the input had ground truth), ``config.yaml`` (the configuration used), ``map.ply`` and
``renders/`` with ``keyframes.json`` and per-keyframe images (mapping/keyframe_views.py).
:func:`write_report` turns them into one self-contained HTML page (every image embedded, no
script, no network) and one summary figure. It reads nothing else, and the output carries no
date, so ``splat-slam-report RUN_DIR`` rebuilds byte-identical files from an earlier run.
"""
from __future__ import annotations

from pathlib import Path
from typing import Tuple

from splat_slam_ros.report import plots as rp
from splat_slam_ros.report.page import build_html
from splat_slam_ros.report.recording import save_config
from splat_slam_ros.report.run_record import (CONFIG_YAML, REPORT_HTML, REPORT_PNG, TILE_NAMES,
                                              ReportError, RunRecord, headline,
                                              keyframe_positions, keyframe_tiles, load_run,
                                              stage_times, worst_keyframe)


# ====================================================================== summary figure
def summary_figure(rec: RunRecord) -> bytes:
    """report.png: trajectory, error over time, map size, stage times, keyframe quality and
    the keyframe with the lowest PSNR."""
    fig, ax = rp.new_figure(15, 9, 2, 3)
    est = rec.ate["aligned_est_poses"][:, :3, 3] if rec.ate else (
        rec.est[1][:, :3, 3] if rec.est is not None else None)
    gt = rec.ate["gt_poses"][:, :3, 3] if rec.ate else None
    rp.draw_trajectory(ax[0, 0], est, gt, keyframe_positions(rec), "trajectory (top view)")
    no_err = ("no ground truth: no trajectory error" if rec.gt is None
              else "trajectory error not available")
    rp.draw_error(ax[0, 1], rec.ate["timestamps"] if rec.ate else None,
                  rec.ate["errors_cm"] if rec.ate else None,
                  rec.ate["rmse_cm"] if rec.ate else None, no_err)
    rp.draw_map_size(ax[0, 2], rec.history, "no map history recorded")
    stages, unit = stage_times(rec)
    rp.draw_timings(ax[1, 0], stages, unit, "no timings recorded")
    rp.draw_keyframe_metrics(ax[1, 1], rec.keyframes, "no map: no rendered keyframes")
    w = worst_keyframe(rec)
    tiles, labels, title = None, [], "keyframe"
    if w is not None:
        got = [(t, n) for t, n in zip(keyframe_tiles(rec, int(w["kf_id"])), TILE_NAMES)
               if t is not None]
        tiles = [t for t, _ in got] or None
        labels = [n for _, n in got]
        title = f"lowest-PSNR keyframe {w['kf_id']} ({w['psnr']:.1f} dB)"
    rp.draw_tiles(ax[1, 2], tiles, labels, title, "no map: no rendered keyframes")
    fig.suptitle(headline(rec), fontsize=11)
    fig.tight_layout()
    return rp.fig_png(fig)


# ====================================================================== output
def write_report(run_dir, cfg=None, out_dir=None,
                 max_keyframes: int = 40) -> Tuple[Path, Path]:
    """Write ``report.html`` and ``report.png`` for a run directory.

    ``cfg`` (the run's SlamConfig) is first saved as ``config.yaml`` in the run directory, so
    runs call this at their end with it and ``splat-slam-report`` without. ``out_dir``
    (default: the run directory) receives the two files. Returns their paths."""
    run_dir = Path(run_dir)
    if cfg is not None:
        save_config(cfg, run_dir / CONFIG_YAML)
    if max_keyframes < 1:
        raise ReportError(f"max_keyframes must be >= 1, got {max_keyframes}")
    rec = load_run(run_dir)
    png = summary_figure(rec)
    page = build_html(rec, png, max_keyframes)
    out = Path(out_dir) if out_dir is not None else run_dir
    out.mkdir(parents=True, exist_ok=True)
    (out / REPORT_PNG).write_bytes(png)
    (out / REPORT_HTML).write_text(page, encoding="utf-8")
    return out / REPORT_HTML, out / REPORT_PNG
