"""Trajectory evaluation of files, what ``splat-slam-eval`` computes and writes: the
estimate of a run directory, trajectory files read with format detection, the ATE and RPE
of two trajectories, and the results as JSON (with the mesh metrics merged in) and as a
plot."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional

import numpy as np

from splat_slam_ros.evaluation.inputs import MetricError
from splat_slam_ros.evaluation.trajectory import ate, rpe
from splat_slam_ros.io.trajectory_io import detect_format, read_trajectory

RUN_DIR_TRAJECTORY = "trajectory_full.txt"


def resolve_estimate(path: str) -> Path:
    """An estimate file, or a run directory's trajectory_full.txt."""
    p = Path(path)
    if p.is_dir():
        f = p / RUN_DIR_TRAJECTORY
        if not f.is_file():
            have = sorted(x.name for x in p.glob("*.txt"))
            raise MetricError(f"run directory {p} has no {RUN_DIR_TRAJECTORY}"
                              + (f" (it has: {', '.join(have[:8])})" if have else ""))
        return f
    if not p.exists():
        raise MetricError(f"estimated trajectory not found: {p}")
    return p


def read_with_format(path: Path, fmt: str, kitti_dt: float):
    """(stamps, poses, format used): ``fmt`` "auto" detects the format."""
    used = detect_format(path) if fmt == "auto" else fmt
    ts, poses = read_trajectory(path, used, kitti_dt=kitti_dt)
    return ts, poses, used


def ate_rpe(gt, est, gt_fmt: str, est_fmt: str, align: str = "sim3", max_diff: float = 0.02,
            offset: float = 0.0, rpe_delta=1, rpe_unit: str = "frames"):
    """ATE and RPE of the read trajectories ``gt`` / ``est`` ((stamps, poses) each):
    ``(ate, rpe or None, the RPE's error or None)``. An ATE whose poses do not associate
    between a KITTI file and a stamped one says why."""
    gt_ts, gt_P = gt
    est_ts, est_P = est
    try:
        a = ate(gt_ts, gt_P, est_ts, est_P, align=align, max_diff=max_diff,
                offset=offset)
    except MetricError as e:
        if (gt_fmt == "kitti") != (est_fmt == "kitti") and "associate" in str(e):
            raise MetricError(f"{e}; note: KITTI files carry no timestamps (row index x "
                              "--kitti-dt), so compare them with KITTI files") from None
        raise
    delta = rpe_delta
    if rpe_unit == "frames" and float(delta).is_integer():
        delta = int(delta)
    r, r_err = None, None
    try:
        r = rpe(gt_ts, gt_P, est_ts, est_P, delta=delta, unit=rpe_unit,
                align=align, max_diff=max_diff, offset=offset)
    except MetricError as e:
        r_err = str(e)
    return a, r, r_err


def _json_safe(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def write_eval_json(path: str, a: dict, r: Optional[dict], r_err, align: str, max_diff: float,
                    offset: float, gt_path, est_path, gt_fmt, est_fmt) -> None:
    """All numbers of an ATE (``a``) and RPE (``r``, or its error ``r_err``) as JSON."""
    ate_keys = ["rmse_cm", "mean_cm", "median_cm", "std_cm", "min_cm", "max_cm", "sse_m2",
                "rot_rmse_deg", "n_matched", "n_gt", "n_est", "scale"]
    out = {
        "gt": str(gt_path), "est": str(est_path), "gt_format": gt_fmt, "est_format": est_fmt,
        "align": align, "max_diff": max_diff, "offset": offset,
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


def plot_ate(path: str, a: dict, title: str) -> None:
    """A PNG of the ground truth and the aligned estimate (two views, xyz over time) and the
    ATE over time."""
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


def write_mesh_json(path: str, m: dict, est, gt, merge: bool) -> None:
    """The mesh metrics ``m`` as the ``mesh`` entry of the JSON file ``path``, merged into
    the file's trajectory numbers when ``merge`` (else the file holds the mesh only)."""
    p = Path(path)
    out = json.loads(p.read_text()) if merge and p.is_file() else {}
    out["mesh"] = {"est": str(est), "gt": str(gt), **m}
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(out, indent=2) + "\n")
