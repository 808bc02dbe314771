"""DSPO: Disparity, Scale and Pose Optimization (paper §3.1, Eq. 2-3).

The tracker alternates two objectives over its local window (Eq. 1 and Eq. 2 are
optimised alternately "to avoid the scale ambiguity"):

- Eq. 1 (DBA, :mod:`dense_ba`): poses and disparities against the optical flow;
- Eq. 2 (here): with the poses fixed, the *high-error* disparities ``d^h``, and per
  keyframe a scale ``theta_i`` and shift ``gamma_i`` of the monocular disparity
  ``1 / D^mono_i``::

      sum_E ||p~_ij - pi(d^h)||^2_Sigma + a1 sum ||d^h - (theta m + gamma)||^2
                                        + a2 sum ||d^l - (theta m + gamma)||^2,  a1 < a2

  High/low error = the multi-view consistency of Eq. 4-6 (:func:`multiview.multiview_filter`)
  evaluated on the window: consistent pixels are ``d^l`` (kept fixed), the rest ``d^h``.

Solution of Eq. 2 per Gauss-Newton step: with the poses fixed every disparity only meets
its own pixel's flow terms, so the flow term is diagonal (``H``, ``g`` from
:func:`dense_ba.disparity_normal_equations`). Eliminating each ``d^h`` exactly (Schur
complement) leaves a 2x2 weighted least-squares problem in ``(theta, gamma)`` per keyframe:
low pixels pull ``theta m + gamma`` to ``d^l`` with weight ``a2``, high pixels to their
flow-optimal value ``d + g/H`` with weight ``a1 H / (H + a1)`` (zero where the flow carries
no information). Then ``d^h <- d^h + (g - a1 (d^h - theta m - gamma)) / (H + a1)``: where
the flow is unreliable (small ``H``) the disparity follows the fitted mono prior, where it
is strong the flow still dominates. ``theta, gamma`` start from the least-squares fit of
Eq. 3 on ``d^l``, which also gates each keyframe: a keyframe whose mono depth does not fit
its reliable disparities (mean residual > ``dspo_mono_thresh`` x mean disparity), with a
non-positive scale, or with fewer than 20 % reliable pixels (the reference: 50 % of the
image; the newest keyframe of a window has few views yet) is left to plain DBA.

Units: the flow term is taken as in :mod:`dense_ba` (confidence weights) divided by
``FLOW_SCALE`` = 1000 and disparities are normalised by the window's mean disparity. This
is the convention under which the reference chose alpha1 = 0.01, alpha2 = 0.1 (its BA
multiplies confidences by 0.001, its disparities have mean ~1); it also makes Eq. 2
invariant to the arbitrary scale of a monocular map.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.tracking.dense_ba import MIN_DISP, disparity_normal_equations
from splat_slam_ros.tracking.multiview import multiview_filter, sample_at_grid
from splat_slam_ros.types import Intrinsics

FLOW_SCALE = 1000.0
DSPO_NEIGHBORS = 4        # nearest window keyframes used (besides edges) for the high/low split


@dataclass
class DspoInfo:
    """Diagnostics of one DSPO call."""
    theta: torch.Tensor            # (N,) scale per keyframe (real disparity units), nan if skipped
    gamma: torch.Tensor            # (N,) shift
    theta0: torch.Tensor           # (N,) Eq. 3 initialisation
    gamma0: torch.Tensor
    used: torch.Tensor             # (N,) bool: keyframe went through Eq. 2
    low_frac: torch.Tensor         # (N,) fraction of low-error (multi-view consistent) pixels
    mono_err: torch.Tensor         # (N,) Eq. 3 mean residual / mean disparity


def _weighted_affine(x, y, w):
    """Batched argmin_{a,b} sum w (a x + b - y)^2 over the last dims -> (a, b, ok)."""
    sw = w.sum((-2, -1))
    sx = (w * x).sum((-2, -1))
    sy = (w * y).sum((-2, -1))
    sxx = (w * x * x).sum((-2, -1))
    sxy = (w * x * y).sum((-2, -1))
    det = sw * sxx - sx * sx
    ok = (sw > 0) & (det > 1e-12 * (sw * sxx).clamp_min(1e-30))
    dets = torch.where(ok, det, torch.ones_like(det))
    a = (sw * sxy - sx * sy) / dets
    b = (sxx * sy - sx * sxy) / dets
    return a, b, ok


@torch.no_grad()
def dspo_step(poses: torch.Tensor, disps: torch.Tensor, intr, ii: torch.Tensor,
              jj: torch.Tensor, target: torch.Tensor, weight: torch.Tensor,
              mono_disp: torch.Tensor, low: torch.Tensor, alpha1: float = 0.01,
              alpha2: float = 0.1, mono_thresh: float = 0.1, min_low_frac: float = 0.2,
              active: Optional[torch.Tensor] = None, iters: int = 2,
              huber: Optional[float] = None,
              normal_equations=disparity_normal_equations) -> Tuple[torch.Tensor, DspoInfo]:
    """Eq. 2 with the poses fixed: update high-error disparities and theta, gamma.

    poses (N,4,4) c2w, disps (N,h,w), intr (fx,fy,cx,cy) at BA res; edges ii->jj with
    target/weight (E,h,w,2) as in :func:`dense_ba.ba_step`; mono_disp (N,h,w) = 1/D^mono
    sampled on the BA grid (<= 0: none); low (N,h,w) bool = multi-view consistent (d^l);
    active (N,) bool: keyframes that may change (default: edge sources).
    Returns (new disparities, :class:`DspoInfo`).
    """
    N, h, w = disps.shape
    dev, dt = disps.device, disps.dtype
    ii = ii.to(dev)
    m = mono_disp.to(dev, dt)
    has_m = torch.isfinite(m) & (m > 0)
    low = low.to(dev) & has_m
    if active is None:
        active = torch.zeros(N, dtype=torch.bool, device=dev)
        active[ii] = True
    active = active.to(dev)
    high = ~low & has_m & active[:, None, None]
    # normalisation: mean disparity of the window
    s = float(disps[disps > 0].mean()) if bool((disps > 0).any()) else 1.0
    # Eq. 3: least-squares init of theta, gamma on d^l (+ the per-keyframe mono gate)
    th0, ga0, ok0 = _weighted_affine(m, disps, low.to(dt))
    res = ((th0[:, None, None] * m + ga0[:, None, None] - disps).abs() * low).sum((1, 2))
    nlow = low.sum((1, 2))
    dmean = (disps * low).sum((1, 2)) / nlow.clamp_min(1)
    err = res / nlow.clamp_min(1) / dmean.clamp_min(1e-12)
    low_frac = nlow.to(dt) / has_m.sum((1, 2)).clamp_min(1).to(dt)
    use = active & ok0 & (th0 > 0) & (err <= mono_thresh) & (low_frac >= min_low_frac)
    theta = torch.where(use, th0, torch.full_like(th0, float("nan")))
    gamma = torch.where(use, ga0, torch.full_like(ga0, float("nan")))
    d = disps.clone()
    if not bool(use.any()):
        return d, DspoInfo(theta, gamma, th0, ga0, use, low_frac, err)
    U = use[:, None, None]
    hi = high & U
    lo = low & U
    for _ in range(max(1, iters)):
        H, g = normal_equations(poses, d, intr, ii, jj, target, weight, huber)
        Hn = H * (s * s) / FLOW_SCALE                      # normalised units: dn = d / s
        gn = g * s / FLOW_SCALE
        dn, mn = d / s, m
        # flow-optimal value of the high pixels and their weight after eliminating d^h
        dstar = torch.where(Hn > 0, dn + gn / Hn.clamp_min(1e-30), dn)
        wh = alpha1 * Hn / (Hn + alpha1)
        wts = torch.where(lo, torch.full_like(dn, alpha2),
                          torch.where(hi, wh, torch.zeros_like(dn)))
        y = torch.where(lo, dn, dstar)
        a, b, ok = _weighted_affine(mn, y, wts)
        ok = ok & use
        a = torch.where(ok, a, th0 / s)
        b = torch.where(ok, b, ga0 / s)
        prior = a[:, None, None] * mn + b[:, None, None]
        step = (gn - alpha1 * (dn - prior)) / (Hn + alpha1)
        d = torch.where(hi, ((dn + step) * s).clamp_min(MIN_DISP), d)   # d^l untouched
        theta = torch.where(use, a * s, theta)
        gamma = torch.where(use, b * s, gamma)
    return d, DspoInfo(theta, gamma, th0, ga0, use, low_frac, err)


class DspoPrior:
    """The tracker's ``depth_prior`` hook: ``prior(BAState) -> disparities (N,h,w) | None``.

    Runs the mono model once per keyframe (while the tracker still holds its image), keeps
    ``1/D^mono`` on the BA grid, classifies high/low-error pixels with the multi-view filter
    over the window (each keyframe against the keyframes it has flow edges with and its 4
    nearest window keyframes) and applies one Gauss-Newton step of :func:`dspo_step`.
    """

    def __init__(self, cfg: SlamConfig, intrinsics: Intrinsics, mono_model=None):
        self.cfg = cfg
        self.tc = cfg.tracking
        self.dc = cfg.depth
        self.intrinsics = intrinsics
        if mono_model is None:
            from splat_slam_ros.tracking.mono_depth import load_mono_depth
            mono_model = load_mono_depth(self.dc.mono_model, self.dc.mono_provider)
        self.mono = mono_model
        self._mono_ba: Dict[int, torch.Tensor] = {}
        self._mono_full: Dict[int, np.ndarray] = {}
        self.last_info: Optional[DspoInfo] = None
        self.calls = 0
        self.iters = 1

    # -- mono depth per keyframe ------------------------------------------------
    def _mono_for(self, kf_id: int, image: Optional[np.ndarray], h: int, w: int, device):
        if kf_id not in self._mono_ba:
            if image is None:
                return None
            depth = self.mono.predict(np.asarray(image))
            self._mono_full[kf_id] = depth
            t = torch.from_numpy(depth)
            disp_full = torch.where(t > 0, 1.0 / t.clamp_min(1e-12), torch.zeros_like(t))
            self._mono_ba[kf_id] = sample_at_grid(disp_full, h, w)
        return self._mono_ba[kf_id].to(device)

    def take_mono_depth(self, kf_id: int) -> Optional[np.ndarray]:
        """The full-resolution mono depth of a keyframe (for ``KeyframeData.mono_depth``, so
        that the depth stage does not run the network again); handed out once."""
        return self._mono_full.pop(int(kf_id), None)

    def forget(self, kf_id: int) -> None:
        self._mono_ba.pop(int(kf_id), None)
        self._mono_full.pop(int(kf_id), None)

    # -- the hook ------------------------------------------------------------------
    def __call__(self, st) -> Optional[torch.Tensor]:
        ids = list(st.kf_ids)
        N, h, w = st.disps.shape
        dev = st.disps.device
        monos = [self._mono_for(k, st.images.get(k), h, w, dev) for k in ids]
        if all(mo is None for mo in monos):
            return None
        mono = torch.stack([mo if mo is not None else torch.zeros(h, w, device=dev)
                            for mo in monos]).to(st.disps.dtype)
        # high / low error split: Eq. 4-6 of each keyframe against the keyframes it shares
        # flow edges with plus its DSPO_NEIGHBORS nearest window keyframes (the newest
        # keyframe has few edges yet), which keeps the cost well below all pairs
        k = max(1, min(DSPO_NEIGHBORS, N - 1))
        idx = torch.arange(N, device=dev)
        dist = (idx[:, None] - idx[None, :]).abs().to(torch.float32) + idx[None, :] * 1e-3
        dist.fill_diagonal_(float("inf"))
        nb = dist.topk(k, dim=1, largest=False).indices
        pairs = torch.cat([torch.stack([idx[:, None].expand(N, k).reshape(-1), nb.reshape(-1)],
                                       -1), torch.stack([st.ii, st.jj], -1).to(dev)])
        pairs = torch.unique(pairs, dim=0)
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        depth = torch.where(st.disps > 0, 1.0 / st.disps.clamp_min(1e-12),
                            torch.zeros_like(st.disps))
        low, _ = multiview_filter(depth, st.poses, st.intr, self.dc.mv_eta,
                                  self.dc.mv_min_views, self.dc.mv_max_depth_ratio, pairs=pairs,
                                  min_parallax_deg=self.dc.mv_min_parallax_deg)
        active = torch.zeros(N, dtype=torch.bool, device=dev)
        active[st.ii.to(dev)] = True
        huber = None
        if getattr(self.tc, "robust_huber_px", 0) > 0:
            huber = self.tc.robust_huber_px / self.tc.ba_downsample
        # one Gauss-Newton step per call: the tracker alternates Eq. 1 and Eq. 2 across its
        # successive local BAs, which is where the alternation of the paper happens
        d, info = dspo_step(st.poses, st.disps, st.intr, st.ii, st.jj, st.target, st.weight,
                            mono, low, self.tc.dspo_alpha1, self.tc.dspo_alpha2,
                            self.tc.dspo_mono_thresh, active=active, huber=huber,
                            iters=self.iters)
        self.last_info = info
        self.calls += 1
        return d


def make_depth_prior(cfg: SlamConfig, intrinsics: Intrinsics, mono_model=None):
    """The tracker's DSPO hook, or None when DSPO is off (no mono model or tracking.dspo
    false). Raises :class:`mono_depth.MonoDepthError` for an unusable model file."""
    if not cfg.tracking.dspo or (mono_model is None and not cfg.depth.mono_model):
        return None
    return DspoPrior(cfg, intrinsics, mono_model)
