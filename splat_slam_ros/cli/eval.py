"""``splat-slam-eval``: ATE/RPE of an estimated trajectory against ground truth.

    splat-slam-eval --gt groundtruth.txt --est runs/fr1_xyz [--align sim3] [--json m.json]
                    [--plot traj.png]
    splat-slam-eval --mesh-gt GT.ply --mesh runs/x/map_mesh.ply [--gt ... --est ... --intrinsics K]

Prints a small table and a line ``ATE_RMSE_cm <value>`` for scripts to grep.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import List, Optional

import numpy as np

from splat_slam_ros.cli.eval_mesh import add_mesh_args, check_mesh_args, run_mesh_eval
from splat_slam_ros.evaluation import ALIGN_MODES, RPE_UNITS, MetricError, ate, rpe
from splat_slam_ros.mapping.mesh import MeshError
from splat_slam_ros.io.trajectory_io import FORMATS, TrajectoryFormatError, detect_format, read_trajectory

RUN_DIR_TRAJECTORY = "trajectory_full.txt"


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


def _resolve_est(path: str) -> Path:
    p = Path(path)
    if p.is_dir():
        f = p / RUN_DIR_TRAJECTORY
        if not f.is_file():
            have = sorted(x.name for x in p.glob("*.txt"))
            raise UserError(f"run directory {p} has no {RUN_DIR_TRAJECTORY}"
                            + (f" (it has: {', '.join(have[:8])})" if have else ""))
        return f
    if not p.exists():
        raise UserError(f"estimated trajectory not found: {p}")
    return p


def _read(path: Path, fmt: str, kitti_dt: float):
    used = detect_format(path) if fmt == "auto" else fmt
    ts, poses = read_trajectory(path, used, kitti_dt=kitti_dt)
    return ts, poses, used


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


def _json_safe(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def _write_json(path: str, a: dict, r: Optional[dict], r_err, args, gt_path, est_path,
                gt_fmt, est_fmt) -> None:
    ate_keys = ["rmse_cm", "mean_cm", "median_cm", "std_cm", "min_cm", "max_cm", "sse_m2",
                "rot_rmse_deg", "n_matched", "n_gt", "n_est", "scale"]
    out = {
        "gt": str(gt_path), "est": str(est_path), "gt_format": gt_fmt, "est_format": est_fmt,
        "align": args.align, "max_diff": args.max_diff, "offset": args.offset,
        "ate": {k: _json_safe(a[k]) for k in ate_keys},
        "alignment": {"scale": a["scale"], "rotation": a["rotation"].tolist(),
                      "translation": a["translation"].tolist()},
        "rpe": None, "rpe_error": r_err,
    }
    if r is not None:
        out["rpe"] = {k: _json_safe(v) for k, v in r.items()
                      if k not in ("trans_errors_cm", "rot_errors_deg", "pairs")}
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(out, indent=2) + "\n")


def _plot(path: str, a: dict, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    G = a["gt_poses"][:, :3, 3]
    E = a["aligned_est_poses"][:, :3, 3]
    t = a["timestamps"] - a["timestamps"][0]
    fig, ax = plt.subplots(2, 2, figsize=(11, 8.5))
    for k, (i, j) in enumerate([(0, 1), (0, 2)]):
        axk = ax[0, k]
        axk.plot(G[:, i], G[:, j], "k-", lw=1.2, label="ground truth")
        axk.plot(E[:, i], E[:, j], "-", color="tab:red", lw=1.0,
                 label=f"estimate ({a['align']} aligned)")
        axk.plot(G[0, i], G[0, j], "go", ms=5, label="start")
        axk.set_xlabel("xyz"[i] + " [m]")
        axk.set_ylabel("xyz"[j] + " [m]")
        axk.set_title(f"{'xyz'[i]}-{'xyz'[j]} view")
        axk.set_aspect("equal", adjustable="datalim")
        axk.grid(alpha=0.3)
    ax[0, 0].legend(fontsize=8, loc="best")
    for i, c in enumerate(("tab:red", "tab:green", "tab:blue")):
        ax[1, 0].plot(t, G[:, i], "-", color=c, lw=1.2, label=f"{'xyz'[i]} gt")
        ax[1, 0].plot(t, E[:, i], "--", color=c, lw=1.0, label=f"{'xyz'[i]} est")
    ax[1, 0].set_xlabel("time [s]")
    ax[1, 0].set_ylabel("position [m]")
    ax[1, 0].legend(fontsize=7, ncol=3)
    ax[1, 0].grid(alpha=0.3)
    ax[1, 1].plot(t, a["errors_cm"], "-", color="tab:purple", lw=1.0)
    ax[1, 1].axhline(a["rmse_cm"], color="k", ls="--", lw=0.8,
                     label=f"rmse {a['rmse_cm']:.2f} cm")
    ax[1, 1].set_xlabel("time [s]")
    ax[1, 1].set_ylabel("ATE [cm]")
    ax[1, 1].legend(fontsize=8)
    ax[1, 1].grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=110)
    plt.close(fig)


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
        est_path = _resolve_est(args.est)
        gt_ts, gt_P, gt_fmt = _read(gt_path, args.gt_format, args.kitti_dt)
        est_ts, est_P, est_fmt = _read(est_path, args.est_format, args.kitti_dt)
        try:
            a = ate(gt_ts, gt_P, est_ts, est_P, align=args.align, max_diff=args.max_diff,
                    offset=args.offset)
        except MetricError as e:
            if (gt_fmt == "kitti") != (est_fmt == "kitti") and "associate" in str(e):
                raise UserError(f"{e}; note: KITTI files carry no timestamps (row index x "
                                "--kitti-dt), so compare them with KITTI files") from None
            raise
        delta = args.rpe_delta
        if args.rpe_unit == "frames" and float(delta).is_integer():
            delta = int(delta)
        r, r_err = None, None
        try:
            r = rpe(gt_ts, gt_P, est_ts, est_P, delta=delta, unit=args.rpe_unit,
                    align=args.align, max_diff=args.max_diff, offset=args.offset)
        except MetricError as e:
            r_err = str(e)
        gt_info = f"{gt_path} ({len(gt_ts)} poses, {gt_fmt})"
        est_info = f"{est_path} ({len(est_ts)} poses, {est_fmt})"
        print(_table(a, r, r_err, args, gt_info, est_info))
        print(f"ATE_RMSE_cm {a['rmse_cm']:.4f}")
        if args.json:
            _write_json(args.json, a, r, r_err, args, gt_path, est_path, gt_fmt, est_fmt)
            print(f"wrote {args.json}")
        if args.plot:
            _plot(args.plot, a, f"{est_path.name} vs {gt_path.name}: ATE rmse "
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
