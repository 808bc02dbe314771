"""Trajectory file formats in one place (TUM, KITTI, EuRoC), evo-compatible.

A trajectory is ``(timestamps (N,), poses (N, 4, 4))`` with camera-to-world (or
body-to-world) float64 poses. TUM rows: ``t tx ty tz qx qy qz qw``. KITTI rows:
12 numbers (the 3x4 matrix row-major, no timestamps: the row index is used,
scaled by ``kitti_dt``). EuRoC ground-truth CSV: ``t[ns], px, py, pz, qw, qx,
qy, qz, ...``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Tuple

import numpy as np
import torch

from splat_slam_ros.geometry import pose_from_tq, pose_to_tq


class TrajectoryFormatError(ValueError):
    """The file is missing or not a trajectory in the stated/detected format."""


FORMATS = ("tum", "kitti", "euroc")


def _numeric_rows(path: Path, delimiter=None, empty_ok: bool = False):
    rows = []
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split() if delimiter == "," else s.split()
        try:
            rows.append([float(x) for x in parts])
        except ValueError:
            raise TrajectoryFormatError(
                f"{path}:{lineno}: not a numeric trajectory row: {s[:80]!r}") from None
    if not rows:
        if empty_ok:
            return np.zeros((0, 0))
        raise TrajectoryFormatError(f"{path}: no trajectory rows found")
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        raise TrajectoryFormatError(f"{path}: rows have different numbers of columns {widths}")
    return np.asarray(rows, dtype=np.float64)


def _euroc_stamps(path: Path) -> np.ndarray:
    """Nanosecond integer stamps -> seconds without float64 rounding of the 1e18 value."""
    ns = [int(line.split(",")[0].strip()) for line in path.read_text().splitlines()
          if line.strip() and not line.startswith("#")]
    ns = np.asarray(ns, dtype=np.int64)
    base = ns[0] - ns[0] % 1_000_000_000
    return base * 1e-9 + (ns - base) * 1e-9


def detect_format(path: str | Path) -> str:
    p = Path(path)
    if not p.is_file():
        raise TrajectoryFormatError(f"trajectory file not found: {p}")
    first = ""
    for line in p.read_text(errors="replace").splitlines():
        if line.strip() and not line.startswith("#"):
            first = line.strip()
            break
    if not first:
        raise TrajectoryFormatError(f"{p}: empty trajectory file")
    if "," in first:
        return "euroc"
    n = len(first.split())
    if n == 8:
        return "tum"
    if n == 12:
        return "kitti"
    raise TrajectoryFormatError(
        f"{p}: cannot tell the format from a row of {n} columns "
        "(TUM has 8, KITTI 12, EuRoC is comma-separated)")


def read_trajectory(path: str | Path, fmt: str = "auto",
                    kitti_dt: float = 0.1) -> Tuple[np.ndarray, np.ndarray]:
    """Read a trajectory file; returns (timestamps (N,), poses (N,4,4))."""
    p = Path(path)
    if not p.is_file():
        raise TrajectoryFormatError(f"trajectory file not found: {p}")
    if fmt == "auto":
        fmt = detect_format(p)
    if fmt == "tum":
        a = _numeric_rows(p)
        if a.shape[1] != 8:
            raise TrajectoryFormatError(f"{p}: TUM rows need 8 columns, found {a.shape[1]}")
        ts, tq = a[:, 0], a[:, 1:8]
    elif fmt == "kitti":
        a = _numeric_rows(p)
        if a.shape[1] != 12:
            raise TrajectoryFormatError(f"{p}: KITTI rows need 12 columns, found {a.shape[1]}")
        T = np.tile(np.eye(4), (len(a), 1, 1))
        T[:, :3, :4] = a.reshape(-1, 3, 4)
        return np.arange(len(a)) * kitti_dt, T
    elif fmt == "euroc":
        a = _numeric_rows(p, delimiter=",")
        if a.shape[1] < 8:
            raise TrajectoryFormatError(f"{p}: EuRoC rows need >= 8 columns, found {a.shape[1]}")
        ts = _euroc_stamps(p)
        tq = np.concatenate([a[:, 1:4], a[:, 5:8], a[:, 4:5]], 1)  # qw qx qy qz -> qx qy qz qw
    else:
        raise TrajectoryFormatError(f"unknown trajectory format '{fmt}' (use one of {FORMATS})")
    order = np.argsort(ts, kind="stable")
    ts, tq = ts[order], tq[order]
    if np.any(np.abs(np.linalg.norm(tq[:, 3:], axis=1) - 1) > 0.1):
        raise TrajectoryFormatError(f"{p}: quaternions are not unit length")
    return ts, pose_from_tq(torch.from_numpy(tq)).numpy()


# the frames a live tracker skipped on arrival (its output folder); splat-slam-run
# --skip-frames replays them
SKIPPED_FRAMES = "frames_skipped.txt"
STAMP_TOL = 5e-4            # s: a listed stamp names the input frame this close to it


def write_stamps(path: str | Path, stamps, header: str) -> None:
    """One timestamp (s) per line, under a ``# header`` line."""
    with open(path, "w") as f:
        f.write(f"# {header}\n")
        for t in stamps:
            f.write(f"{float(t):.6f}\n")


def read_stamps(path: str | Path) -> np.ndarray:
    """Timestamps (s), one per line (``#`` comments), as :func:`write_stamps` writes them."""
    p = Path(path)
    if not p.is_file():
        raise TrajectoryFormatError(f"{p}: no such file")
    rows = _numeric_rows(p, empty_ok=True)
    if rows.size == 0:
        return np.zeros(0)
    if rows.shape[1] != 1:
        raise TrajectoryFormatError(f"{p}: expected one timestamp per line, found "
                                    f"{rows.shape[1]} columns")
    return rows[:, 0]


def write_tum(path: str | Path, timestamps, poses) -> None:
    """Write camera-to-world poses as a TUM trajectory file (what evo reads)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tq = pose_to_tq(torch.as_tensor(np.asarray(poses, dtype=np.float64))).numpy()
    ts = np.asarray(timestamps, dtype=np.float64)
    with open(p, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, r in zip(ts, tq):
            f.write(f"{t:.6f} " + " ".join(f"{x:.9f}" for x in r) + "\n")
