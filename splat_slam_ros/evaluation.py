"""Evaluation metrics as pure functions: trajectory (ATE, RPE) and rendering (PSNR, SSIM,
LPIPS, depth L1).

The trajectory metrics follow the reference evaluation (the evo library): poses are
associated by nearest timestamp, the estimate is aligned to the ground truth with
Umeyama's method (Sim(3) by default, the monocular case) over the full matched
trajectory, and the translational error is reported in centimetres. File formats are
read by :mod:`splat_slam_ros.io.trajectory_io`.

Rendering metrics take images in [0, 1] (float, torch or numpy, H x W x 3 or 3 x H x W;
uint8 images are divided by 255). PSNR can be computed after per-channel exposure
compensation (:func:`exposure_compensate`), as in the reference evaluation.
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from splat_slam_ros.geometry import apply_sim3_to_poses, se3_inverse, so3_log


class MetricError(ValueError):
    """A metric cannot be computed from the given inputs (a user-facing, one-line reason)."""


ALIGN_MODES = ("sim3", "se3", "none")
RPE_UNITS = ("frames", "meters")


# ------------------------------------------------------------------ helpers
def _np64(x, name: str) -> np.ndarray:
    if torch.is_tensor(x):
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise MetricError(f"{name} must be numeric array-like") from None


def _check_traj(ts, poses, name: str) -> Tuple[np.ndarray, np.ndarray]:
    ts = _np64(ts, f"{name} timestamps").reshape(-1)
    P = _np64(poses, f"{name} poses")
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise MetricError(f"{name} poses must have shape (N, 4, 4), got {tuple(P.shape)}")
    if len(ts) != len(P):
        raise MetricError(f"{name}: {len(ts)} timestamps but {len(P)} poses")
    if not (np.all(np.isfinite(ts)) and np.all(np.isfinite(P))):
        raise MetricError(f"{name} trajectory contains non-finite values")
    return ts, P


def _stats(e: np.ndarray) -> Dict[str, float]:
    return dict(rmse=float(np.sqrt(np.mean(e ** 2))), mean=float(np.mean(e)),
                median=float(np.median(e)), std=float(np.std(e)),
                min=float(np.min(e)), max=float(np.max(e)), sse=float(np.sum(e ** 2)))


def _range(ts: np.ndarray) -> str:
    if len(ts) == 0:
        return "(empty)"
    return f"[{np.min(ts):.6f}, {np.max(ts):.6f}] s ({len(ts)} poses)"


def _rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices -> (N,) rotation angles in degrees."""
    w = so3_log(torch.from_numpy(np.ascontiguousarray(R, dtype=np.float64)))
    return np.degrees(w.norm(dim=-1).numpy())


# -------------------------------------------------------------- association
def associate(ts_a, ts_b, max_diff: float = 0.02,
              offset: float = 0.0) -> Tuple[np.ndarray, np.ndarray]:
    """Match timestamps one-to-one by nearest time, like evo/TUM ``associate.py``.

    ``ts_b + offset`` is compared with ``ts_a``; candidate pairs within ``max_diff``
    seconds are accepted greedily from the smallest difference on, so every stamp
    is used at most once. Returns index arrays ``(idx_a, idx_b)`` sorted by ``idx_a``.
    Inputs need not be sorted.
    """
    a = _np64(ts_a, "timestamps").reshape(-1)
    b = _np64(ts_b, "timestamps").reshape(-1) + float(offset)
    if max_diff < 0:
        raise MetricError(f"max_diff must be >= 0, got {max_diff}")
    empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    if len(a) == 0 or len(b) == 0:
        return empty
    ob = np.argsort(b, kind="stable")
    bs = b[ob]
    lo = np.searchsorted(bs, a - max_diff, side="left")
    hi = np.searchsorted(bs, a + max_diff, side="right")
    counts = hi - lo
    total = int(counts.sum())
    if total == 0:
        return empty
    if total > 5_000_000:
        raise MetricError(f"max_diff {max_diff} s is far larger than the sampling interval "
                          f"({total} candidate pairs); use a smaller --max-diff")
    ia = np.repeat(np.arange(len(a)), counts)
    starts = np.repeat(lo - np.cumsum(counts) + counts, counts)  # per-a start, offset by rank
    jb = starts + np.arange(total)
    diff = np.abs(bs[jb] - a[ia])
    order = np.lexsort((jb, ia, diff))          # smallest difference first, ties by index
    used_a = np.zeros(len(a), bool)
    used_b = np.zeros(len(b), bool)
    out_a, out_b = [], []
    for k in order:
        i, j = ia[k], jb[k]
        if used_a[i] or used_b[j]:
            continue
        used_a[i] = used_b[j] = True
        out_a.append(i)
        out_b.append(ob[j])
    out_a = np.asarray(out_a, dtype=np.int64)
    out_b = np.asarray(out_b, dtype=np.int64)
    s = np.argsort(out_a, kind="stable")
    return out_a[s], out_b[s]


