"""Camera trajectories for synthetic sequences: the built-in hand-held path, loading
TUM/KITTI/EuRoC files, pose interpolation, frame stamps and the world up axis."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.geometry import pose_from_tq, pose_to_tq, quat_slerp
from splat_slam_synth.options import GAP_WARN_S, SynthError
from splat_slam_ros.io.trajectory_io import detect_format, read_trajectory


def builtin_trajectory(duration: float = 60.0, seed: int = 0,
                       rate: float = 100.0) -> Tuple[np.ndarray, np.ndarray]:
    """A smooth hand-held-like path (world z up, 100 Hz, t from 0): a person strolling in a
    loop through a room while looking around a desk area, with hand tremor and small rolls."""
    rng = np.random.default_rng([int(seed), 11])
    n = int(math.ceil(duration * rate)) + 1
    t = np.arange(n) / rate

    def wave(amp, pmin, pmax, k=3):
        out = np.zeros_like(t)
        for _ in range(k):
            out += rng.uniform(0.5, 1.0) * np.sin(2 * np.pi * t / rng.uniform(pmin, pmax)
                                                  + rng.uniform(0, 2 * np.pi))
        return amp * out / k

    pos = np.stack([0.55 * np.sin(2 * np.pi * t / 38.0 + rng.uniform(0, 6)) + wave(0.15, 6, 15),
                    0.40 * np.sin(2 * np.pi * t / 27.0 + rng.uniform(0, 6)) + wave(0.15, 6, 15),
                    1.45 + wave(0.10, 4, 12)], 1)
    pos += np.stack([wave(0.004, 0.25, 0.7), wave(0.004, 0.25, 0.7), wave(0.003, 0.25, 0.7)], 1)
    target = np.stack([1.9 + wave(0.5, 8, 20), wave(1.2, 10, 25), 0.75 + wave(0.35, 6, 14)], 1)
    roll = np.radians(3.0) * wave(1.0, 3, 9) + np.radians(0.3) * wave(1.0, 0.3, 0.8)
    z = target - pos
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 0] = c * x + s * y          # roll about the optical axis
    poses[:, :3, 1] = -s * x + c * y
    poses[:, :3, 2] = z
    poses[:, :3, 3] = pos
    return t, poses


def _slerp(q0: np.ndarray, q1: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Batched SLERP of (x, y, z, w) quaternions (numpy front of geometry.quat_slerp)."""
    return quat_slerp(torch.from_numpy(np.asarray(q0, np.float64)),
                      torch.from_numpy(np.asarray(q1, np.float64)),
                      torch.from_numpy(np.asarray(a, np.float64))).numpy()


class PoseInterpolator:
    """Pose at any time from a (jittery, gappy) stamped trajectory: linear translation,
    SLERP rotation between the two bracketing rows; clamped outside the time range.

    Robust to motion-capture artefacts: rows are sorted by time, rows repeating a stamp
    (within 1 us) are dropped (first kept), and uneven spacing is handled by using the
    stamps, never the row index.
    """

    def __init__(self, timestamps, poses):
        ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        P = np.asarray(poses, dtype=np.float64)
        if P.ndim != 3 or P.shape[1:] != (4, 4) or len(P) != len(ts):
            raise SynthError(f"trajectory needs N stamps and N 4x4 poses, got {ts.shape} "
                             f"and {P.shape}")
        if not (np.all(np.isfinite(ts)) and np.all(np.isfinite(P))):
            raise SynthError("trajectory contains non-finite values")
        order = np.argsort(ts, kind="stable")
        ts, P = ts[order], P[order]
        keep = np.concatenate([[True], np.diff(ts) > 1e-6])
        ts, P = ts[keep], P[keep]
        if len(ts) < 2:
            raise SynthError("trajectory needs at least 2 poses with distinct timestamps")
        tq = pose_to_tq(torch.from_numpy(P)).numpy()
        q = tq[:, 3:]
        # make consecutive quaternions lie in the same hemisphere
        flips = np.concatenate([[1.0], np.sign(np.sum(q[1:] * q[:-1], 1) + 1e-300)])
        q = q * np.cumprod(flips)[:, None]
        self.t, self.p, self.q = ts, tq[:, :3], q
        self.dropped_duplicates = int((~keep).sum())

    @property
    def t_start(self) -> float:
        return float(self.t[0])

    @property
    def t_end(self) -> float:
        return float(self.t[-1])

    def _bracket(self, t) -> Tuple[np.ndarray, np.ndarray]:
        tc = np.clip(np.asarray(t, dtype=np.float64).reshape(-1), self.t[0], self.t[-1])
        i = np.clip(np.searchsorted(self.t, tc, side="right") - 1, 0, len(self.t) - 2)
        a = (tc - self.t[i]) / (self.t[i + 1] - self.t[i])
        return i, np.clip(a, 0.0, 1.0)

    def __call__(self, t) -> np.ndarray:
        """(M,) stamps -> (M, 4, 4) camera-to-world poses."""
        i, a = self._bracket(t)
        p = (1 - a)[:, None] * self.p[i] + a[:, None] * self.p[i + 1]
        q = _slerp(self.q[i], self.q[i + 1], a)
        return pose_from_tq(torch.from_numpy(np.concatenate([p, q], 1))).numpy()

    def gap_at(self, t) -> np.ndarray:
        """Length (s) of the ground-truth interval each stamp falls in."""
        i, _ = self._bracket(t)
        return self.t[i + 1] - self.t[i]

    def longest_gap_free(self, max_gap: float = GAP_WARN_S) -> Tuple[float, float]:
        """(start, end) seconds after the first stamp of the longest stretch whose rows are at
        most ``max_gap`` apart."""
        big = np.nonzero(np.diff(self.t) > max_gap)[0]
        starts = np.concatenate([[0], big + 1])
        ends = np.concatenate([big, [len(self.t) - 1]])
        k = int(np.argmax(self.t[ends] - self.t[starts]))
        return float(self.t[starts[k]] - self.t[0]), float(self.t[ends[k]] - self.t[0])

    def positions_between(self, t0: float, t1: float, rate: float = 200.0) -> np.ndarray:
        """Camera positions densely covering [t0, t1] (resampled + original rows)."""
        n = max(2, int(math.ceil((t1 - t0) * rate)) + 1)
        ts = np.linspace(t0, t1, n)
        rows = self.p[(self.t >= t0) & (self.t <= t1)]
        return np.concatenate([self(ts)[:, :3, 3], rows], 0)


