"""Synthetic RGB-D sequences in the TUM layout, driven by real recorded camera trajectories.

``generate_sequence`` samples N camera frames at ``fps`` along a trajectory (TUM, KITTI,
EuRoC or the built-in hand-held path), fits a textured room with furniture-like boxes
around it, renders RGB + exact z-depth by vectorised ray casting (analytic ray/box slab
intersections, trilinear mip-mapped textures, Lambertian shading with contact shadows)
and writes::

    OUT/rgb/<t>.png  OUT/depth/<t>.png (uint16, 5000 per metre)  OUT/rgb.txt  OUT/depth.txt
    OUT/groundtruth.txt (TUM, camera-to-world, the exact pose each frame was rendered with)
    OUT/intrinsics.yaml (Intrinsics.to_yaml + depth_scale, fps, generation record)

Camera realism (motion blur, auto-exposure drift, vignetting, shot/read noise, JPEG) is
applied to RGB only; depth stays clean for evaluation.

Conventions follow ``types.py``: poses camera-to-world, OpenCV camera axes (x right,
y down, z forward), pixel centres at integer coordinates. Internally the scene lives in a
"room frame" (z up, origin at the mean camera position); ``Scene.T_room_world`` maps
world points into it.
"""
from __future__ import annotations

import functools
import math
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Union

import cv2
import numpy as np
import torch

from splat_slam_ros.geometry import pose_from_tq, pose_to_tq, quat_slerp
from splat_slam_ros.io.trajectory_io import detect_format, read_trajectory, write_tum
from splat_slam_ros.types import Intrinsics

DEPTH_SCALE = 5000.0          # uint16 units per metre (TUM)
TEX_SIZE = 512                # texture tile size (texels, power of two)
TEX_LEVELS = 8                # mip levels 512 .. 4
IMAGE_EXTS = (".png", ".jpg", ".jpeg")
GAP_WARN_S = 0.2              # ground-truth gaps longer than this are reported


class SynthError(ValueError):
    """A user mistake in the synthetic-sequence options (printed as ``error: ...``)."""


# ============================================================ options / parsing
@dataclass
class RealismOptions:
    """Camera-realism effects (RGB only). Zero / 1 means off."""
    motion_blur: int = 1          # sub-exposure renders averaged per frame (1 = off)
    exposure_ms: float = 15.0     # exposure window before the frame stamp (for motion blur)
    auto_exposure: float = 0.0    # relative amplitude of the smooth gain drift (0.1 = +-10 %)
    vignetting: float = 0.0       # brightness loss in the image corners (0.3 = -30 %)
    noise: float = 0.0            # noise std at mid-grey, 8-bit units (shot + read)
    jpeg: int = 0                 # JPEG quality 1..100 (0 = off)

    def validate(self, fps: float) -> "RealismOptions":
        if int(self.motion_blur) != self.motion_blur or not 1 <= self.motion_blur <= 64:
            raise SynthError(f"--motion-blur must be an integer in 1..64, got {self.motion_blur}")
        self.motion_blur = int(self.motion_blur)
        frame_ms = 1000.0 / fps
        if not 0.0 < self.exposure_ms <= frame_ms + 1e-9:
            raise SynthError(f"--exposure must be in (0, {frame_ms:.3g}] ms (the frame period at "
                             f"{fps:g} fps), got {self.exposure_ms:g}")
        if not 0.0 <= self.auto_exposure <= 0.9:
            raise SynthError(f"--auto-exposure must be in [0, 0.9], got {self.auto_exposure:g}")
        if not 0.0 <= self.vignetting < 1.0:
            raise SynthError(f"--vignetting must be in [0, 1), got {self.vignetting:g}")
        if not 0.0 <= self.noise <= 64.0:
            raise SynthError(f"--noise must be in [0, 64] (8-bit units), got {self.noise:g}")
        if int(self.jpeg) != self.jpeg or not 0 <= self.jpeg <= 100:
            raise SynthError(f"--jpeg must be an integer quality in 1..100 (0 = off), got {self.jpeg}")
        self.jpeg = int(self.jpeg)
        return self

    @property
    def any(self) -> bool:
        return (self.motion_blur > 1 or self.auto_exposure > 0 or self.vignetting > 0
                or self.noise > 0 or self.jpeg > 0)


REALISM_PRESETS: Dict[str, RealismOptions] = {
    "clean": RealismOptions(),
    # A hand-held consumer RGB-D camera indoors: short blur, slow AE drift, mild vignetting,
    # sensor noise and light JPEG artefacts (the TUM Kinect streams were compressed too).
    "realistic": RealismOptions(motion_blur=5, exposure_ms=15.0, auto_exposure=0.08,
                                vignetting=0.25, noise=2.0, jpeg=90),
}


def parse_size(size) -> Tuple[int, int]:
    """'640x480' or (640, 480) -> (width, height)."""
    if isinstance(size, str):
        parts = size.lower().replace("*", "x").split("x")
        try:
            if len(parts) != 2:
                raise ValueError
            w, h = int(parts[0]), int(parts[1])
        except ValueError:
            raise SynthError(f"--size must look like WIDTHxHEIGHT (e.g. 640x480), got '{size}'") \
                from None
    else:
        try:
            w, h = (int(x) for x in size)
        except (TypeError, ValueError):
            raise SynthError(f"size must be (width, height) or 'WxH', got {size!r}") from None
    if not (8 <= w <= 8192 and 8 <= h <= 8192):
        raise SynthError(f"image size {w}x{h} out of range (each side 8..8192 pixels)")
    return w, h


def default_intrinsics(width: int, height: int, fov_deg: Optional[float] = None) -> Intrinsics:
    """TUM-like pinhole: fx = fy = 525 at 640 px wide (scaled), principal point at the centre;
    or the focal length giving a horizontal field of view ``fov_deg``."""
    if fov_deg is None:
        f = 525.0 * width / 640.0
    else:
        if not 10.0 <= fov_deg <= 160.0:
            raise SynthError(f"--fov must be in [10, 160] degrees, got {fov_deg:g}")
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


# ================================================================ trajectories
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


