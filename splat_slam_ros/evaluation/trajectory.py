"""Trajectory metrics as pure functions: ATE and RPE, timestamp association, Umeyama
alignment and the scale drift per segment.

The trajectory metrics follow the reference evaluation (the evo library): poses are
associated by nearest timestamp, the estimate is aligned to the ground truth with
Umeyama's method (Sim(3) by default, the monocular case) over the full matched
trajectory, and the translational error is reported in centimetres. File formats are
read by :mod:`splat_slam_ros.io.trajectory_io`.
"""
from __future__ import annotations

from typing import Dict, List, Tuple

import numpy as np
import torch

from splat_slam_ros.evaluation.inputs import MetricError, to_float64
from splat_slam_ros.geometry import apply_sim3_to_poses, se3_inverse, so3_log

ALIGN_MODES = ("sim3", "se3", "none")
RPE_UNITS = ("frames", "meters")


# ------------------------------------------------------------------ helpers
def _check_traj(ts, poses, name: str) -> Tuple[np.ndarray, np.ndarray]:
    ts = to_float64(ts, f"{name} timestamps").reshape(-1)
    P = to_float64(poses, f"{name} poses")
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
    a = to_float64(ts_a, "timestamps").reshape(-1)
    b = to_float64(ts_b, "timestamps").reshape(-1) + float(offset)
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
    x = to_float64(src, "src")
    y = to_float64(dst, "dst")
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
    P = torch.from_numpy(to_float64(poses, "poses"))
    return apply_sim3_to_poses(float(s), torch.from_numpy(to_float64(R, "R")),
                               torch.from_numpy(to_float64(t, "t")), P).numpy()


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
