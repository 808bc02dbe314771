"""Planning and writing a synthetic TUM-layout RGB-D sequence (see the package docstring)."""
from __future__ import annotations

import math
import shutil
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np
import torch
from tqdm import tqdm

from splat_slam_synth.camera import CameraEffects
from splat_slam_synth.options import (DEPTH_SCALE, GAP_WARN_S, RealismOptions, SynthError,
                                     check_scene, default_intrinsics, parse_size,
                                     resolve_realism)
from splat_slam_synth.render import render_view
from splat_slam_synth.scene import Scene
from splat_slam_synth.variants import build_scene
from splat_slam_synth.trajectories import PoseInterpolator, frame_stamps, load_trajectory
from splat_slam_ros.io.trajectory_io import write_tum
from splat_slam_ros.runtime import DeviceError, limit_threads, resolve_device
from splat_slam_ros.types import Frame, Intrinsics


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
        """Frame ``k`` exactly as written: (rgb uint8 with the realism effects, clean depth).
        Depth is always the global-shutter view at the frame's pose (the ground truth)."""
        effects = effects or CameraEffects(self.realism, self.intrinsics, self.seed)
        with torch.no_grad():
            rgb, depth = render_view(self.scene, self.poses[k], self.intrinsics, self.device)
            n_sub = self.realism.motion_blur
            if self.realism.rolling_shutter_ms > 0:
                rgb = self._render_rolling(k)
            elif n_sub > 1:   # sub-exposures over [t - E, t]; the last one is the frame's pose
                E = self.realism.exposure_ms * 1e-3
                sub_t = self.stamps[k] - E * (1.0 - np.arange(n_sub - 1) / (n_sub - 1))
                acc = rgb.clone()
                for T_sub in self.interpolator(sub_t):
                    acc += render_view(self.scene, T_sub, self.intrinsics, self.device)[0]
                rgb = acc / n_sub
        img = effects(rgb.cpu().numpy(), k, float(self.stamps[k] - self.stamps[0]))
        return img, depth.cpu().numpy().astype(np.float32)

    def _render_rolling(self, k: int) -> torch.Tensor:
        """Rolling-shutter RGB of frame ``k``: each row band rendered (with its motion-blur
        sub-exposures) at the readout time of its centre row (:func:`rolling_shutter_bands`)."""
        K, ro = self.intrinsics, self.realism
        out = torch.empty((K.height, K.width, 3), dtype=torch.float32,
                          device=torch.device(self.device))
        n_sub, E = ro.motion_blur, ro.exposure_ms * 1e-3
        for r0, r1, dt in rolling_shutter_bands(K.height, ro.rolling_shutter_ms):
            t_row = self.stamps[k] - dt
            sub_t = np.array([t_row]) if n_sub == 1 else \
                t_row - E * (1.0 - np.arange(n_sub) / (n_sub - 1))
            Kb = replace(K, cy=K.cy - r0, height=r1 - r0)     # the band's rows only
            acc = None
            for T_sub in self.interpolator(sub_t):
                x = render_view(self.scene, T_sub, Kb, self.device)[0]
                acc = x if acc is None else acc + x
            out[r0:r1] = acc / n_sub
        return out

    def frames(self, n: Optional[int] = None) -> List[Frame]:
        """The first ``n`` frames (all by default) rendered in memory as the tracker's input:
        :class:`Frame` (index, stamp, the RGB image exactly as written, intrinsics)."""
        effects = CameraEffects(self.realism, self.intrinsics, self.seed)
        return [Frame(k, float(self.stamps[k]), self.render(k, effects)[0], self.intrinsics)
                for k in range(len(self.stamps) if n is None else n)]


def rolling_shutter_bands(height: int, readout_ms: float, max_step_ms: float = 0.5
                          ) -> List[Tuple[int, int, float]]:
    """Row bands of a rolling-shutter frame: (first row, end row, seconds before the frame
    stamp). Convention: row ``r`` is read out (its exposure ends) ``readout * (1 - r/(H-1))``
    before the stamp, so the top row at ``stamp - readout`` and the bottom row at the stamp
    (the ground-truth pose); each band is rendered at the time of its centre row, with bands
    at most ``max_step_ms`` of readout apart (and one row at least)."""
    H = int(height)
    n = int(min(H, max(2, math.ceil(readout_ms / max_step_ms))))
    edges = np.round(np.linspace(0, H, n + 1)).astype(int)
    span = max(H - 1, 1)
    return [(int(a), int(b), readout_ms * 1e-3 * (1.0 - 0.5 * (a + b - 1) / span))
            for a, b in zip(edges[:-1], edges[1:]) if b > a]


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
                  jpeg: Optional[int] = None, rolling_shutter_ms: Optional[float] = None,
                  scene: Optional[str] = None, device: str = "cpu",
                  warn: bool = True) -> SequencePlan:
    """Validate the options, sample the frame stamps and poses, fit the scene (no rendering).
    Same options as :func:`generate_sequence`."""
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames <= 0:
        raise SynthError(f"--frames must be a positive integer, got {frames}")
    frames = int(frames)
    try:
        device = str(resolve_device(device, "--device"))
    except DeviceError as e:
        raise SynthError(str(e)) from None
    if not (isinstance(fps, (int, float)) and 0 < fps <= 1000):
        raise SynthError(f"--fps must be in (0, 1000], got {fps}")
    fps = float(fps)
    scene_name = check_scene(scene)
    K = _resolve_intrinsics(size, intrinsics, fov)
    ropts = resolve_realism(realism, motion_blur=motion_blur, exposure_ms=exposure_ms,
                            auto_exposure=auto_exposure, vignetting=vignetting, noise=noise,
                            jpeg=jpeg, rolling_shutter_ms=rolling_shutter_ms
                            ).validate(fps, realism)
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
    lead = 1.0 / fps
    if ropts.rolling_shutter_ms > 0:     # the top rows are exposed up to readout + E earlier
        lead = max(lead, (ropts.rolling_shutter_ms + ropts.exposure_ms) * 1e-3)
    dense = interp.positions_between(max(stamps[0] - lead, interp.t_start), stamps[-1])
    scene = build_scene(poses, seed=seed, textures=textures, up=up, fmt=fmt_used,
                        positions=dense, scene=scene_name)
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
    seed, textures, fov, intrinsics, up, scene (``options.SCENES``: 'room' (default),
    'low_texture', 'tiled', 'repetitive', 'thin', 'deep'), realism ('clean' | 'realistic' |
    'harsh'), motion_blur, exposure_ms, auto_exposure, vignetting, noise, jpeg,
    rolling_shutter_ms (row readout time, see :func:`rolling_shutter_bands`), device
    ('cpu' | 'cuda' | 'auto').
    ``threads``: torch/OpenCV CPU threads while rendering (1 by default: fastest on a shared
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
        it = tqdm(it, desc="synth", unit="frame")
    t_render = time.perf_counter()
    with limit_threads(threads or 0):
        for k in it:
            img, depth = plan.render(k, effects)
            cv2.imwrite(str(out / "rgb" / names[k]), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(out / "depth" / names[k]), depth_to_png16(depth))
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
