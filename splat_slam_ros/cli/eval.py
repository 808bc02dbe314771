"""``splat-slam-eval``: ATE/RPE of an estimated trajectory against ground truth.

    splat-slam-eval --gt groundtruth.txt --est runs/fr1_xyz [--align sim3] [--json m.json]
                    [--plot traj.png]
    splat-slam-eval --mesh-gt GT.ply --mesh runs/x/map_mesh.ply [--gt ... --est ... --intrinsics K]

Prints a small table and a line ``ATE_RMSE_cm <value>`` for scripts to grep.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import List, Optional

from splat_slam_ros.cli.eval_mesh import add_mesh_args, check_mesh_args, run_mesh_eval
from splat_slam_ros.evaluation.files import (RUN_DIR_TRAJECTORY, ate_rpe, plot_ate,
                                             read_with_format, resolve_estimate,
                                             write_eval_json)
from splat_slam_ros.evaluation.inputs import MetricError
from splat_slam_ros.evaluation.trajectory import ALIGN_MODES, RPE_UNITS
from splat_slam_ros.mapping.mesh import MeshError
from splat_slam_ros.io.trajectory_io import FORMATS, TrajectoryFormatError


class UserError(Exception):
    pass


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="splat-slam-eval",
        description="Absolute (ATE) and relative (RPE) trajectory error of an estimate against "
                    "ground truth, after Umeyama alignment of the full matched trajectory "
                    "(Sim(3) by default, as in the reference evaluation).")
    p.add_argument("--gt", help="ground-truth trajectory file (TUM, KITTI, EuRoC)")
    p.add_argument("--est",
                   help=f"estimated trajectory file, or a run directory (uses DIR/{RUN_DIR_TRAJECTORY})")
    p.add_argument("--align", choices=ALIGN_MODES, default="sim3",
                   help="alignment before computing errors (default: sim3)")
    p.add_argument("--max-diff", type=float, default=0.02,
                   help="max timestamp difference (s) for associating poses (default: 0.02)")
    p.add_argument("--offset", type=float, default=0.0,
                   help="time offset (s) added to the estimate's stamps when associating")
    fmts = ("auto",) + FORMATS
    p.add_argument("--gt-format", choices=fmts, default="auto")
    p.add_argument("--est-format", choices=fmts, default="auto")
    p.add_argument("--kitti-dt", type=float, default=0.1,
                   help="seconds between rows of KITTI files (which carry no stamps)")
    p.add_argument("--rpe-delta", type=float, default=1,
                   help="RPE pair distance (default: 1 frame)")
    p.add_argument("--rpe-unit", choices=RPE_UNITS, default="frames")
    p.add_argument("--json", metavar="OUT", help="write all numbers to this JSON file")
    p.add_argument("--plot", metavar="PNG", help="write a plot of GT and aligned estimate")
    add_mesh_args(p)
    return p


def _fmt(v, nd=4) -> str:
    return "n/a" if v is None else f"{v:.{nd}f}"


def _table(a: dict, r: Optional[dict], r_err: Optional[str], args, gt_info, est_info) -> str:
    rows = [
        f"Trajectory evaluation (align {args.align}, max time diff {args.max_diff} s)",
        f"  ground truth   {gt_info}",
        f"  estimate       {est_info}",
        f"  matched poses  {a['n_matched']}",
        f"  scale          {a['scale']:.6f}",
        "  ---------------------------------",
        f"  ATE rmse   [cm]  {_fmt(a['rmse_cm'])}",
        f"  ATE mean   [cm]  {_fmt(a['mean_cm'])}",
        f"  ATE median [cm]  {_fmt(a['median_cm'])}",
        f"  ATE std    [cm]  {_fmt(a['std_cm'])}",
        f"  ATE max    [cm]  {_fmt(a['max_cm'])}",
    ]
    d = f"delta {args.rpe_delta:g} {args.rpe_unit}"
    if r is not None:
        rows += [f"  RPE trans rmse [cm]  {_fmt(r['trans_rmse_cm'])}  ({d}, {r['n_pairs']} pairs)",
                 f"  RPE rot rmse  [deg]  {_fmt(r['rot_rmse_deg'])}"]
    else:
        rows += [f"  RPE  n/a: {r_err}"]
    return "\n".join(rows)


def main(argv: Optional[List[str]] = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if not args.max_diff >= 0:
            raise UserError(f"--max-diff must be >= 0, got {args.max_diff}")
        if not args.kitti_dt > 0:
            raise UserError(f"--kitti-dt must be > 0, got {args.kitti_dt}")
        mesh = check_mesh_args(args)
        if (args.gt is None) != (args.est is None) or (args.gt is None and not mesh):
            raise UserError("give --gt and --est (trajectories), --mesh-gt and --mesh, or both")
        if args.gt is None:
            run_mesh_eval(args, None)
            return 0
        gt_path = Path(args.gt)
        if gt_path.is_dir():
            raise UserError(f"--gt must be a trajectory file, {gt_path} is a directory")
        est_path = resolve_estimate(args.est)
        gt_ts, gt_P, gt_fmt = read_with_format(gt_path, args.gt_format, args.kitti_dt)
        est_ts, est_P, est_fmt = read_with_format(est_path, args.est_format, args.kitti_dt)
        a, r, r_err = ate_rpe((gt_ts, gt_P), (est_ts, est_P), gt_fmt, est_fmt, align=args.align,
                              max_diff=args.max_diff, offset=args.offset,
                              rpe_delta=args.rpe_delta, rpe_unit=args.rpe_unit)
        gt_info = f"{gt_path} ({len(gt_ts)} poses, {gt_fmt})"
        est_info = f"{est_path} ({len(est_ts)} poses, {est_fmt})"
        print(_table(a, r, r_err, args, gt_info, est_info))
        print(f"ATE_RMSE_cm {a['rmse_cm']:.4f}")
        if args.json:
            write_eval_json(args.json, a, r, r_err, args.align, args.max_diff, args.offset,
                            gt_path, est_path, gt_fmt, est_fmt)
            print(f"wrote {args.json}")
        if args.plot:
            plot_ate(args.plot, a, f"{est_path.name} vs {gt_path.name}: ATE rmse "
                     f"{a['rmse_cm']:.2f} cm ({args.align}, scale {a['scale']:.3f}, "
                     f"{a['n_matched']} poses)")
            print(f"wrote {args.plot}")
        if mesh:
            run_mesh_eval(args, a, gt_P)
    except (UserError, MetricError, TrajectoryFormatError, MeshError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: {e.strerror or e}: {e.filename or ''}".rstrip(": "), file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