# ======================================================================= scene
_UP_AXES = {"+x": (1, 0, 0), "x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "y": (0, 1, 0),
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


def _point_box_distance(P: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    d = np.maximum(np.maximum(lo - P, 0.0), P - hi)
    return np.linalg.norm(d, axis=-1)


# ------------------------------------------------------------------ textures
_FREQ_CACHE: Dict = {}


def _noise(rng, S: int, fmin: float, fmax: float, beta: float = 1.0,
           aniso: Tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Periodic (tileable) band-limited noise on S x S, zero mean, unit std.
    fmin/fmax in cycles per tile; aniso stretches the spectrum (x, y)."""
    key = (S, aniso)
    if key not in _FREQ_CACHE:
        fy = np.fft.fftfreq(S)[:, None] * S * aniso[1]
        fx = np.fft.rfftfreq(S)[None, :] * S * aniso[0]
        f = np.sqrt(fx ** 2 + fy ** 2).astype(np.float32)
        _FREQ_CACHE[key] = (f, 1.0 / np.maximum(f, 1.0))
    f, inv_f = _FREQ_CACHE[key]
    amp = np.where((f >= fmin) & (f <= fmax), inv_f if beta == 1.0 else inv_f ** beta, 0.0)
    spec = rng.standard_normal((2,) + f.shape, dtype=np.float32) * amp
    spec = spec[0] + 1j * spec[1]
    n = np.fft.irfft2(spec, s=(S, S))
    return ((n - n.mean()) / (n.std() + 1e-12)).astype(np.float32)


def _fbm(rng, S):
    """Multi-scale noise: coarse mottling + mid + fine grain."""
    return 0.6 * _noise(rng, S, 1, 6) + 0.3 * _noise(rng, S, 6, 40) + 0.2 * _noise(rng, S, 40, S / 2)


def _color(rng, sat=(0.15, 0.6), val=(0.35, 0.85), hue=None) -> np.ndarray:
    h = rng.uniform(0, 1) if hue is None else hue
    s, v = rng.uniform(*sat), rng.uniform(*val)
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i],
                     dtype=np.float32)


def _draw_tiled(img: np.ndarray, fn) -> None:
    """Call fn(img, dx, dy) for the 9 periodic copies so shapes wrap across tile edges."""
    S = img.shape[0]
    for dy in (-S, 0, S):
        for dx in (-S, 0, S):
            fn(img, dx, dy)


def _shapes(rng, img: np.ndarray, n: int, kinds=("rect", "circle", "line", "text"),
            bright=(0.1, 0.95)) -> None:
    S = img.shape[0]
    for _ in range(n):
        kind = kinds[rng.integers(len(kinds))]
        col = tuple(float(c) for c in _color(rng, sat=(0.0, 0.8), val=bright))
        x, y = int(rng.integers(S)), int(rng.integers(S))
        if kind == "rect":
            w, h = int(rng.integers(S // 40, S // 5)), int(rng.integers(S // 40, S // 5))
            th = -1 if rng.uniform() < 0.7 else int(rng.integers(1, 4))
            _draw_tiled(img, lambda im, dx, dy: cv2.rectangle(
                im, (x + dx, y + dy), (x + dx + w, y + dy + h), col, th, cv2.LINE_AA))
        elif kind == "circle":
            r = int(rng.integers(S // 60, S // 10))
            th = -1 if rng.uniform() < 0.6 else int(rng.integers(1, 4))
            _draw_tiled(img, lambda im, dx, dy: cv2.circle(im, (x + dx, y + dy), r, col, th,
                                                             cv2.LINE_AA))
        elif kind == "line":
            x2, y2 = x + int(rng.integers(-S // 4, S // 4)), y + int(rng.integers(-S // 4, S // 4))
            th = int(rng.integers(1, 5))
            _draw_tiled(img, lambda im, dx, dy: cv2.line(im, (x + dx, y + dy), (x2 + dx, y2 + dy),
                                                           col, th, cv2.LINE_AA))
        else:  # "text": rows of small word blocks
            rows, lh = int(rng.integers(2, 7)), int(rng.integers(5, 10))
            width = int(rng.integers(S // 10, S // 4))
            blocks = []
            for r in range(rows):
                cx = 0
                while cx < width:
                    wl = int(rng.integers(4, 22))
                    blocks.append((cx, r * lh * 2, wl, lh))
                    cx += wl + int(rng.integers(3, 7))

            def draw(im, dx, dy):
                for bx, by, bw, bh in blocks:
                    cv2.rectangle(im, (x + dx + bx, y + dy + by),
                                  (x + dx + bx + bw, y + dy + by + bh), col, -1, cv2.LINE_AA)
            _draw_tiled(img, draw)


def tex_plaster(rng, S):
    c = _color(rng, sat=(0.02, 0.15), val=(0.72, 0.9))
    n = 0.045 * _noise(rng, S, 1, 8) + 0.03 * _noise(rng, S, 12, 64) + 0.02 * _noise(rng, S, 64, S / 2)
    return c[None, None] * (1 + n[..., None])


def tex_wallpaper(rng, S):
    c = _color(rng, sat=(0.05, 0.4), val=(0.55, 0.85))
    c2 = c * rng.uniform(0.6, 0.85)
    p = S // int(rng.choice([8, 16, 32]))
    y, x = np.mgrid[0:S, 0:S].astype(np.float32)
    kind = rng.integers(3)
    if kind == 0:
        pat = 0.5 + 0.5 * np.sin(2 * np.pi * x / p)
    elif kind == 1:
        pat = np.abs(np.sin(np.pi * x / p)) + np.abs(np.sin(np.pi * y / p))
        pat = (pat > 1.0).astype(np.float32)
    else:
        pat = ((np.hypot((x % p) - p / 2, (y % p) - p / 2) < p * 0.22)).astype(np.float32)
    pat = cv2.GaussianBlur(pat, (0, 0), 1.0)
    img = c[None, None] * (1 - pat[..., None]) + c2[None, None] * pat[..., None]
    img = img * (1 + 0.08 * _fbm(rng, S)[..., None])
    # a few posters / frames on the wall
    for _ in range(int(rng.integers(1, 4))):
        w, h = int(rng.integers(S // 6, S // 3)), int(rng.integers(S // 6, S // 3))
        x0, y0 = int(rng.integers(0, S - w)), int(rng.integers(0, S - h))
        poster = tex_clutter(rng, S)[:h, :w]
        img[y0:y0 + h, x0:x0 + w] = poster
        cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), (0.15, 0.12, 0.1), 3, cv2.LINE_AA)
    return img


def tex_wood(rng, S):
    planks = int(rng.choice([4, 8]))
    ph = S // planks
    y, x = np.mgrid[0:S, 0:S].astype(np.float32)
    warp = _noise(rng, S, 1, 12, aniso=(4.0, 0.5))
    k = int(rng.integers(20, 45))
    grain = np.sin(2 * np.pi * (k * y / S + 0.8 * warp))
    fine = _noise(rng, S, 30, S / 2, aniso=(6.0, 0.6))
    dark, light = _color(rng, sat=(0.45, 0.7), val=(0.25, 0.4), hue=rng.uniform(0.05, 0.1)), \
        _color(rng, sat=(0.35, 0.6), val=(0.55, 0.8), hue=rng.uniform(0.06, 0.11))
    t = np.clip(0.5 + 0.3 * grain + 0.15 * fine, 0, 1)[..., None]
    img = dark[None, None] * (1 - t) + light[None, None] * t
    row = (y // ph).astype(int)
    tone = rng.uniform(0.8, 1.15, planks)
    img *= tone[row][..., None]
    gap = ((y % ph) < 2).astype(np.float32)
    for r in range(planks):             # plank end joints
        jx = int(rng.integers(S))
        gap[r * ph:(r + 1) * ph, jx:jx + 2] = 1
    img *= (1 - 0.6 * cv2.GaussianBlur(gap, (0, 0), 0.7))[..., None]
    return img


def tex_tiles(rng, S):
    n = int(rng.choice([4, 8]))
    p = S // n
    y, x = np.mgrid[0:S, 0:S]
    c = _color(rng, sat=(0.05, 0.5), val=(0.45, 0.85))
    tile_tone = rng.uniform(0.85, 1.12, (n, n, 3))
    img = c[None, None] * tile_tone[y // p, x // p].astype(np.float32)
    if rng.uniform() < 0.4:   # checkerboard variant
        chk = ((y // p + x // p) % 2).astype(np.float32)[..., None]
        img = img * (1 - 0.35 * chk)
    img *= 1 + 0.06 * _fbm(rng, S)[..., None]
    mortar = (((y % p) < 3) | ((x % p) < 3)).astype(np.float32)
    mortar = cv2.GaussianBlur(mortar, (0, 0), 0.8)[..., None]
    mc = _color(rng, sat=(0.0, 0.1), val=(0.3, 0.75))
    return img * (1 - mortar) + mc[None, None] * mortar


def tex_bricks(rng, S):
    rows, cols = 16, 4
    bh, bw = S // rows, S // cols
    y, x = np.mgrid[0:S, 0:S]
    r = y // bh
    xs = (x + (r % 2) * bw // 2) % S
    c = r * cols + xs // bw
    base = _color(rng, sat=(0.35, 0.65), val=(0.35, 0.6), hue=rng.uniform(0.0, 0.08))
    tone = rng.uniform(0.75, 1.2, (rows * cols, 3)).astype(np.float32)
    img = base[None, None] * tone[c]
    img *= 1 + 0.1 * _fbm(rng, S)[..., None]
    m = (((y % bh) < 3) | ((xs % bw) < 3)).astype(np.float32)
    m = cv2.GaussianBlur(m, (0, 0), 0.8)[..., None]
    return img * (1 - m) + np.float32(0.72) * m


def tex_carpet(rng, S):
    c = _color(rng, sat=(0.2, 0.6), val=(0.3, 0.6))
    n = 0.12 * _noise(rng, S, 60, S / 2) + 0.1 * _noise(rng, S, 2, 12) + 0.06 * _noise(rng, S, 12, 60)
    img = c[None, None] * (1 + n[..., None])
    img *= 1 + 0.05 * _noise(rng, S, 20, 80)[..., None] * np.array([1, -0.5, 0.3], np.float32)
    return img


def tex_fabric(rng, S):
    y, x = np.mgrid[0:S, 0:S].astype(np.float32)
    c1, c2 = _color(rng), _color(rng)
    px, py = S / int(rng.choice([4, 8, 16])), S / int(rng.choice([4, 8, 16]))
    a = (0.5 + 0.5 * np.sin(2 * np.pi * x / px))[..., None]
    b = (0.5 + 0.5 * np.sin(2 * np.pi * y / py))[..., None]
    img = c1[None, None] * (1 - 0.5 * a) + c2[None, None] * 0.5 * b
    weave = np.sin(np.pi * x / 2.0) * np.sin(np.pi * y / 2.0)
    img *= (1 + 0.06 * weave[..., None] + 0.06 * _fbm(rng, S)[..., None])
    return img


def tex_clutter(rng, S):
    img = np.ascontiguousarray(
        np.repeat((0.55 + 0.12 * _fbm(rng, S))[..., None], 3, 2) * _color(rng, sat=(0, 0.3),
                                                                          val=(0.7, 1.0)))
    _shapes(rng, img, int(rng.integers(40, 110)))
    return img


def tex_granite(rng, S):
    c = [_color(rng, sat=(0.0, 0.3), val=v) for v in ((0.15, 0.35), (0.45, 0.65), (0.75, 0.95))]
    n1, n2 = _noise(rng, S, 20, S / 2), _noise(rng, S, 4, 30)
    img = np.where((n1 > 1.0)[..., None], c[0], np.where((n1 < -1.0)[..., None], c[2], c[1]))
    return img.astype(np.float32) * (1 + 0.1 * n2[..., None])


def tex_whiteboard(rng, S):
    img = np.ones((S, S, 3), np.float32) * _color(rng, sat=(0, 0.05), val=(0.82, 0.95))
    img *= 1 + 0.03 * _fbm(rng, S)[..., None]   # smudges: a realistic low-texture surface
    img = np.ascontiguousarray(img)
    for _ in range(int(rng.integers(16, 32))):  # handwriting-like strokes
        col = tuple(float(c) for c in _color(rng, sat=(0.5, 0.9), val=(0.15, 0.5)))
        p = rng.uniform(0, S, 2)
        pts = [p.copy()]
        ang = rng.uniform(0, 2 * np.pi)
        for _ in range(int(rng.integers(10, 40))):
            ang += rng.normal(0, 0.8)
            p = p + 8 * np.array([math.cos(ang), math.sin(ang)])
            pts.append(p.copy())
        arr = np.array(pts, np.int32)
        _draw_tiled(img, lambda im, dx, dy: cv2.polylines(im, [arr + (dx, dy)], False, col, 2,
                                                             cv2.LINE_AA))
    return img


PROCEDURAL = {"plaster": tex_plaster, "wallpaper": tex_wallpaper, "wood": tex_wood,
              "tiles": tex_tiles, "bricks": tex_bricks, "carpet": tex_carpet,
              "fabric": tex_fabric, "clutter": tex_clutter, "granite": tex_granite,
              "whiteboard": tex_whiteboard}


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=48)
def procedural_texture(kind: str, seed: int, slot: int) -> np.ndarray:
    """A TEX_SIZE^2 tileable uint8 RGB texture of ``kind`` (see PROCEDURAL), deterministic in
    (seed, slot); cached (read-only) so scenes re-built with one seed share textures."""
    arr = _to_u8(PROCEDURAL[kind](np.random.default_rng([int(seed), 31, int(slot)]), TEX_SIZE))
    arr.setflags(write=False)
    return arr


def _load_texture_images(folder, rng, S: int, max_images: int = 24) -> List[Tuple[str, np.ndarray]]:
    d = Path(folder)
    if not d.is_dir():
        raise SynthError(f"--textures folder not found: {d}")
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in IMAGE_EXTS and p.is_file())
    if not files:
        raise SynthError(f"--textures folder {d} holds no .png/.jpg images")
    if len(files) > max_images:
        files = [files[i] for i in sorted(rng.choice(len(files), max_images, replace=False))]
    out = []
    for p in files:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise SynthError(f"cannot read texture image {p}")
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        h, w = img.shape[:2]
        side = int(min(h, w) * rng.uniform(0.6, 1.0))
        y0, x0 = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
        crop = cv2.resize(img[y0:y0 + side, x0:x0 + side], (S, S), interpolation=cv2.INTER_AREA)
        out.append((f"image:{p.name}", crop))
    return out


def _mip_levels(tex: np.ndarray, levels: int) -> List[np.ndarray]:
    out = [tex]
    for _ in range(levels - 1):
        s = out[-1].shape[0] // 2
        out.append(cv2.resize(out[-1], (s, s), interpolation=cv2.INTER_AREA))
    return out


# --------------------------------------------------------------------- Scene
@dataclass
class Scene:
    """Axis-aligned room + boxes in the room frame (z up), with textures and lights.

    Surface ids: room faces ``2*axis + side`` (side 1 = the face at ``room_hi``), box ``b``
    faces ``6 + 6*b + 2*axis + side``.
    """
    room_lo: np.ndarray
    room_hi: np.ndarray
    boxes_lo: np.ndarray                    # (B, 3)
    boxes_hi: np.ndarray                    # (B, 3)
    T_room_world: np.ndarray                # (4, 4): X_room = T @ X_world
    textures: List[np.ndarray]              # (TEX_SIZE, TEX_SIZE, 3) uint8 RGB
    texture_names: List[str]
    surf_tex: np.ndarray                    # (6 + 6B,) texture index
    surf_density: np.ndarray                # (6 + 6B,) texels per metre
    surf_offset: np.ndarray                 # (6 + 6B, 2) texels
    surf_tint: np.ndarray                   # (6 + 6B, 3)
    light_pos: np.ndarray                   # point light (room frame)
    light_dir: np.ndarray                   # unit vector towards the directional light
    info: Dict = field(default_factory=dict)
    _cache: Dict = field(default_factory=dict, repr=False)

    @property
    def n_boxes(self) -> int:
        return len(self.boxes_lo)

    def without_boxes(self) -> "Scene":
        """The same room (textures, lights, frame) with every box removed."""
        return Scene(self.room_lo, self.room_hi, np.zeros((0, 3)), np.zeros((0, 3)),
                     self.T_room_world, self.textures, self.texture_names, self.surf_tex[:6],
                     self.surf_density[:6], self.surf_offset[:6], self.surf_tint[:6],
                     self.light_pos, self.light_dir, dict(self.info))

    def summary(self) -> Dict:
        return {"room_size_m": [round(float(x), 3) for x in self.room_hi - self.room_lo],
                "boxes": int(self.n_boxes), "textures": list(self.texture_names), **self.info}

    # ------------------------------------------------------------- torch state
    def _torch(self, device=None) -> Dict[str, torch.Tensor]:
        dev = torch.device(device or "cpu")
        key = f"t:{dev}"
        if key in self._cache:
            return self._cache[key]
        if dev.type != "cpu":
            t = {k: v.to(dev) for k, v in self._torch("cpu").items()}
            self._cache[key] = t
            return t
        B = self.n_boxes
        nS = 6 + 6 * B
        normal = np.zeros((nS, 3), np.float32)
        uax = np.zeros(nS, np.int64)
        vax = np.zeros(nS, np.int64)
        usign = np.ones(nS, np.float32)
        vsign = np.ones(nS, np.float32)
        flo = np.zeros((nS, 3), np.float32)
        fhi = np.zeros((nS, 3), np.float32)
        ao_k = np.zeros(nS, np.float32)
        ao_r = np.ones(nS, np.float32)
        for s in range(nS):
            box = (s - 6) // 6 if s >= 6 else -1
            a, side = (s % 6) // 2, s % 2
            if box < 0:   # room faces: normals point into the room
                n = np.eye(3)[a] * (1.0 if side == 0 else -1.0)
                flo[s], fhi[s] = self.room_lo, self.room_hi
                ao_k[s], ao_r[s] = 0.35, 0.3       # soft darkening in concave corners
            else:
                n = np.eye(3)[a] * (-1.0 if side == 0 else 1.0)
                flo[s], fhi[s] = self.boxes_lo[box], self.boxes_hi[box]
                ao_k[s], ao_r[s] = 0.35, 0.008     # thin dark bevel along box edges
            normal[s] = n
            if a == 2:
                uax[s], vax[s] = 0, 1
            else:
                # u = viewer's right when facing the surface (textures not mirrored), v down
                uax[s] = 1 if a == 0 else 0
                usign[s] = n[0] if a == 0 else -n[1]
                vax[s], vsign[s] = 2, -1.0
        # texture atlas: every texture's mip levels stacked vertically in a column block,
        # each level with one wrapped border row/column so bilinear sampling tiles seamlessly
        S = TEX_SIZE
        Hb = sum((S >> l) + 1 for l in range(TEX_LEVELS))
        atlas = np.zeros((3, Hb, len(self.textures) * (S + 1)), np.float32)
        org = np.zeros((len(self.textures), TEX_LEVELS, 2), np.float32)   # (x, y) of texel 0
        for i, tx in enumerate(self.textures):
            y = 0
            for l, arr in enumerate(_mip_levels(tx, TEX_LEVELS)):
                sl = arr.shape[0]
                x = i * (S + 1)
                wrapped = np.concatenate([arr, arr[:1]], 0)
                wrapped = np.concatenate([wrapped, wrapped[:, :1]], 1)
                atlas[:, y:y + sl + 1, x:x + sl + 1] = wrapped.transpose(2, 0, 1)
                org[i, l] = (x, y)
                y += sl + 1
        # baked contact shadows of the boxes standing on the floor (view-independent)
        ext = self.room_hi[:2] - self.room_lo[:2]
        res = max(0.01, float(ext.max()) / 1024)
        gx = self.room_lo[0] + (np.arange(int(math.ceil(ext[0] / res)) + 1)) * res
        gy = self.room_lo[1] + (np.arange(int(math.ceil(ext[1] / res)) + 1)) * res
        shadow = np.ones((len(gy), len(gx)), np.float32)
        for b in range(B):
            if abs(self.boxes_lo[b, 2] - self.room_lo[2]) > 1e-6:
                continue
            dx = np.maximum(np.maximum(self.boxes_lo[b, 0] - gx, gx - self.boxes_hi[b, 0]), 0)
            dy = np.maximum(np.maximum(self.boxes_lo[b, 1] - gy, gy - self.boxes_hi[b, 1]), 0)
            dist = np.sqrt(dy[:, None] ** 2 + dx[None, :] ** 2)
            shadow *= (1 - 0.45 * np.exp(-dist / 0.12)).astype(np.float32)
        # per-surface tables: one float and one int row per surface id
        tabf = np.zeros((nS, 13), np.float32)
        tabf[:, 0], tabf[:, 1] = usign, vsign
        tabf[:, 2] = self.surf_density
        tabf[:, 3:5] = self.surf_offset
        tabf[:, 5:8] = normal
        tabf[:, 8], tabf[:, 9] = ao_k, ao_r
        tabf[:, 10] = flo[np.arange(nS), uax]
        tabf[:, 11] = fhi[np.arange(nS), uax]
        tabf[:, 12] = 0.0                # (unused)
        tabv = np.stack([flo[np.arange(nS), vax], fhi[np.arange(nS), vax]], 1).astype(np.float32)
        axis = (np.arange(nS) % 6) // 2
        tabi = np.stack([uax, vax, axis, self.surf_tex.astype(np.int64)], 1)
        f32 = lambda x: torch.as_tensor(np.asarray(x, np.float32))  # noqa: E731
        t = dict(room_lo=f32(self.room_lo), room_hi=f32(self.room_hi),
                 boxes_lo=f32(self.boxes_lo.reshape(-1, 3)), boxes_hi=f32(self.boxes_hi.reshape(-1, 3)),
                 tabf=torch.cat([f32(tabf), f32(tabv), f32(self.surf_tint)], 1),
                 tabi=torch.as_tensor(tabi),
                 atlas=torch.from_numpy(atlas)[None],
                 org=f32(org.reshape(-1, 2)),
                 light_pos=f32(self.light_pos), light_dir=f32(self.light_dir),
                 floor_shadow=torch.from_numpy(shadow)[None, None],
                 floor_grid=torch.tensor([self.room_lo[0], self.room_lo[1],
                                          2.0 / (res * (len(gx) - 1)), 2.0 / (res * (len(gy) - 1))],
                                         dtype=torch.float32))
        self._cache[key] = t
        return t


def make_scene(room_lo, room_hi, boxes_lo=(), boxes_hi=(), *, seed: int = 0,
               T_room_world=None, textures: Optional[Union[str, Path]] = None,
               info: Optional[Dict] = None) -> Scene:
    """A scene from explicit geometry (room frame, z up): textures, tints and lights are
    drawn from ``seed`` (images from the ``textures`` folder when given)."""
    rng = np.random.default_rng([int(seed), 3])
    room_lo, room_hi = np.asarray(room_lo, float), np.asarray(room_hi, float)
    boxes_lo = np.asarray(boxes_lo, float).reshape(-1, 3)
    boxes_hi = np.asarray(boxes_hi, float).reshape(-1, 3)
    if np.any(room_hi - room_lo <= 0) or np.any(boxes_hi - boxes_lo <= 0):
        raise SynthError("scene boxes need lo < hi on every axis")
    S = TEX_SIZE
    B = len(boxes_lo)
    images = _load_texture_images(textures, rng, S) if textures else []
    names: List[str] = []
    texs: List[np.ndarray] = []

    def add(name, arr):
        if name.startswith("image:") and name in names:
            return names.index(name)
        names.append(name)
        texs.append(arr if arr.dtype == np.uint8 else _to_u8(arr))
        return len(texs) - 1

    # room: floor (z lo), ceiling (z hi), four walls
    slot = iter(range(10 ** 6))

    def proc(kind):
        return add(kind, procedural_texture(kind, seed, next(slot)))

    floor = proc(str(rng.choice(["wood", "tiles", "carpet"])))
    ceiling = proc("plaster")
    wall_kinds = ["wallpaper", "bricks", "clutter", "whiteboard", "tiles", "wallpaper"]
    rng.shuffle(wall_kinds)
    walls = []
    for i in range(4):
        if images and rng.uniform() < 0.5:
            walls.append(add(*images[int(rng.integers(len(images)))]))
        else:
            walls.append(proc(wall_kinds[i]))
    obj_kinds = ["wood", "fabric", "clutter", "granite", "tiles", "whiteboard", "carpet",
                 "plaster", "clutter", "wood"]
    obj = []
    for i in range(min(max(B, 1), 10)):
        if images and rng.uniform() < 0.6:
            obj.append(add(*images[int(rng.integers(len(images)))]))
        else:
            obj.append(proc(obj_kinds[int(rng.integers(len(obj_kinds)))]))
    nS = 6 + 6 * B
    tex = np.zeros(nS, np.int64)
    dens = np.zeros(nS)
    tint = np.ones((nS, 3))
    tex[[0, 1, 2, 3]] = walls                 # x-lo, x-hi, y-lo, y-hi walls
    tex[4], tex[5] = floor, ceiling
    dens[:4] = S / rng.uniform(1.2, 2.0, 4)    # one tile per 1.2-2 m
    dens[4], dens[5] = S / rng.uniform(1.0, 1.6), S / rng.uniform(1.5, 2.5)
    tint[:6] = rng.uniform(0.9, 1.08, (6, 3))
    for b in range(B):
        t_b = obj[int(rng.integers(len(obj)))]
        sl = slice(6 + 6 * b, 12 + 6 * b)
        tex[sl] = t_b
        dens[sl] = S / rng.uniform(0.5, 1.1)
        tint[sl] = rng.uniform(0.8, 1.15, 3)[None] * rng.uniform(0.95, 1.05, (6, 3))
    off = rng.uniform(0, S, (nS, 2))
    centre = 0.5 * (room_lo + room_hi)
    light_pos = np.array([centre[0] + rng.uniform(-0.5, 0.5), centre[1] + rng.uniform(-0.5, 0.5),
                          room_hi[2] - 0.3])
    ld = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), 1.0])
    return Scene(room_lo, room_hi, boxes_lo, boxes_hi,
                 np.eye(4) if T_room_world is None else np.asarray(T_room_world, float),
                 texs, names, tex, dens, off, tint, light_pos, ld / np.linalg.norm(ld),
                 dict(info or {}))


def build_scene(poses: np.ndarray, *, seed: int = 0, textures=None, up=None, fmt=None,
                positions: Optional[np.ndarray] = None, clearance: float = 0.5,
                n_boxes: Optional[int] = None) -> Scene:
    """Fit a room with furniture-like boxes around camera-to-world ``poses`` (world frame).

    All camera positions (``poses`` plus the optional dense ``positions``, e.g. the whole
    exposure windows) lie inside the room with >= 1.1 m margin, and every box keeps
    ``clearance`` metres from every position. Boxes are placed around points the cameras
    look at (0.9-3.2 m along central view rays), so they give parallax and occlusion.
    """
    rng = np.random.default_rng([int(seed), 5])
    P = np.asarray(poses, float)
    up_v = np.asarray(_UP_AXES[up] if isinstance(up, str) else (up if up is not None
                      else estimate_up(P, fmt)), float)
    up_v /= np.linalg.norm(up_v)
    # room frame: z up, x along the mean horizontal viewing direction
    fwd = P[:, :3, 2] - np.outer(P[:, :3, 2] @ up_v, up_v)
    f = fwd.mean(0)
    if np.linalg.norm(f) < 0.2:
        pos_h = P[:, :3, 3] - np.outer(P[:, :3, 3] @ up_v, up_v)
        pos_h = pos_h - pos_h.mean(0)
        f = np.linalg.svd(pos_h, full_matrices=False)[2][0] if len(P) > 2 else np.zeros(3)
        if np.linalg.norm(f - (f @ up_v) * up_v) < 1e-6:
            f = np.cross(up_v, np.eye(3)[int(np.argmin(np.abs(up_v)))])
    f = f - (f @ up_v) * up_v
    xr = f / np.linalg.norm(f)
    yr = np.cross(up_v, xr)
    R_rw = np.stack([xr, yr, up_v], 0)
    origin = P[:, :3, 3].mean(0)
    T_rw = np.eye(4)
    T_rw[:3, :3] = R_rw
    T_rw[:3, 3] = -R_rw @ origin
    cams = P[:, :3, 3] @ R_rw.T + T_rw[:3, 3]
    allp = cams if positions is None else np.concatenate(
        [cams, np.asarray(positions, float).reshape(-1, 3) @ R_rw.T + T_rw[:3, 3]], 0)
    R_rc = np.einsum("ij,njk->nik", R_rw, P[:, :3, :3])
    lo, hi = allp.min(0), allp.max(0)
    room_lo = np.array([lo[0] - rng.uniform(1.3, 2.0), lo[1] - rng.uniform(1.3, 2.0),
                        lo[2] - rng.uniform(1.15, 1.45)])
    room_hi = np.array([hi[0] + rng.uniform(1.6, 2.4), hi[1] + rng.uniform(1.3, 2.0), 0.0])
    room_hi[2] = max(hi[2] + rng.uniform(0.9, 1.3), room_lo[2] + 2.6)
    for a in range(2):                     # at least 3.6 m across
        short = 3.6 - (room_hi[a] - room_lo[a])
        if short > 0:
            room_lo[a] -= short / 2
            room_hi[a] += short / 2
    floor_z, ceil_z = room_lo[2], room_hi[2]
    area = float(np.prod(room_hi[:2] - room_lo[:2]))
    target = int(np.clip(area / 2.0 + 6, 8, 32)) if n_boxes is None else int(n_boxes)

    def exit_dist(o, d):
        with np.errstate(divide="ignore"):
            inv = 1.0 / np.where(d == 0, 1e-12, d)
        return np.min(np.maximum((room_lo - o) * inv, (room_hi - o) * inv))

    blo: List[np.ndarray] = []
    bhi: List[np.ndarray] = []
    kinds: List[str] = []
    tries = 0
    while len(blo) < target and tries < 60 * max(target, 1):
        tries += 1
        i = int(rng.integers(len(P)))
        o = cams[i]
        d = R_rc[i] @ np.array([rng.uniform(-0.45, 0.45), rng.uniform(-0.34, 0.34), 1.0])
        d /= np.linalg.norm(d)
        tw = exit_dist(o, d)
        kind = str(rng.choice(["furniture", "cabinet", "object"], p=[0.45, 0.2, 0.35]))
        if kind == "cabinet":
            s = tw - 0.05
        else:
            s = min(max(rng.uniform(0.35, 0.85) * tw, 0.9), 3.2, tw - 0.4)
            if s < 0.9:
                continue
        c = o + s * d
        if kind == "furniture":
            half = rng.uniform(0.2, 0.6, 2)
            z0, z1 = floor_z, np.clip(c[2] + rng.uniform(-0.05, 0.2), floor_z + 0.3, ceil_z - 0.3)
        elif kind == "cabinet":
            half = rng.uniform(0.2, 0.5, 2)
            z0 = floor_z
            z1 = min(floor_z + rng.uniform(0.9, 2.0), ceil_z - 0.2)
        else:
            half = rng.uniform(0.06, 0.25, 2)
            z0 = floor_z
            for bl, bh in zip(blo, bhi):       # rest on the highest box below the point
                if bl[0] <= c[0] <= bh[0] and bl[1] <= c[1] <= bh[1] and bh[2] <= c[2] + 0.1:
                    z0 = max(z0, bh[2])
            z1 = z0 + rng.uniform(0.1, 0.45)
        b_lo = np.array([c[0] - half[0], c[1] - half[1], z0])
        b_hi = np.array([c[0] + half[0], c[1] + half[1], z1])
        # keep inside the room (shift against the wall, then clip)
        for a in range(2):
            if b_lo[a] < room_lo[a]:
                b_hi[a] += room_lo[a] - b_lo[a]
                b_lo[a] = room_lo[a]
            if b_hi[a] > room_hi[a]:
                b_lo[a] -= b_hi[a] - room_hi[a]
                b_hi[a] = room_hi[a]
        b_lo[:2] = np.maximum(b_lo[:2], room_lo[:2])
        b_hi[:2] = np.minimum(b_hi[:2], room_hi[:2])
        ok = False
        for _ in range(8):                     # shrink until clear of every camera position
            if np.any(b_hi - b_lo < 0.06) or b_hi[2] <= b_lo[2] + 0.05:
                break
            if _point_box_distance(allp, b_lo, b_hi).min() >= clearance:
                ok = True
                break
            ctr = 0.5 * (b_lo + b_hi)
            b_lo[:2] = ctr[:2] - 0.8 * (ctr[:2] - b_lo[:2])
            b_hi[:2] = ctr[:2] + 0.8 * (b_hi[:2] - ctr[:2])
            b_hi[2] = b_lo[2] + 0.75 * (b_hi[2] - b_lo[2])
        if not ok:
            continue
        if any(np.all(b_lo < h - 1e-3) and np.all(b_hi > l + 1e-3) for l, h in zip(blo, bhi)):
            continue                           # no interpenetrating boxes
        blo.append(b_lo)
        bhi.append(b_hi)
        kinds.append(kind)
    info = {"up_world": [float(x) for x in up_v], "box_kinds": {k: kinds.count(k) for k in
                                                                 sorted(set(kinds))},
            "min_camera_box_distance_m": round(float(min(
                [_point_box_distance(allp, l, h).min() for l, h in zip(blo, bhi)] or [np.inf])), 3)}
    return make_scene(room_lo, room_hi, np.array(blo).reshape(-1, 3), np.array(bhi).reshape(-1, 3),
                      seed=seed, T_room_world=T_rw, textures=textures, info=info)


# =================================================================== rendering
def _camera_rays(scene: Scene, K: Intrinsics, device=None) -> torch.Tensor:
    """(H, W, 3) camera-frame ray directions with z = 1 through the pixel centres."""
    key = ("rays", K.fx, K.fy, K.cx, K.cy, K.width, K.height, K.distortion_model,
           tuple(K.distortion), str(torch.device(device or "cpu")))
    if key in scene._cache:
        return scene._cache[key]
    v, u = np.mgrid[0:K.height, 0:K.width].astype(np.float64)
    if K.has_distortion:
        pts = np.stack([u, v], -1).reshape(-1, 1, 2)
        D = np.asarray(K.distortion, np.float64)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        if K.distortion_model == "equidistant":
            xy = cv2.fisheye.undistortPoints(pts, K.K, D[:4], criteria=crit)
        else:
            xy = cv2.undistortPoints(pts, K.K, D, criteria=crit)
        xy = xy.reshape(K.height, K.width, 2)
        x, y = xy[..., 0], xy[..., 1]
    else:
        x, y = (u - K.cx) / K.fx, (v - K.cy) / K.fy
    rays = torch.from_numpy(np.stack([x, y, np.ones_like(x)], -1).astype(np.float32))
    rays = rays.to(torch.device(device or "cpu"))
    scene._cache[key] = rays
    return rays


def _sample_trilinear(t, tex, lev, u, v):
    """Trilinear mip-mapped texture lookup: texture ``tex`` (per pixel) at level-0 texel
    coordinates (u, v) (texel centres at +0.5), continuous mip level ``lev``."""
    l0 = lev.floor()
    l1 = (l0 + 1).clamp(max=TEX_LEVELS - 1)
    pts = []
    for l in (l0, l1):
        scale = torch.exp2(-l)
        Sl = TEX_SIZE * scale
        x = torch.remainder(u * scale - 0.5, Sl)
        y = torch.remainder(v * scale - 0.5, Sl)
        o = t["org"][tex * TEX_LEVELS + l.to(torch.int64)]
        pts.append(torch.stack([o[:, 0] + x, o[:, 1] + y], -1))
    atlas = t["atlas"]
    Ha, Wa = atlas.shape[-2:]
    g = torch.stack(pts, 0)                                    # (2, P, 2) atlas pixels
    g = g * torch.tensor([2.0 / (Wa - 1), 2.0 / (Ha - 1)], device=g.device) - 1.0
    c = torch.nn.functional.grid_sample(atlas, g[None], mode="bilinear",
                                        padding_mode="border", align_corners=True)[0]
    w = (lev - l0)[None]
    return (c[:, 0] + (c[:, 1] - c[:, 0]) * w).T                # (P, 3) in 0..255


def _render_room(scene: Scene, pose_world: np.ndarray, K: Intrinsics, device=None):
    """Core ray caster. Returns (rgb float32 (H,W,3) in [0,255+], z-depth (H,W)) torch
    tensors on ``device`` (default CPU)."""
    dev = torch.device(device or "cpu")
    t = scene._torch(dev)
    T_rc = scene.T_room_world @ np.asarray(pose_world, np.float64)
    R = torch.from_numpy(T_rc[:3, :3].astype(np.float32)).to(dev)
    o = torch.from_numpy(T_rc[:3, 3].astype(np.float32)).to(dev)
    rays = _camera_rays(scene, K, dev)
    H, W = rays.shape[:2]
    d = rays @ R.T                                       # (H, W, 3) room-frame, camera z = 1
    d = torch.where(d == 0, torch.full_like(d, 1e-12), d)
    inv = 1.0 / d
    # room interior: exit distance, the face is the axis where the ray leaves first
    tmax = torch.maximum((t["room_lo"] - o) * inv, (t["room_hi"] - o) * inv)
    depth, ax = tmax.min(-1)
    sid = 2 * ax + (d.gather(-1, ax[..., None])[..., 0] > 0).long()
    # boxes: slab test, restricted to each box's projected bounding rectangle
    Rn, on = T_rc[:3, :3], T_rc[:3, 3]
    for b in range(scene.n_boxes):
        lo_b, hi_b = scene.boxes_lo[b], scene.boxes_hi[b]
        corners = np.array([[x, y, z] for x in (lo_b[0], hi_b[0]) for y in (lo_b[1], hi_b[1])
                            for z in (lo_b[2], hi_b[2])])
        Xc = (corners - on) @ Rn
        zc = Xc[:, 2]
        if np.all(zc <= 1e-3):
            continue
        if np.any(zc <= 1e-3) or K.has_distortion:
            v0, v1, u0, u1 = 0, H, 0, W
        else:
            u = K.fx * Xc[:, 0] / zc + K.cx
            v = K.fy * Xc[:, 1] / zc + K.cy
            u0, u1 = max(int(math.floor(u.min())) - 1, 0), min(int(math.ceil(u.max())) + 2, W)
            v0, v1 = max(int(math.floor(v.min())) - 1, 0), min(int(math.ceil(v.max())) + 2, H)
            if u0 >= u1 or v0 >= v1:
                continue
        inv_s = inv[v0:v1, u0:u1]
        t1 = (t["boxes_lo"][b] - o) * inv_s
        t2 = (t["boxes_hi"][b] - o) * inv_s
        tn, axb = torch.minimum(t1, t2).max(-1)
        tf = torch.maximum(t1, t2).min(-1).values
        dep = depth[v0:v1, u0:u1]
        hit = (tn <= tf) & (tn > 1e-4) & (tn < dep)
        if not bool(hit.any()):
            continue
        side = (d[v0:v1, u0:u1].gather(-1, axb[..., None])[..., 0] < 0).long()
        depth[v0:v1, u0:u1] = torch.where(hit, tn, dep)
        sid[v0:v1, u0:u1] = torch.where(hit, 6 + 6 * b + 2 * axb + side, sid[v0:v1, u0:u1])
    # ---- shading (flattened)
    dd = d.reshape(-1, 3)
    z = depth.reshape(-1)
    s = sid.reshape(-1)
    X = o + z[:, None] * dd
    tf = t["tabf"][s]                                    # (P, 18) per-surface floats
    ti = t["tabi"][s]                                    # (P, 4) uax, vax, axis, texture
    Xu = X.gather(1, ti[:, 0:1])[:, 0]
    Xv = X.gather(1, ti[:, 1:2])[:, 0]
    dens = tf[:, 2]
    u = Xu * tf[:, 0] * dens + tf[:, 3]
    v = Xv * tf[:, 1] * dens + tf[:, 4]
    # mip level from the pixel footprint on the surface (geometric mean of its axes)
    dn = dd.norm(dim=1)
    cos = (dd.gather(1, ti[:, 2:3])[:, 0].abs() / dn).clamp_min(0.05)
    f = 0.5 * (abs(K.fx) + abs(K.fy))
    foot = z * dn * (1.0 / f) * dens / cos.sqrt()
    lev = torch.log2(foot.clamp_min(1e-6)).clamp(0, TEX_LEVELS - 1)
    albedo = _sample_trilinear(t, ti[:, 3], lev, u, v) * tf[:, 15:18]
    # Lambertian: ambient + directional ("window") + point light near the ceiling
    n = tf[:, 5:8]
    lp = t["light_pos"] - X
    ldist = lp.norm(dim=1).clamp_min(1e-3)
    point = ((n * lp).sum(1) / ldist).clamp_min(0) / (1 + (ldist / 3.0) ** 2)
    direc = (n * t["light_dir"]).sum(1).clamp_min(0)
    # ambient occlusion near face edges (room corners, box bevels)
    edge = torch.minimum(torch.minimum(Xu - tf[:, 10], tf[:, 11] - Xu),
                         torch.minimum(Xv - tf[:, 13], tf[:, 14] - Xv)).clamp_min(0)
    ao = 1 - tf[:, 8] * torch.exp(-edge / tf[:, 9])
    # contact shadows of the boxes standing on the floor (baked map)
    fl = (s == 4).nonzero()[:, 0]
    if scene.n_boxes and len(fl):
        g = t["floor_grid"]
        xy = (X[fl, :2] - g[:2]) * g[2:] - 1.0
        sh = torch.nn.functional.grid_sample(t["floor_shadow"], xy[None, None], mode="bilinear",
                                             padding_mode="border", align_corners=True)[0, 0, 0]
        ao[fl] = ao[fl] * sh
    amb = ((0.4 + 0.25 * direc) * ao)[:, None] * torch.tensor([0.97, 0.99, 1.03], device=dev)
    pnt = (0.6 * point * ao)[:, None] * torch.tensor([1.03, 0.98, 0.9], device=dev)
    rgb = albedo * (amb + pnt)
    return rgb.reshape(H, W, 3), depth


def render_frame(scene: Scene, pose: np.ndarray, intrinsics: Intrinsics,
                 as_float: bool = False, device=None) -> Tuple[np.ndarray, np.ndarray]:
    """Render one clean view. ``pose``: 4x4 camera-to-world in the trajectory's world frame.

    Returns (rgb H x W x 3 uint8 RGB — or float32 in [0, 255] with ``as_float`` —, depth
    H x W float32 z-depth in metres), numpy; ``device`` (torch) does the work."""
    with torch.no_grad():
        rgb, depth = _render_room(scene, pose, intrinsics, device)
    rgb = rgb.cpu().numpy()
    if not as_float:
        rgb = np.clip(rgb + 0.5, 0, 255).astype(np.uint8)
    return rgb, depth.cpu().numpy().astype(np.float32)


# ===================================================================== realism
def _smooth_signal(rng, n_terms: int = 3) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    periods = rng.uniform(3.0, 14.0, n_terms)
    phases = rng.uniform(0, 2 * np.pi, n_terms)
    amps = rng.uniform(0.5, 1.0, n_terms)
    return periods, phases, amps / amps.sum()


def _eval_signal(sig, t: float) -> float:
    periods, phases, amps = sig
    return float(np.sum(amps * np.sin(2 * np.pi * t / periods + phases)))


class CameraEffects:
    """Per-frame photometric camera model applied to a float render in [0, 255]."""

    def __init__(self, opts: RealismOptions, K: Intrinsics, seed: int):
        self.opts, self.seed = opts, int(seed)
        rng = np.random.default_rng([self.seed, 17])
        self.gain_sig, self.off_sig = _smooth_signal(rng), _smooth_signal(rng)
        v, u = np.mgrid[0:K.height, 0:K.width].astype(np.float32)
        r2 = (u - K.cx) ** 2 + (v - K.cy) ** 2
        r2max = max((x - K.cx) ** 2 + (y - K.cy) ** 2 for x in (0, K.width - 1)
                    for y in (0, K.height - 1))
        self.vig = (1.0 - opts.vignetting * r2 / r2max).astype(np.float32)[..., None]

    def gain_offset(self, t_rel: float) -> Tuple[float, float]:
        A = self.opts.auto_exposure
        if A <= 0:
            return 1.0, 0.0
        return 1.0 + A * _eval_signal(self.gain_sig, t_rel), 0.25 * A * 255.0 * _eval_signal(
            self.off_sig, t_rel)

    def __call__(self, img: np.ndarray, index: int, t_rel: float) -> np.ndarray:
        o = self.opts
        x = img
        if o.vignetting > 0:
            x = x * self.vig
        if o.auto_exposure > 0:
            g, b = self.gain_offset(t_rel)
            x = x * g + b
        if o.noise > 0:
            rng = np.random.default_rng([self.seed, 23, int(index)])
            # read noise std = noise/2; shot noise variance grows linearly with intensity
            var = (0.25 * o.noise ** 2) + (0.75 * o.noise ** 2 / 127.5) * np.clip(x, 0, 255)
            x = x + rng.standard_normal(x.shape, dtype=np.float32) * np.sqrt(var)
        out = np.clip(x + 0.5, 0, 255).astype(np.uint8)
        if o.jpeg > 0:
            ok, enc = cv2.imencode(".jpg", cv2.cvtColor(out, cv2.COLOR_RGB2BGR),
                                   [int(cv2.IMWRITE_JPEG_QUALITY), int(o.jpeg)])
            out = cv2.cvtColor(cv2.imdecode(enc, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        return out


# ============================================================ the generator
def depth_to_png16(depth: np.ndarray) -> np.ndarray:
    """Metres -> uint16 at 5000/m; 0 where missing or beyond 13.1 m (the uint16 range)."""
    d = np.nan_to_num(np.asarray(depth, np.float64), nan=0.0, posinf=0.0) * DEPTH_SCALE
    d = np.where((d > 0) & (d <= 65535), np.round(d), 0)
    return d.astype(np.uint16)


def _prepare_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise SynthError(f"--out {out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise SynthError(f"output directory {out} is not empty (use --overwrite to replace "
                             "a previous synthetic sequence there)")
        for sub in ("rgb", "depth"):
            if (out / sub).is_dir():
                shutil.rmtree(out / sub)
        for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.yaml"):
            if (out / name).is_file():
                (out / name).unlink()
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)


def resolve_realism(realism: Optional[str] = None, **overrides) -> RealismOptions:
    """Preset (``clean`` | ``realistic``) with explicit options (not None) on top."""
    name = realism or "clean"
    if name not in REALISM_PRESETS:
        raise SynthError(f"unknown --realism '{name}' (use one of {sorted(REALISM_PRESETS)})")
    d = asdict(REALISM_PRESETS[name])
    for k, v in overrides.items():
        if k not in d:
            raise SynthError(f"unknown realism option '{k}'")
        if v is not None:
            d[k] = v
    return RealismOptions(**d)


@dataclass
class SequencePlan:
    """Everything a sequence is rendered from (what ``generate_sequence`` writes out)."""
    stamps: np.ndarray              # (N,) frame stamps, seconds
    poses: np.ndarray               # (N, 4, 4) camera-to-world at the stamps (world frame)
    intrinsics: Intrinsics
    realism: RealismOptions
    scene: Scene
    interpolator: PoseInterpolator
    fps: float
    seed: int
    record: Dict                    # generation options (written to intrinsics.yaml)
    device: str = "cpu"             # torch device used for rendering

    def render(self, k: int, effects: Optional["CameraEffects"] = None
               ) -> Tuple[np.ndarray, np.ndarray]:
        """Frame ``k`` exactly as written: (rgb uint8 with the realism effects, clean depth)."""
        effects = effects or CameraEffects(self.realism, self.intrinsics, self.seed)
        with torch.no_grad():
            rgb, depth = _render_room(self.scene, self.poses[k], self.intrinsics, self.device)
            n_sub = self.realism.motion_blur
            if n_sub > 1:   # sub-exposures over [t - E, t]; the last one is the frame's pose
                E = self.realism.exposure_ms * 1e-3
                sub_t = self.stamps[k] - E * (1.0 - np.arange(n_sub - 1) / (n_sub - 1))
                acc = rgb.clone()
                for T_sub in self.interpolator(sub_t):
                    acc += _render_room(self.scene, T_sub, self.intrinsics, self.device)[0]
                rgb = acc / n_sub
        img = effects(rgb.cpu().numpy(), k, float(self.stamps[k] - self.stamps[0]))
        return img, depth.cpu().numpy().astype(np.float32)


def _resolve_device(device) -> str:
    name = str(device or "cpu")
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise SynthError(f"unknown --device '{name}' (cpu, cuda, cuda:N or auto)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SynthError("--device cuda requested but CUDA is not available")
    return str(dev)


def _resolve_intrinsics(size, intrinsics, fov) -> Intrinsics:
    if intrinsics is None:
        w, h = parse_size("640x480" if size is None else size)
        return default_intrinsics(w, h, fov)
    if fov is not None:
        raise SynthError("give either --fov or --intrinsics, not both")
    K = intrinsics if isinstance(intrinsics, Intrinsics) else Intrinsics.from_yaml(intrinsics)
    if K.width <= 0 or K.height <= 0 or K.fx == 0 or K.fy == 0:
        raise SynthError(f"intrinsics need positive width/height and non-zero fx, fy: {K}")
    if K.has_distortion and K.distortion_model not in ("plumb_bob", "rational_polynomial",
                                                       "equidistant"):
        raise SynthError(f"unsupported distortion model '{K.distortion_model}' "
                         "(plumb_bob, rational_polynomial or equidistant)")
    if size is not None:
        w, h = parse_size(size)
        if (w, h) != (K.width, K.height):
            sx, sy = w / K.width, h / K.height
            if abs(sx - sy) > 1e-3 * max(sx, sy):
                raise SynthError(f"--size {w}x{h} has another aspect ratio than the intrinsics "
                                 f"({K.width}x{K.height}); omit --size to use theirs")
            K = K.scaled(sx, sy)
    return K


def plan_sequence(trajectory, frames: int, size="640x480", *, fps: float = 30.0,
                  start: float = 0.0, fmt: str = "auto", kitti_dt: float = 0.1, seed: int = 0,
                  textures=None, fov: Optional[float] = None, intrinsics=None, up=None,
                  realism: Optional[str] = None, motion_blur: Optional[int] = None,
                  exposure_ms: Optional[float] = None, auto_exposure: Optional[float] = None,
                  vignetting: Optional[float] = None, noise: Optional[float] = None,
                  jpeg: Optional[int] = None, device: str = "cpu",
                  warn: bool = True) -> SequencePlan:
    """Validate the options, sample the frame stamps and poses, fit the scene (no rendering).
    Same options as :func:`generate_sequence`."""
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames <= 0:
        raise SynthError(f"--frames must be a positive integer, got {frames}")
    frames = int(frames)
    device = _resolve_device(device)
    if not (isinstance(fps, (int, float)) and 0 < fps <= 1000):
        raise SynthError(f"--fps must be in (0, 1000], got {fps}")
    fps = float(fps)
    K = _resolve_intrinsics(size, intrinsics, fov)
    ropts = resolve_realism(realism, motion_blur=motion_blur, exposure_ms=exposure_ms,
                            auto_exposure=auto_exposure, vignetting=vignetting, noise=noise,
                            jpeg=jpeg).validate(fps)
    ts, P, fmt_used = load_trajectory(trajectory, fmt=fmt, kitti_dt=kitti_dt,
                                      min_duration=start + frames / fps + 1.0, seed=seed)
    interp = PoseInterpolator(ts, P)
    stamps = frame_stamps(interp.t_start, interp.t_end, frames, fps, start)
    poses = interp(stamps)
    gaps = interp.gap_at(stamps)
    n_gap = int((gaps > GAP_WARN_S).sum())
    if n_gap and warn:
        a, b = interp.longest_gap_free()
        print(f"warning: {n_gap} of {frames} frames fall in ground-truth gaps longer than "
              f"{GAP_WARN_S:g} s (longest {gaps.max():.2f} s); their poses are interpolated "
              f"linearly across the gap. The longest gap-free stretch is {a:.1f}-{b:.1f} s "
              f"(--start {a:.1f}, at most {int((b - a) * fps) + 1} frames)", file=sys.stderr)
    # every position the camera passes through, exposure windows included, stays clear of boxes
    dense = interp.positions_between(max(stamps[0] - 1.0 / fps, interp.t_start), stamps[-1])
    scene = build_scene(poses, seed=seed, textures=textures, up=up, fmt=fmt_used,
                        positions=dense)
    src = "array" if isinstance(trajectory, (tuple, list)) else str(trajectory)
    record = {
        "tool": "splat-slam-synth", "trajectory": src, "trajectory_format": fmt_used,
        "frames": frames, "fps": fps, "start": float(start), "seed": int(seed),
        "size": [K.width, K.height], "fov": fov,
        "intrinsics_file": None if intrinsics is None or isinstance(intrinsics, Intrinsics)
        else str(intrinsics),
        "textures": None if textures is None else str(textures),
        "up": None if up is None else (up if isinstance(up, str) else [float(x) for x in up]),
        "realism": realism or "clean", "realism_options": asdict(ropts), "device": device,
        "first_stamp": float(stamps[0]), "last_stamp": float(stamps[-1]),
        "gt_gap_frames": n_gap, "gt_longest_gap_s": round(float(gaps.max()), 4),
        "gt_duplicates_dropped": interp.dropped_duplicates,
        "scene": scene.summary(),
    }
    return SequencePlan(stamps, poses, K, ropts, scene, interp, fps, int(seed), record, device)


def generate_sequence(trajectory, frames: int, size="640x480", out=None, *,
                      overwrite: bool = False, threads: Optional[int] = 1,
                      progress: bool = True, stats: Optional[Dict] = None,
                      **options) -> Path:
    """Render a TUM-layout RGB-D sequence into ``out``; returns the output folder.

    ``trajectory``: a TUM/KITTI/EuRoC file, ``"builtin"`` or ``(timestamps, poses)``.
    ``frames`` camera frames are sampled at ``fps`` (default 30) from the trajectory's first
    stamp + ``start`` seconds (poses interpolated: linear translation, SLERP rotation).
    ``size``: ``'WxH'`` or (W, H); None with ``intrinsics`` (YAML path or Intrinsics) keeps
    the file's size. Other options (see :func:`plan_sequence`): fps, start, fmt, kitti_dt,
    seed, textures, fov, intrinsics, up, realism ('clean' | 'realistic'), motion_blur,
    exposure_ms, auto_exposure, vignetting, noise, jpeg, device ('cpu' | 'cuda' | 'auto').
    ``threads``: torch CPU threads while rendering (1 by default: fastest on a shared
    2-core machine; None = leave torch's setting). ``stats`` (a dict) receives timings.
    """
    if out is None:
        raise SynthError("an output directory is required (--out)")
    out = Path(out)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not overwrite)):
        _prepare_out(out, overwrite)          # raises the clear error before any work
    t_setup = time.perf_counter()
    plan = plan_sequence(trajectory, frames, size, **options)
    t_setup = time.perf_counter() - t_setup
    _prepare_out(out, overwrite)
    names = [f"{t:.6f}.png" for t in plan.stamps]
    effects = CameraEffects(plan.realism, plan.intrinsics, plan.seed)
    it = range(len(plan.stamps))
    if progress:
        from tqdm import tqdm
        it = tqdm(it, desc="synth", unit="frame")
    old_threads = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    t_render = time.perf_counter()
    try:
        for k in it:
            img, depth = plan.render(k, effects)
            cv2.imwrite(str(out / "rgb" / names[k]), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(out / "depth" / names[k]), depth_to_png16(depth))
    finally:
        torch.set_num_threads(old_threads)
    t_render = time.perf_counter() - t_render
    # ---- index files, ground truth, intrinsics
    src_name = Path(plan.record["trajectory"]).name
    for kind, label in (("rgb", "color images"), ("depth", "depth maps")):
        with open(out / f"{kind}.txt", "w") as fh:
            fh.write(f"# {label}\n# file: 'splat-slam-synth {src_name}'\n# timestamp filename\n")
            for t, n in zip(plan.stamps, names):
                fh.write(f"{t:.6f} {kind}/{n}\n")
    write_tum(out / "groundtruth.txt", plan.stamps, plan.poses)
    plan.intrinsics.to_yaml(out / "intrinsics.yaml", depth_scale=DEPTH_SCALE, fps=plan.fps,
                            generation=plan.record)
    if stats is not None:
        n = len(plan.stamps)
        stats.update(setup_s=t_setup, render_s=t_render, s_per_frame=t_render / n, frames=n,
                     size=[plan.intrinsics.width, plan.intrinsics.height],
                     boxes=plan.scene.n_boxes)
    return out