# ---------------------------------------------------------------- alignment
def umeyama_alignment(src, dst, with_scale: bool = True) -> Tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~= s R src + t`` (Umeyama 1991).

    ``src``, ``dst``: (N, 3) corresponding points. Returns ``(s, R, t)``; ``s = 1``
    when ``with_scale`` is False (SE(3) alignment).
    """
    x = _np64(src, "src")
    y = _np64(dst, "dst")
    if x.ndim != 2 or x.shape != y.shape or x.shape[1] != 3:
        raise MetricError(f"umeyama_alignment needs two (N, 3) arrays of equal shape, "
                          f"got {x.shape} and {y.shape}")
    n = len(x)
    if n < 3:
        raise MetricError(f"alignment needs at least 3 corresponding points, got {n}")
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    var_x = float((xc ** 2).sum() / n)
    cov = yc.T @ xc / n
    U, d, Vt = np.linalg.svd(cov)
    if var_x <= 0 or d[0] <= 0 or d[1] <= 1e-12 * d[0]:
        raise MetricError("the trajectory positions are (nearly) identical or collinear, so the "
                          "rotation of the alignment is undefined; use align 'none'")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0                          # keep a proper rotation (no reflection)
    R = U @ S @ Vt
    s = float(np.trace(np.diag(d) @ S) / var_x) if with_scale else 1.0
    t = my - s * R @ mx
    return s, R, t


def align_poses(poses, s: float, R, t) -> np.ndarray:
    """Apply the similarity ``x -> s R x + t`` to camera-to-world poses (N, 4, 4)."""
    P = torch.from_numpy(_np64(poses, "poses"))
    return apply_sim3_to_poses(float(s), torch.from_numpy(_np64(R, "R")),
                               torch.from_numpy(_np64(t, "t")), P).numpy()


def _associate_checked(gt_ts, est_ts, max_diff, offset):
    ia, ib = associate(gt_ts, est_ts, max_diff, offset)
    if len(ia) < 3:
        raise MetricError(
            f"only {len(ia)} poses associate within max_diff={max_diff} s (need >= 3); "
            f"ground-truth stamps {_range(gt_ts)}, estimate stamps {_range(est_ts)}"
            + (f" (offset {offset} s)" if offset else ""))
    return ia, ib


def _alignment(align: str, gt_pos: np.ndarray, est_pos: np.ndarray):
    if align not in ALIGN_MODES:
        raise MetricError(f"unknown alignment '{align}' (use one of {', '.join(ALIGN_MODES)})")
    if align == "none":
        return 1.0, np.eye(3), np.zeros(3)
    return umeyama_alignment(est_pos, gt_pos, with_scale=(align == "sim3"))


def _matched_aligned(gt_ts, gt_poses, est_ts, est_poses, align, max_diff, offset):
    """Checked, associated and aligned trajectories: (ground-truth stamps, matched ground
    truth G, matched estimate aligned onto it Ea, match indices ia / ib, (s, R, t))."""
    gt_ts, G = _check_traj(gt_ts, gt_poses, "ground-truth")
    est_ts, E = _check_traj(est_ts, est_poses, "estimated")
    ia, ib = _associate_checked(gt_ts, est_ts, max_diff, offset)
    G, E = G[ia], E[ib]
    s, R, t = _alignment(align, G[:, :3, 3], E[:, :3, 3])
    return gt_ts, G, align_poses(E, s, R, t), ia, ib, (s, R, t)


# --------------------------------------------------------------------- ATE
def ate(gt_ts, gt_poses, est_ts, est_poses, align: str = "sim3", max_diff: float = 0.02,
        offset: float = 0.0) -> Dict:
    """Absolute trajectory error (translation) in cm after aligning the full matched trajectory.

    Returns a dict with ``rmse_cm, mean_cm, median_cm, std_cm, min_cm, max_cm, sse_m2,
    n_matched, n_gt, n_est, scale, rotation (3x3), translation (3,), align, max_diff,
    rot_rmse_deg`` (rotation part of the absolute error after alignment) and the arrays
    ``timestamps`` (ground-truth stamps of the matches), ``errors_cm``, ``gt_poses``
    (matched), ``aligned_est_poses`` (matched estimate after alignment), ``idx_gt``, ``idx_est``.
    """
    gt_ts, G, Ea, ia, ib, (s, R, t) = _matched_aligned(gt_ts, gt_poses, est_ts, est_poses,
                                                        align, max_diff, offset)
    err = np.linalg.norm(G[:, :3, 3] - Ea[:, :3, 3], axis=1)
    st = _stats(err)
    rot_err = _rotation_angles_deg(np.swapaxes(G[:, :3, :3], 1, 2) @ Ea[:, :3, :3])
    return dict(
        rmse_cm=100 * st["rmse"], mean_cm=100 * st["mean"], median_cm=100 * st["median"],
        std_cm=100 * st["std"], min_cm=100 * st["min"], max_cm=100 * st["max"],
        sse_m2=st["sse"], rot_rmse_deg=float(np.sqrt(np.mean(rot_err ** 2))),
        n_matched=int(len(ia)), n_gt=int(len(gt_ts)), n_est=int(len(est_ts)),
        scale=float(s), rotation=R, translation=t, align=align, max_diff=float(max_diff),
        timestamps=gt_ts[ia], errors_cm=100 * err, gt_poses=G, aligned_est_poses=Ea,
        idx_gt=ia, idx_est=ib)


def segment_scales(gt_ts, gt_poses, est_ts, est_poses, seconds: float = 2.0,
                   max_diff: float = 0.02, min_path_m: float = 0.05) -> Dict:
    """Scale drift: the Sim(3) scale of each ``seconds``-long segment of the matched
    trajectory (aligned on its own), divided by the scale of the whole trajectory. A
    trajectory whose scale holds gives ratios near 1 everywhere; a segment where the scale
    breaks stands out. Segments whose ground-truth path is shorter than ``min_path_m`` (a
    scale is not observable there) are left out.

    Returns ``starts`` (segment start stamps, s from the first match), ``ratios``,
    ``path_m`` (ground-truth path length per segment), ``drift`` (max ratio / min ratio,
    1 = none) and ``scale`` (the whole trajectory's)."""
    if seconds <= 0:
        raise MetricError(f"segment length must be > 0 s, got {seconds}")
    gt_ts, G, Ea, ia, _ib, (s_all, _R, _t) = _matched_aligned(
        gt_ts, gt_poses, est_ts, est_poses, "sim3", max_diff, 0.0)
    # a segment of the estimate aligned as a whole, aligned again on its own: the extra
    # scale is the segment's scale over the whole trajectory's
    t, Pg, Pe = gt_ts[ia], G[:, :3, 3], Ea[:, :3, 3]
    starts, ratios, paths = [], [], []
    for t0 in np.arange(t[0], t[-1] - 0.5 * seconds, seconds):
        m = (t >= t0) & (t < t0 + seconds)
        path = float(np.linalg.norm(np.diff(Pg[m], axis=0), axis=1).sum()) if m.sum() > 1 else 0
        if m.sum() < 3 or path < min_path_m:
            continue
        ratio, _, _ = umeyama_alignment(Pe[m], Pg[m], with_scale=True)
        starts.append(float(t0 - t[0]))
        ratios.append(float(ratio))
        paths.append(path)
    r = np.asarray(ratios)
    return dict(starts=starts, ratios=ratios, path_m=paths, scale=float(s_all),
                drift=float(r.max() / r.min()) if len(r) else float("nan"))


# --------------------------------------------------------------------- RPE
def _pairs(P: np.ndarray, delta, unit: str, all_pairs: bool) -> List[Tuple[int, int]]:
    n = len(P)
    if unit == "frames":
        d = int(delta)
        if d != delta or d < 1:
            raise MetricError(f"RPE delta in frames must be a positive integer, got {delta}")
        if all_pairs:
            return [(i, i + d) for i in range(n - d)]
        ids = list(range(0, n, d))
        return list(zip(ids[:-1], ids[1:]))
    if unit == "meters":
        if not delta > 0:
            raise MetricError(f"RPE delta in meters must be > 0, got {delta}")
        if all_pairs:
            raise MetricError("all_pairs is only supported with unit 'frames'")
        steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
        ids, acc = [0], 0.0
        for i, step in enumerate(steps, start=1):   # consecutive pairs >= delta of path apart
            acc += step
            if acc >= delta:
                ids.append(i)
                acc = 0.0
        return list(zip(ids[:-1], ids[1:]))
    raise MetricError(f"unknown RPE unit '{unit}' (use one of {', '.join(RPE_UNITS)})")


def rpe(gt_ts, gt_poses, est_ts, est_poses, delta=1, unit: str = "frames",
        align: str = "sim3", max_diff: float = 0.02, offset: float = 0.0,
        all_pairs: bool = False) -> Dict:
    """Relative pose error between pose pairs ``delta`` apart (evo's RPE definition).

    ``E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` for ground truth Q and estimate P (after the
    same alignment as :func:`ate`, which only matters for the scale). Pairs are consecutive
    with index step ``delta`` (``unit='frames'``, or every pair with ``all_pairs``), or
    consecutive at >= ``delta`` metres of travelled path of the aligned estimate
    (``unit='meters'``). Returns ``trans_{rmse,mean,median,std,min,max}_cm``,
    ``rot_{rmse,mean,median,std,min,max}_deg``, ``n_pairs``, ``n_matched``, ``scale`` and
    the per-pair arrays ``trans_errors_cm``, ``rot_errors_deg``, ``pairs``.
    """
    gt_ts, G, Ea, ia, ib, (s, R, t) = _matched_aligned(gt_ts, gt_poses, est_ts, est_poses,
                                                        align, max_diff, offset)
    pairs = _pairs(Ea, delta, unit, all_pairs)
    if not pairs:
        raise MetricError(f"RPE delta {delta} ({unit}) leaves no pose pairs among "
                          f"{len(ia)} matched poses; use a smaller delta")
    i = np.array([p[0] for p in pairs])
    j = np.array([p[1] for p in pairs])
    Gt, Et = torch.from_numpy(G), torch.from_numpy(Ea)
    Q_rel = se3_inverse(Gt[i]) @ Gt[j]
    P_rel = se3_inverse(Et[i]) @ Et[j]
    Err = (se3_inverse(Q_rel) @ P_rel).numpy()
    te = np.linalg.norm(Err[:, :3, 3], axis=1)
    re_ = _rotation_angles_deg(Err[:, :3, :3])
    out = dict(n_pairs=len(pairs), n_matched=int(len(ia)), scale=float(s), align=align,
               delta=delta, unit=unit, all_pairs=bool(all_pairs),
               trans_errors_cm=100 * te, rot_errors_deg=re_, pairs=np.stack([i, j], 1))
    for k, v in _stats(te).items():
        if k != "sse":
            out[f"trans_{k}_cm"] = 100 * v
    for k, v in _stats(re_).items():
        if k != "sse":
            out[f"rot_{k}_deg"] = v
    return out


# --------------------------------------------------------- image handling
def _as_image(x, name: str) -> torch.Tensor:
    """Any H x W x C / C x H x W (C in 1, 3) image -> float64 tensor H x W x C in [0, 1]."""
    if isinstance(x, np.ndarray):
        t = torch.from_numpy(np.ascontiguousarray(x))
    elif torch.is_tensor(x):
        t = x.detach()
    else:
        raise MetricError(f"{name} must be a numpy array or torch tensor, got {type(x).__name__}")
    if t.dtype == torch.uint8:
        t = t.double() / 255.0
    elif t.is_floating_point():
        t = t.double()
    else:
        raise MetricError(f"{name} must be float in [0, 1] or uint8, got {t.dtype}")
    if t.ndim == 2:
        t = t[..., None]
    if t.ndim != 3:
        raise MetricError(f"{name} must be H x W x 3 or 3 x H x W, got shape {tuple(t.shape)}")
    if t.shape[-1] not in (1, 3) and t.shape[0] in (1, 3):
        t = t.permute(1, 2, 0)
    if t.shape[-1] not in (1, 3):
        raise MetricError(f"{name} must have 1 or 3 channels, got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise MetricError(f"{name} contains non-finite values")
    if t.numel() and (t.max() > 2.0 or t.min() < -1.0):
        raise MetricError(f"{name} values span [{float(t.min()):.3g}, {float(t.max()):.3g}]; "
                          "float images must be in [0, 1] (divide 8-bit images by 255)")
    return t.clamp(0.0, 1.0)


def _pair(img, ref) -> Tuple[torch.Tensor, torch.Tensor]:
    a, b = _as_image(img, "image"), _as_image(ref, "reference image")
    if a.shape != b.shape:
        raise MetricError(f"image shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    return a, b.to(a.device)


def _as_mask(mask, shape, device) -> torch.Tensor:
    m = torch.as_tensor(np.asarray(mask) if isinstance(mask, np.ndarray) else mask,
                        device=device).bool()
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if tuple(m.shape) != tuple(shape):
        raise MetricError(f"mask shape {tuple(m.shape)} does not match image {tuple(shape)}")
    return m


def exposure_compensate(img, ref, mask=None, return_params: bool = False):
    """Fit ``a * img + b`` to ``ref`` per channel (least squares) and return it clamped to [0, 1].

    Removes a global brightness/contrast difference (the per-keyframe exposure the map
    learns) before PSNR, like the reference evaluation. Output is a float64 torch tensor
    H x W x C; with ``return_params`` also the (C,) arrays ``a`` and ``b``.
    """
    a_img, r = _pair(img, ref)
    m = (torch.ones(a_img.shape[:2], dtype=torch.bool, device=a_img.device) if mask is None
         else _as_mask(mask, a_img.shape[:2], a_img.device))
    if int(m.sum()) < 2:
        raise MetricError("exposure compensation needs at least 2 valid pixels")
    x, y = a_img[m], r[m]                            # (n, C)
    mx, my = x.mean(0), y.mean(0)
    vx = ((x - mx) ** 2).mean(0)
    cxy = ((x - mx) * (y - my)).mean(0)
    a = torch.where(vx > 1e-12, cxy / vx.clamp_min(1e-12), torch.ones_like(vx))
    b = my - a * mx
    out = (a_img * a + b).clamp(0.0, 1.0)
    if return_params:
        return out, a.cpu().numpy(), b.cpu().numpy()
    return out


def psnr(img, ref, mask=None, exposure_compensation: bool = False) -> float:
    """Peak signal-to-noise ratio (dB) for images in [0, 1]; ``inf`` if identical.

    ``mask`` (H x W bool) restricts the mean squared error to those pixels.
    """
    a, b = _pair(img, ref)
    if exposure_compensation:
        a = exposure_compensate(a, b, mask)
    if mask is not None:
        m = _as_mask(mask, a.shape[:2], a.device)
        if not bool(m.any()):
            raise MetricError("psnr mask selects no pixels")
        a, b = a[m], b[m]
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else float(-10.0 * np.log10(mse))


def ssim(img, ref, win_size: int = 11) -> float:
    """Structural similarity (Gaussian window 11, sigma 1.5) via pytorch-msssim."""
    from pytorch_msssim import ssim as _ssim
    a, b = _pair(img, ref)
    h, w = a.shape[:2]
    if min(h, w) < win_size:
        raise MetricError(f"ssim needs images of at least {win_size}x{win_size} px, got {h}x{w}")
    X = a.permute(2, 0, 1)[None].float()
    Y = b.permute(2, 0, 1)[None].float()
    return float(_ssim(X, Y, data_range=1.0, size_average=True, win_size=win_size))


def depth_l1_cm(depth, ref, mask=None) -> float:
    """Mean absolute depth error in cm over pixels valid in both maps (finite and > 0)."""
    d = torch.as_tensor(_np64(depth, "depth"))
    r = torch.as_tensor(_np64(ref, "reference depth"))
    d, r = d.squeeze(), r.squeeze()
    if d.shape != r.shape or d.ndim != 2:
        raise MetricError(f"depth maps must both be H x W, got {tuple(d.shape)} and "
                          f"{tuple(r.shape)}")
    valid = torch.isfinite(d) & torch.isfinite(r) & (d > 0) & (r > 0)
    if mask is not None:
        valid &= _as_mask(mask, d.shape, d.device)
    if not bool(valid.any()):
        raise MetricError("depth_l1_cm: no pixel has a valid depth in both maps")
    return float(100.0 * (d[valid] - r[valid]).abs().mean())


def _jumps_along_rows(lg: np.ndarray, ok: np.ndarray, jump: float, edge: np.ndarray) -> None:
    """Mark in ``edge`` both pixels of every pair of valid pixels of a row with nothing but
    invalid pixels between them (none for neighbours) whose log depths differ by more than
    ``jump`` per pixel of distance."""
    H, W = lg.shape
    last = np.maximum.accumulate(np.where(ok, np.arange(W)[None, :], -1), axis=1)
    prev = np.concatenate([np.full((H, 1), -1), last[:, :-1]], axis=1)  # previous valid column
    rows, cols = np.nonzero(ok & (prev >= 0))
    pcols = prev[rows, cols]
    hit = np.abs(lg[rows, cols] - lg[rows, pcols]) > jump * (cols - pcols)
    edge[rows[hit], cols[hit]] = True
    edge[rows[hit], pcols[hit]] = True


def depth_edge_band(ref, radius: int, jump: float = 0.05) -> torch.Tensor:
    """(H, W) bool: pixels within ``radius`` px (square window) of a depth discontinuity of
    ``ref``: two valid pixels of a row or column, neighbours or with only invalid pixels
    between them, whose depths differ by more than ``jump`` in log depth (5 %) per pixel of
    distance. The invalid gap matters: depth sensors and many renderers leave no depth on
    the pixels along a silhouette (mixed or occluded pixels), and a test of neighbours only
    would find no edge there. Splits depth errors into "at object boundaries" (where a
    coarse depth bleeds from one surface onto the other) and "on surfaces"."""
    r = _np64(ref, "reference depth").squeeze()
    if r.ndim != 2:
        raise MetricError(f"reference depth must be H x W, got {tuple(r.shape)}")
    ok = np.isfinite(r) & (r > 0)
    lg = np.log(np.where(ok, r, 1.0))
    edge = np.zeros(r.shape, bool)
    _jumps_along_rows(lg, ok, jump, edge)
    _jumps_along_rows(lg.T, ok.T, jump, edge.T)          # columns (edge.T is a view)
    out = torch.from_numpy(edge)
    if radius > 0:
        k = 2 * int(radius) + 1
        out = torch.nn.functional.max_pool2d(out[None, None].float(), k, 1,
                                             int(radius))[0, 0] > 0
    return out


# -------------------------------------------------------------------- LPIPS
_LPIPS_CACHE: Dict[tuple, tuple] = {}
_WEIGHT_NAME = re.compile(r"(?:^|\.)(?:lpips_w(\d+)|lin(\d+)(?:\.model\.1)?\.weight)$")


def _weights_from_named(named) -> Optional[List[torch.Tensor]]:
    """Per-layer channel weights from names ``lpips_w<i>`` or ``lin<i>[.model.1].weight``."""
    found = {}
    for name, v in named:
        m = _WEIGHT_NAME.search(name)
        if m and torch.is_tensor(v):
            found[int(m.group(1) or m.group(2))] = v.detach().float().reshape(-1)
    if not found:
        return None
    if sorted(found) != list(range(len(found))):
        raise MetricError(f"LPIPS layer weights are not numbered 0..n-1: {sorted(found)}")
    return [found[i] for i in range(len(found))]


def _load_weights(path: Path) -> List[torch.Tensor]:
    if not path.is_file():
        raise MetricError(f"LPIPS weights file not found: {path}")
    try:
        obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any load failure is a user-file problem
        raise MetricError(f"cannot read LPIPS weights file {path}: "
                          f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}") from None
    if isinstance(obj, (list, tuple)) and all(torch.is_tensor(v) for v in obj):
        return [v.detach().float().reshape(-1) for v in obj]
    if isinstance(obj, dict):
        w = _weights_from_named(obj.items())
        if w is not None:
            return w
    raise MetricError(f"LPIPS weights file {path} must hold a list of per-layer tensors or a "
                      "state dict with keys 'lin<i>.model.1.weight' / 'lpips_w<i>'")


def _load_backbone(p: Path) -> torch.nn.Module:
    """TorchScript file (torch.jit.save), else a torch.export program (torch.export.save)."""
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)   # torch.jit is deprecated in 2.x
        try:
            return torch.jit.load(str(p), map_location="cpu")
        except Exception as e:  # noqa: BLE001 - any failure means "not TorchScript"
            jit_err = type(e).__name__
        try:
            return torch.export.load(str(p)).module()
        except Exception:  # noqa: BLE001
            pass
    raise MetricError(f"LPIPS backbone {p} is not a loadable TorchScript file ({jit_err}) nor "
                      "a torch.export program; save it with torch.jit.save or torch.export.save")


def _load_lpips(model, weights_path, device) -> tuple:
    if isinstance(model, torch.nn.Module):
        key = (id(model), str(weights_path), str(device))
    else:
        p = Path(os.fspath(model))
        if not p.is_file():
            raise MetricError(f"LPIPS backbone file not found: {p}")
        key = (str(p.resolve()), p.stat().st_mtime_ns, str(weights_path), str(device))
    if key in _LPIPS_CACHE:
        return _LPIPS_CACHE[key]
    if not isinstance(model, torch.nn.Module):
        net = _load_backbone(p)
    else:
        net = model
    try:
        net = net.eval()
    except NotImplementedError:          # torch.export modules have no train/eval switch
        pass
    if torch.device(device) != torch.device("cpu"):
        try:
            net = net.to(device)
        except Exception as e:  # noqa: BLE001
            raise MetricError(f"cannot move the LPIPS backbone to {device}: "
                              f"{type(e).__name__}") from None
    if weights_path is not None:
        weights = _load_weights(Path(os.fspath(weights_path)))
    else:
        weights = _weights_from_named(list(net.named_buffers()) + list(net.named_parameters()))
    entry = (net, None if weights is None else [w.to(device) for w in weights])
    _LPIPS_CACHE.clear()                 # keep one model in memory
    _LPIPS_CACHE[key] = entry
    return entry


def lpips(img, ref, model_path, weights_path=None, layer_reduce: str = "sum") -> float:
    """LPIPS-style perceptual distance with a user-supplied backbone (no downloads).

    ``model_path``: a TorchScript file (``torch.jit.save``; a ``torch.export.save`` program
    also loads) or an ``nn.Module`` whose
    forward maps a (B, 3, H, W) batch in [-1, 1] to a list/tuple of feature maps
    (B, C_l, H_l, W_l) (a single tensor counts as one layer); any input normalisation
    belongs inside the module. Per-layer channel weights ``w_l`` come from
    ``weights_path`` (a ``torch.save``d list of tensors, or a state dict with keys
    ``lin<i>.model.1.weight`` like the official LPIPS files, or ``lpips_w<i>``), else
    from buffers/parameters named that way inside the module, else all ones.
    Distance (the LPIPS formula): for each layer, unit-normalise features over channels,
    take ``sum_c w_c (f1 - f2)^2`` averaged over space; then sum over layers
    (``layer_reduce='mean'`` averages instead). Identical images give 0.
    """
    if layer_reduce not in ("sum", "mean"):
        raise MetricError(f"layer_reduce must be 'sum' or 'mean', got {layer_reduce!r}")
    a, b = _pair(img, ref)
    if a.shape[-1] == 1:
        a, b = a.expand(-1, -1, 3), b.expand(-1, -1, 3)
    device = a.device
    net, weights = _load_lpips(model_path, weights_path, device)
    x = torch.stack([a, b]).permute(0, 3, 1, 2).float() * 2 - 1
    try:
        with torch.no_grad():
            feats = net(x)
    except Exception as e:  # noqa: BLE001
        msg = str(e).strip().splitlines()
        raise MetricError(f"LPIPS backbone failed on a {tuple(x.shape)} batch: "
                          f"{type(e).__name__}{': ' + msg[-1][:200] if msg else ''}") from None
    if torch.is_tensor(feats):
        feats = [feats]
    if (not isinstance(feats, (list, tuple)) or not feats
            or not all(torch.is_tensor(f) and f.ndim == 4 and f.shape[0] == 2 for f in feats)):
        raise MetricError("LPIPS backbone must return a tensor or a list/tuple of (B, C, H, W) "
                          "feature maps")
    if weights is not None and len(weights) != len(feats):
        raise MetricError(f"LPIPS weights have {len(weights)} layers but the backbone returns "
                          f"{len(feats)} feature maps")
    dists = []
    for li, f in enumerate(feats):
        f = f.double()
        f = f / (f.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)     # unit-normalise channels
        d2 = (f[0] - f[1]).pow(2)                                  # (C, H, W)
        if weights is not None:
            w = weights[li].double()
            if w.numel() != d2.shape[0]:
                raise MetricError(f"LPIPS layer {li}: {w.numel()} weights for "
                                  f"{d2.shape[0]} channels")
            d2 = d2 * w[:, None, None]
        dists.append(d2.sum(0).mean())
    d = torch.stack(dists)
    return float(d.sum() if layer_reduce == "sum" else d.mean())


def check_lpips(model_path, weights_path=None) -> None:
    """Load an LPIPS backbone file (and weights file) as :func:`lpips` does, then drop it:
    MetricError at once when a file is missing or is no backbone / weights file (before a
    run whose LPIPS would fail at its end)."""
    try:
        _load_lpips(model_path, weights_path or None, "cpu")
    finally:
        release_lpips()


def release_lpips() -> None:
    """Free the backbone :func:`lpips` keeps loaded between calls."""
    _LPIPS_CACHE.clear()


def image_metrics(img, ref, depth=None, ref_depth=None, lpips_model=None,
                  lpips_weights=None, exposure_compensation: bool = True) -> Dict[str, float]:
    """All rendering metrics of one view: psnr (optionally exposure-compensated), ssim,
    lpips (when a backbone is given) and depth_l1_cm (when both depths are given)."""
    out = {"psnr": psnr(img, ref, exposure_compensation=exposure_compensation),
           "ssim": ssim(img, ref)}
    if lpips_model is not None:
        out["lpips"] = lpips(img, ref, lpips_model, lpips_weights)
    if depth is not None and ref_depth is not None:
        out["depth_l1_cm"] = depth_l1_cm(depth, ref_depth)
    return out


def summarize(values: Sequence[Dict[str, float]]) -> Dict[str, float]:
    """Mean of each metric over views (``inf`` PSNRs are kept out of the PSNR mean)."""
    keys = sorted({k for v in values for k in v})
    out = {}
    for k in keys:
        xs = np.array([v[k] for v in values if k in v], dtype=np.float64)
        xs = xs[np.isfinite(xs)]
        if len(xs):
            out[k] = float(xs.mean())
    return out