def frame_stamps(t_first: float, t_last: float, frames: int, fps: float,
                 start: float = 0.0) -> np.ndarray:
    """N camera stamps at ``fps`` from ``t_first + start`` (rounded to the microsecond, the
    precision of the written file names); SynthError when they overrun ``t_last``."""
    if start < 0:
        raise SynthError(f"--start must be >= 0 seconds, got {start:g}")
    t0 = t_first + start
    avail = t_last - t0
    max_frames = int(math.floor(avail * fps + 1e-6)) + 1 if avail >= 0 else 0
    if frames > max_frames:
        raise SynthError(
            f"{frames} frames at {fps:g} fps need {(frames - 1) / fps:.2f} s of trajectory "
            f"after --start {start:g} s, but it covers only {max(avail, 0):.2f} s "
            f"(max --frames is {max_frames} at this fps and start)")
    return np.round((t0 + np.arange(frames) / fps) * 1e6) / 1e6


def load_trajectory(trajectory, *, fmt: str = "auto", kitti_dt: float = 0.1,
                    min_duration: float = 60.0, seed: int = 0):
    """'builtin' | path | (timestamps, poses) -> (timestamps, poses, format name)."""
    if isinstance(trajectory, str) and trajectory == "builtin":
        ts, P = builtin_trajectory(max(60.0, min_duration), seed=seed)
        return ts, P, "builtin"
    if isinstance(trajectory, (tuple, list)) and len(trajectory) == 2:
        return np.asarray(trajectory[0], float), np.asarray(trajectory[1], float), "array"
    path = Path(trajectory)
    f = detect_format(path) if fmt == "auto" else fmt
    ts, P = read_trajectory(path, fmt=f, kitti_dt=kitti_dt)
    return ts, P, f


UP_AXES = {"+x": (1, 0, 0), "x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "y": (0, 1, 0),
            "-y": (0, -1, 0), "+z": (0, 0, 1), "z": (0, 0, 1), "-z": (0, 0, -1)}


def estimate_up(poses: np.ndarray, fmt: Optional[str] = None) -> np.ndarray:
    """World 'up' for the room: motion-capture formats (TUM, EuRoC) and the built-in path are
    z-up; KITTI is -y (camera y points down); otherwise the mean camera -y axis, snapped to
    the nearest world axis when within 35 degrees."""
    if fmt in ("tum", "euroc", "builtin"):
        return np.array([0.0, 0.0, 1.0])
    if fmt == "kitti":
        return np.array([0.0, -1.0, 0.0])
    v = -np.asarray(poses)[:, :3, 1].mean(0)
    if np.linalg.norm(v) < 1e-6:
        return np.array([0.0, 0.0, 1.0])
    v = v / np.linalg.norm(v)
    k = int(np.argmax(np.abs(v)))
    if abs(v[k]) > math.cos(math.radians(35)):
        v = np.sign(v[k]) * np.eye(3)[k]
    return v
