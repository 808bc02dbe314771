"""Dense bundle adjustment over keyframe poses and per-pixel disparities (paper Eq. 1).

Variables: camera-to-world poses ``T_i`` (N, 4, 4) float64 and inverse depths
``d_i`` (N, h, w) at the BA resolution. An edge ``(i, j)`` carries a target
``p~_ij`` (h, w, 2): where the pixels of keyframe ``i`` land in keyframe ``j``
according to the optical flow (BA pixels, absolute coordinates), and a weight
``Sigma_ij`` (h, w, 2) in [0, 1] (the flow confidence). Residual:

    r_ij(p) = p~_ij(p) - pi(T_j^-1 T_i pi^-1(p, d_i(p)))

Poses are updated on the left in the world frame, ``T <- exp(xi) T`` (the
geometry.py convention); with that choice the Jacobian w.r.t. the target pose
is exactly minus the one w.r.t. the source pose. Points are homogeneous
``(R q + t d, d)`` with ``q = K^-1 [u, v, 1]``, so zero disparity (points at
infinity) is handled. Disparities are eliminated with the Schur complement of
their diagonal block, the reduced 6Nx6N pose system is solved densely.

Everything is vectorised over edges and pixels (one batched matmul per
quantity), float32 per pixel and float64 for the pose system; any device.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple, Union

import torch

from splat_slam_ros import native
from splat_slam_ros.config import BA_BACKENDS
from splat_slam_ros.geometry import (intr_tensor, pixel_grid, project_homogeneous, se3_exp,
                                     se3_exp_one, se3_inverse)

MIN_DISP = 1e-3


@dataclass
class BAInfo:
    """Diagnostics of one Gauss-Newton iteration (cost before the step)."""
    cost: float            # sum of weighted squared residuals (robust weights included)
    rms: float             # weighted RMS residual (BA pixels)
    n_valid: int           # pixel-edges with a positive weight and depth


def _rays(h: int, w: int, intr: torch.Tensor) -> torch.Tensor:
    """(3, h*w) normalised rays q = K^-1 [u, v, 1] of the BA grid."""
    uv = pixel_grid(h, w, dtype=intr.dtype, device=intr.device).reshape(-1, 2)
    x = (uv[:, 0] - intr[2]) / intr[0]
    y = (uv[:, 1] - intr[3]) / intr[1]
    return torch.stack([x, y, torch.ones_like(x)], 0)


def reproject(poses: torch.Tensor, disps: torch.Tensor, intr, ii: torch.Tensor,
              jj: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Pixels of keyframes ``ii`` reprojected into ``jj`` with the current
    poses/disparities: (E, h, w, 2) coordinates and (E, h, w) validity (z > 0)."""
    N, h, w = disps.shape
    intr = intr_tensor(intr, disps.dtype, disps.device)
    Gij = se3_inverse(poses[jj]) @ poses[ii]                      # cam i -> cam j
    R = Gij[:, :3, :3].to(disps.dtype)
    t = Gij[:, :3, 3].to(disps.dtype)
    q = _rays(h, w, intr)
    d = disps[ii].reshape(len(ii), 1, -1)
    X = torch.einsum("eab,bp->eap", R, q) + t[:, :, None] * d      # (E, 3, P)
    uv, _ = project_homogeneous(X.transpose(1, 2), intr)
    valid = X[:, 2] > 1e-3 * d[:, 0].clamp_min(1e-6)
    return uv.reshape(len(ii), h, w, 2), valid.reshape(len(ii), h, w)


def induced_flow_distance(poses: torch.Tensor, disps: torch.Tensor, intr, ii: torch.Tensor,
                          jj: torch.Tensor, stride: int = 2) -> torch.Tensor:
    """Mean magnitude (BA pixels) of the flow induced by the current estimate for
    each edge (i -> j), on a ``stride``-subsampled grid. Used for proximity edges
    and loop candidates; invalid (behind-camera) pixels count as a large flow."""
    N, h, w = disps.shape
    if len(ii) == 0:
        return torch.zeros(0, dtype=disps.dtype, device=disps.device)
    ds = disps[:, ::stride, ::stride].contiguous()
    intr = intr_tensor(intr, disps.dtype, disps.device)
    # subsampled grid keeps pixel-centre geometry: u_sub = (u - 0) / stride
    intr_s = torch.stack([intr[0] / stride, intr[1] / stride, intr[2] / stride,
                          intr[3] / stride])
    uv, valid = reproject(poses, ds, intr_s, ii, jj)
    grid = pixel_grid(ds.shape[1], ds.shape[2], dtype=ds.dtype, device=ds.device)
    mag = (uv - grid).norm(dim=-1) * stride
    mag = torch.where(valid, mag, torch.full_like(mag, 1e3))
    return mag.mean(dim=(1, 2))


def _edge_terms(poses, disps, intr, ii, jj, target, weight, huber):
    """Per-edge, per-pixel residuals and Jacobians of Eq. 1, pre-multiplied by
    the square root of the (robust) weights.

    Returns rs (E, P, 2), wgt (E, P, 2) (robust weights applied, 0 where the
    point is behind camera j), Jp (E, P, 2, 6) the Jacobian of the projection
    w.r.t. the source pose (the target pose's is -Jp), Jd (E, P, 2) w.r.t. the
    source disparity; rs, Jp, Jd carry the factor sqrt(wgt).
    """
    E = len(ii)
    N, h, w_ = disps.shape
    P = h * w_
    dt = disps.dtype
    intr = intr_tensor(intr, dt, disps.device)
    Ti, Tj = poses[ii], poses[jj]
    Gij = se3_inverse(Tj) @ Ti
    Rji = Gij[:, :3, :3].to(dt)
    tji = Gij[:, :3, 3].to(dt)
    Ri = Ti[:, :3, :3].to(dt)
    ti = Ti[:, :3, 3].to(dt)
    Rj = Tj[:, :3, :3].to(dt)
    q = _rays(h, w_, intr)                                          # (3, P)
    d = disps[ii].reshape(E, P)
    X = torch.einsum("eab,bp->epa", Rji, q) + tji[:, None, :] * d[..., None]   # (E, P, 3)
    Xw = torch.einsum("eab,bp->epa", Ri, q) + ti[:, None, :] * d[..., None]    # homog. world
    z = X[..., 2]
    valid = z > 1e-3 * d.clamp_min(1e-6)
    iz = 1.0 / z.clamp_min(1e-6)
    xz = X[..., 0] * iz
    yz = X[..., 1] * iz
    a = intr[0] * iz
    b = intr[1] * iz
    r = torch.stack([target[..., 0].reshape(E, P).to(dt) - (intr[0] * xz + intr[2]),
                     target[..., 1].reshape(E, P).to(dt) - (intr[1] * yz + intr[3])], -1)
    wgt = weight.reshape(E, P, 2).to(dt) * valid[..., None].to(dt)
    if huber is not None and huber > 0:
        rn = r.norm(dim=-1, keepdim=True)
        wgt = wgt * torch.where(rn > huber, huber / rn.clamp_min(1e-12), torch.ones_like(rn))
    r = torch.where(valid[..., None], r, torch.zeros_like(r))
    sw = wgt.sqrt()
    rs = r * sw
    # rows of d(pixel)/d(Xw_h) = Jproj R_j^T (columns c0, c1, c2 of R_j), scaled by sqrt(w)
    c0, c1, c2 = Rj[:, None, :, 0], Rj[:, None, :, 1], Rj[:, None, :, 2]     # (E, 1, 3)
    sa = a * sw[..., 0]
    sb = b * sw[..., 1]
    M = torch.stack([sa[..., None] * (c0 - xz[..., None] * c2),
                     sb[..., None] * (c1 - yz[..., None] * c2)], 2)          # (E, P, 2, 3)
    # pose Jacobian: [d m, Xw x m]  (left world-frame perturbation, xi = (t, w))
    Jp = torch.empty(E, P, 2, 6, dtype=dt, device=disps.device)
    torch.mul(M, d[..., None, None], out=Jp[..., :3])
    Xe = Xw[:, :, None, :]
    Jp[..., 3] = Xe[..., 1] * M[..., 2] - Xe[..., 2] * M[..., 1]
    Jp[..., 4] = Xe[..., 2] * M[..., 0] - Xe[..., 0] * M[..., 2]
    Jp[..., 5] = Xe[..., 0] * M[..., 1] - Xe[..., 1] * M[..., 0]
    tx, ty, tz = tji[:, None, 0], tji[:, None, 1], tji[:, None, 2]
    Jd = torch.stack([sa * (tx - xz * tz), sb * (ty - yz * tz)], -1)       # (E, P, 2)
    return rs, wgt, Jp, Jd


def disparity_normal_equations(poses: torch.Tensor, disps: torch.Tensor, intr,
                               ii: torch.Tensor, jj: torch.Tensor, target: torch.Tensor,
                               weight: torch.Tensor, huber: Optional[float] = None
                               ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel disparity normal equations of Eq. 1 with poses FIXED.

    Returns ``H_dd`` (N, h, w) = sum_e J_d^T Sigma J_d and ``g_d`` (N, h, w) =
    sum_e J_d^T Sigma r for every keyframe (zero where it is not an edge source);
    the Gauss-Newton disparity step is ``g_d / H_dd``. For DSPO (Eq. 2), which
    adds its own diagonal terms before dividing.
    """
    N, h, w = disps.shape
    rs, _, _, Jd = _edge_terms(poses, disps, intr, ii, jj, target, weight, huber)
    c = (Jd * Jd).sum(-1)
    b = (Jd * rs).sum(-1)
    H = torch.zeros(N, h * w, dtype=disps.dtype, device=disps.device)
    g = torch.zeros_like(H)
    H.index_add_(0, ii, c)
    g.index_add_(0, ii, b)
    return H.reshape(N, h, w), g.reshape(N, h, w)


def _fixed_mask(fixed, N, device) -> torch.Tensor:
    if torch.is_tensor(fixed) and fixed.dtype == torch.bool:
        return fixed.to(device)
    m = torch.zeros(N, dtype=torch.bool, device=device)
    m[: int(fixed)] = True
    return m


EDGE_CHUNK = 12         # edges whose Jacobians are built at once (bounds the BA's memory)
GRAM_CHUNK = 1 << 18    # elements of the padded coupling blocks built at once (1 MiB float32)


# tracking.ba_backend (config.BA_BACKENDS): "cpp" the C++/OpenMP kernel (ba_kernels.h, CPU
# float32), "torch" the reference below (any device), "auto" the kernel where it applies
_backend = {"requested": "auto"}


def use_backend(name: str, device: torch.device) -> None:
    """Select how the per-edge blocks are built (``tracking.ba_backend``): the process's
    BA runs (tracker, loop closer, global BA) all use it. On a CPU ``device`` the kernel is
    loaded (built on first use) now, not at the first keyframe; "cpp" must load."""
    if name not in BA_BACKENDS:
        raise ValueError(f"tracking.ba_backend must be one of {', '.join(BA_BACKENDS)}")
    _backend["requested"] = name
    if device.type == "cpu" or name == "cpp":
        _kernel()


def _kernel():
    """(the compiled module or None for the torch path, why): ``native`` keeps the module
    (built on first use) and a failure to build; "cpp" raises it."""
    requested = _backend["requested"]
    if requested == "torch":
        return None, "torch: as configured"
    try:
        return native.load_extension(), f"cpp: {requested}"
    except native.KernelBuildError as e:
        if requested == "cpp":
            raise
        return None, f"torch: auto, the C++ kernel did not load ({e})"


def backend_in_use(device: torch.device) -> str:
    """"cpp: ..." or "torch: ..." with why: what builds the BA terms of tensors on
    ``device`` in this process."""
    return f"torch: {device.type} device" if device.type != "cpu" else _kernel()[1]


def _edge_blocks(poses, disps, intr, ii, jj, target, weight, huber):
    """Per-edge pose blocks H_e = Jp^T W Jp (E, 6, 6) and v_e = Jp^T W r (E, 6), the
    pose-disparity couplings a_e (E, P, 6), disparity diagonals c_e and right-hand sides
    b_e (E, P), and the cost info: the C++ kernel for CPU float32 disparities (when the
    backend allows), else :func:`_edge_blocks_torch`."""
    ext = _kernel()[0] if disps.device.type == "cpu" and disps.dtype == torch.float32 else None
    if ext is None:
        return _edge_blocks_torch(poses, disps, intr, ii, jj, target, weight, huber)
    E = len(ii)
    N, h, w = disps.shape
    Ti, Tj = poses[ii], poses[jj]
    Gij = se3_inverse(Tj) @ Ti
    geo = torch.cat([Gij[:, :3, :3].reshape(E, 9), Gij[:, :3, 3], Ti[:, :3, :3].reshape(E, 9),
                     Ti[:, :3, 3], Tj[:, :3, :3].reshape(E, 9)], 1).float().contiguous()
    He, ve, ae, ce, be, st = ext.ba_edge_blocks(
        geo, intr_tensor(intr, torch.float32, disps.device).contiguous(),
        disps[ii].contiguous(), target.float().contiguous(), weight.float().contiguous(),
        h, w, float(huber or 0.0))
    cost, wsum = float(st[:, 0].sum()), float(st[:, 1].sum())
    info = BAInfo(cost=cost, rms=(cost / max(wsum, 1e-12)) ** 0.5, n_valid=int(st[:, 2].sum()))
    return He, ve, ae, ce, be, info


def _edge_blocks_torch(poses, disps, intr, ii, jj, target, weight, huber):
    """The reference of :func:`_edge_blocks` in torch (any device), EDGE_CHUNK edges at a
    time."""
    E = len(ii)
    P = disps.shape[1] * disps.shape[2]
    opts = dict(dtype=disps.dtype, device=disps.device)
    He, ve = torch.empty(E, 6, 6, **opts), torch.empty(E, 6, **opts)
    ae, ce, be = torch.empty(E, P, 6, **opts), torch.empty(E, P, **opts), torch.empty(E, P, **opts)
    cost, wsum, n_valid = 0.0, 0.0, 0
    for s in range(0, E, EDGE_CHUNK):
        sl = slice(s, min(s + EDGE_CHUNK, E))
        rs, wgt, Jp, Jd = _edge_terms(poses, disps, intr, ii[sl], jj[sl], target[sl],
                                      weight[sl], huber)
        e = rs.shape[0]
        cost += float((rs * rs).sum())
        wsum += float(wgt.sum())
        n_valid += int((wgt.sum(-1) > 0).sum())
        Jf = Jp.reshape(e, P * 2, 6)
        JfT = Jf.transpose(1, 2)
        torch.matmul(JfT, Jf, out=He[sl])                                # (e, 6, 6)
        ve[sl] = (JfT @ rs.reshape(e, P * 2, 1))[..., 0]                 # (e, 6)
        torch.mul(Jp[:, :, 0], Jd[:, :, 0:1], out=ae[sl])                # (e, P, 6)
        ae[sl] += Jp[:, :, 1] * Jd[:, :, 1:2]
        torch.sum(Jd * Jd, -1, out=ce[sl])                               # (e, P) x 2
        torch.sum(Jd * rs, -1, out=be[sl])
        del rs, wgt, Jp, Jd, Jf, JfT
    info = BAInfo(cost=cost, rms=(cost / max(wsum, 1e-12)) ** 0.5, n_valid=n_valid)
    return He, ve, ae, ce, be, info


def ba_step(poses: torch.Tensor, disps: torch.Tensor, intr, ii: torch.Tensor, jj: torch.Tensor,
            target: torch.Tensor, weight: torch.Tensor, fixed: Union[int, torch.Tensor] = 1,
            huber: Optional[float] = None, lm: float = 1e-4, ep: float = 1e-3,
            disp_damping: float = 1e-4, optimize_disps: Optional[torch.Tensor] = None,
            ) -> Tuple[torch.Tensor, torch.Tensor, BAInfo]:
    """One Gauss-Newton (LM-damped) iteration of Eq. 1 (DBA).

    poses (N,4,4) float64 c2w, disps (N,h,w), intr (fx,fy,cx,cy) at BA res,
    ii/jj (E,) long, target (E,h,w,2) absolute BA-pixel coordinates, weight
    (E,h,w,2) confidences. ``fixed``: number of leading poses kept fixed (gauge)
    or a boolean mask (N,). ``optimize_disps``: optional boolean mask (N,) of
    keyframes whose disparities may change (default: all edge sources).
    Returns updated (poses, disps, info).
    """
    # Eq. 1 (DBA)
    device = disps.device
    N, h, w = disps.shape
    P = h * w
    E = len(ii)
    dt = disps.dtype
    ii = ii.to(device)
    jj = jj.to(device)
    He, ve, ae, ce, be, info = _edge_blocks(poses, disps, intr, ii, jj, target, weight, huber)
    C = torch.zeros(N, P, dtype=dt, device=device).index_add_(0, ii, ce)
    b = torch.zeros(N, P, dtype=dt, device=device).index_add_(0, ii, be)
    dmask = torch.zeros(N, dtype=torch.bool, device=device)
    dmask[ii] = True
    if optimize_disps is not None:
        dmask &= optimize_disps.to(device)
    # damping: relative (LM) plus a small absolute term so unobserved pixels stay put
    Cd = C * (1 + disp_damping) + disp_damping * (C.mean() + 1e-6)
    Cinv = torch.where(dmask[:, None], 1.0 / Cd, torch.zeros_like(Cd))

    # --- reduced pose system S = B - E C^-1 E^T, v_red = v - E C^-1 b
    Hd = He.to(torch.float64)
    B = torch.zeros(N, N, 6, 6, dtype=torch.float64, device=device)
    B.index_put_((ii, ii), Hd, accumulate=True)
    B.index_put_((jj, jj), Hd, accumulate=True)
    B.index_put_((ii, jj), -Hd, accumulate=True)
    B.index_put_((jj, ii), -Hd, accumulate=True)
    v = torch.zeros(N, 6, dtype=torch.float64, device=device)
    v.index_add_(0, ii, ve.to(torch.float64))
    v.index_add_(0, jj, -ve.to(torch.float64))

    # E C^-1 E^T: Gram matrices of the couplings of all edges that share a source
    # keyframe, one batched matmul over sources (edges padded into slots)
    src, inv = torch.unique(ii, return_inverse=True)                 # sources, edge -> src
    ns = len(src)
    order = torch.argsort(inv, stable=True)
    counts = torch.bincount(inv, minlength=ns)
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.empty_like(inv)
    slot[order] = torch.arange(E, device=device) - starts[inv[order]]
    M = int(counts.max())
    sqc = Cinv[src].sqrt()                                           # (ns, P)
    G = torch.empty(ns, M * 6, M * 6, dtype=dt, device=device)
    per = max(1, GRAM_CHUNK // (M * P * 6))          # sources per batch (bounds the memory)
    for s0 in range(0, ns, per):
        n = min(per, ns - s0)
        sel = ((inv >= s0) & (inv < s0 + n)).nonzero()[:, 0]
        A = torch.zeros(n, M, P, 6, dtype=dt, device=device)
        A[inv[sel] - s0, slot[sel]] = ae[sel] * sqc[inv[sel]][..., None]
        At = A.permute(0, 1, 3, 2).reshape(n, M * 6, P)
        torch.matmul(At, At.transpose(1, 2), out=G[s0:s0 + n])
        del A, At
    G = G.reshape(ns, M, 6, M, 6)                                    # (ns, M, 6, M, 6)
    same = inv[:, None] == inv[None, :]
    e1, e2 = same.nonzero(as_tuple=True)
    F = G[inv[e1], slot[e1], :, slot[e2], :].to(torch.float64)       # (npairs, 6, 6)
    i1, j1, j2 = ii[e1], jj[e1], jj[e2]
    B.index_put_((i1, i1), -F, accumulate=True)
    B.index_put_((i1, j2), F, accumulate=True)
    B.index_put_((j1, i1), F, accumulate=True)
    B.index_put_((j1, j2), -F, accumulate=True)
    bC = (b * Cinv)[ii]                                              # (E, P)
    ge = (ae.transpose(1, 2) @ bC[..., None])[..., 0].to(torch.float64)   # (E, 6)
    v.index_add_(0, ii, -ge)
    v.index_add_(0, jj, ge)

    free = ~_fixed_mask(fixed, N, device)
    nf = int(free.sum())
    dxi = torch.zeros(N, 6, dtype=torch.float64, device=device)
    if nf > 0:
        S = B[free][:, free].permute(0, 2, 1, 3).reshape(6 * nf, 6 * nf)
        rhs = v[free].reshape(-1)
        diag = torch.diagonal(S)
        S = S + torch.diag(lm * diag + ep)
        try:
            sol = torch.linalg.solve(S, rhs)
        except RuntimeError:
            sol = torch.linalg.lstsq(S, rhs[:, None]).solution[:, 0]
        if torch.isfinite(sol).all():
            dxi[free] = sol.reshape(nf, 6)

    # --- back-substitution for the disparities
    dxi_f = dxi.to(dt)
    rel = dxi_f[ii] - dxi_f[jj]                                      # (E, 6)
    Ed = (ae @ rel[:, :, None])[..., 0]                              # (E, P)
    Etx = torch.zeros(N, P, dtype=dt, device=device).index_add_(0, ii, Ed)
    dd = (b - Etx) * Cinv
    dd = torch.where(torch.isfinite(dd), dd, torch.zeros_like(dd))
    new_disps = (disps.reshape(N, P) + dd).clamp_min(MIN_DISP).reshape(N, h, w)
    new_poses = se3_exp(dxi) @ poses
    return new_poses, new_disps, info


def bundle_adjust(poses, disps, intr, ii, jj, target, weight, iters: int = 4, fixed=1,
                  huber=None, rtol: float = 0.0, **kw):
    """Run up to ``iters`` BA iterations; returns (poses, disps, list[BAInfo]).

    With ``rtol > 0`` it stops once an iteration lowered the cost by less than
    that fraction (not when the cost rose: Gauss-Newton may need to recover)."""
    infos = []
    for _ in range(iters):
        poses, disps, info = ba_step(poses, disps, intr, ii, jj, target, weight, fixed=fixed,
                                     huber=huber, **kw)
        infos.append(info)
        if rtol > 0 and len(infos) >= 2 and \
                0 <= infos[-2].cost - info.cost < rtol * max(infos[-2].cost, 1e-12):
            break
    return poses, disps, infos


def ba_cost(poses, disps, intr, ii, jj, target, weight, huber=None) -> float:
    rs, _, _, _ = _edge_terms(poses, disps, intr, ii, jj, target, weight, huber)
    return float((rs * rs).sum())


# ------------------------------------------------------------ pose-only GN
def pose_only_refine(T_ref: torch.Tensor, disp_ref: torch.Tensor, T_cur: torch.Tensor, intr,
                     target: torch.Tensor, weight: torch.Tensor, iters: int = 5,
                     huber: Optional[float] = None, lm: float = 1e-4, ep: float = 1e-3
                     ) -> Tuple[torch.Tensor, BAInfo]:
    """Refine the pose ``T_cur`` of a frame against the flow from a reference
    keyframe (pose ``T_ref``, disparity ``disp_ref`` (h,w)) into it: the target
    block of Eq. 1 with the keyframe fixed. Returns (T_cur, info of last iter)."""
    return pose_only_refine_multi(T_ref[None], disp_ref[None], T_cur, intr, target[None],
                                  weight[None], iters, huber, lm, ep)


def _pose_only_system(pw, d, tgt, w0, T, k4, huber, dmin):
    """Normal equations of the motion-only problem for a batch of frames (the target-pose
    block of Eq. 1): world points ``pw`` (N, M, 3) (homogeneous, scale ``d`` (N, M)),
    targets / weights (N, M, 2), frame poses ``T`` (N, 4, 4) float64 with the perturbation on
    the right. Returns H (N, 6, 6) and g (N, 6) float64, cost, weight sum and valid count (N,)."""
    dt = pw.dtype
    fx, fy, cx, cy = k4
    X = (pw - T[:, None, :3, 3].to(dt) * d[..., None]) @ T[:, :3, :3].to(dt)  # R^T (p - t d)
    z = X[..., 2]
    valid = z > dmin
    iz = 1.0 / z.clamp_min(1e-6)
    xz, yz = X[..., 0] * iz, X[..., 1] * iz
    r = tgt - torch.stack([fx * xz + cx, fy * yz + cy], -1)
    wgt = w0 * valid[..., None]
    if huber is not None and huber > 0:
        rn = r.norm(dim=-1, keepdim=True)
        wgt = wgt * torch.where(rn > huber, huber / rn.clamp_min(1e-12), torch.ones_like(rn))
    r = torch.where(valid[..., None], r, torch.zeros_like(r))
    wr = wgt * r
    cost = (wr * r).sum((1, 2))
    wsum = wgt.sum((1, 2))
    n_valid = (wgt.sum(-1) > 0).sum(1)
    # d(pixel)/d(dx), dx = (t, w) on the right: X' = X - (w x X + t d)
    di = d * iz
    zero = torch.zeros_like(di)
    Ju = fx * torch.stack([-di, zero, xz * di, xz * yz, -(1 + xz * xz), yz], -1)
    Jv = fy * torch.stack([zero, -di, yz * di, 1 + yz * yz, -xz * yz, -xz], -1)
    H = (Ju * wgt[..., :1]).transpose(1, 2) @ Ju + (Jv * wgt[..., 1:]).transpose(1, 2) @ Jv
    g = (Ju.transpose(1, 2) @ wr[..., :1] + Jv.transpose(1, 2) @ wr[..., 1:])[..., 0]
    return H.to(torch.float64), g.to(torch.float64), cost, wsum, n_valid


def _lift(T_refs: torch.Tensor, disp_refs: torch.Tensor, q: torch.Tensor, dt):
    """World points (homogeneous: R q + t d, scale d) of keyframes (..., 4, 4) with
    disparities (..., h, w): ((..., P, 3), (..., P))."""
    dk = disp_refs.reshape(*disp_refs.shape[:-2], -1)
    R = T_refs[..., :3, :3].to(dt)
    t = T_refs[..., :3, 3].to(dt)
    return (torch.einsum("...ab,bp->...pa", R, q) + t[..., None, :] * dk[..., None]), dk


def pose_only_refine_multi(T_refs: torch.Tensor, disp_refs: torch.Tensor, T_cur: torch.Tensor,
                           intr, targets: torch.Tensor, weights: torch.Tensor, iters: int = 5,
                           huber: Optional[float] = None, lm: float = 1e-4, ep: float = 1e-3
                           ) -> Tuple[torch.Tensor, BAInfo]:
    """Motion-only alignment of a frame against K fixed keyframes (poses (K, 4, 4),
    disparities (K, h, w)) through the flows keyframe k -> frame (targets/weights
    (K, h, w, 2)): the target-pose block of Eq. 1 summed over the K edges.

    The keyframes' points are lifted to the world once (homogeneous, scale d); each
    Gauss-Newton iteration then only projects them into the frame, with the frame's pose
    perturbed on the right (``T <- T exp(dx)``, camera-frame Jacobian) and cells of zero
    weight left out. Residual, weights and Huber are those of the BA (:func:`_edge_terms`)."""
    dev, dt = disp_refs.device, disp_refs.dtype
    K, h, w = disp_refs.shape
    k4 = intr_tensor(intr, dt, dev)
    keep = weights.reshape(-1, 2).sum(-1) > 0
    pw, dk = _lift(T_refs, disp_refs, _rays(h, w, k4), dt)
    pw, d = pw.reshape(-1, 3)[keep][None], dk.reshape(-1)[keep][None]
    tgt = targets.reshape(-1, 2)[keep].to(dt)[None]
    w0 = weights.reshape(-1, 2)[keep].to(dt)[None]
    T = T_cur.to(torch.float64).clone()
    dmin = 1e-3 * d.clamp_min(1e-6)
    info = None
    for _ in range(iters):
        H, g, cost, wsum, n_valid = _pose_only_system(pw, d, tgt, w0, T[None], k4, huber, dmin)
        cost, wsum = float(cost[0]), float(wsum[0])
        info = BAInfo(cost, (cost / max(wsum, 1e-12)) ** 0.5, int(n_valid[0]))
        if wsum <= 0:
            break
        H = H[0] + torch.diag(lm * torch.diagonal(H[0]) + ep)
        try:
            dx = torch.linalg.solve(H, g[0])
        except RuntimeError:
            break
        if not torch.isfinite(dx).all():
            break
        T = T @ se3_exp_one(dx)
        if float(dx.norm()) < 1e-6:
            break
    return T, info


def pose_only_refine_batch(T_refs: torch.Tensor, disp_refs: torch.Tensor, T_cur: torch.Tensor,
                           intr, targets: torch.Tensor, weights: torch.Tensor,
                           iters: torch.Tensor, huber: Optional[float] = None, lm: float = 1e-4,
                           ep: float = 1e-3) -> torch.Tensor:
    """:func:`pose_only_refine_multi` for N frames at once (the trajectory filler, which
    sizes the batches): keyframe poses (N, K, 4, 4), disparities (N, K, h, w), frame poses
    (N, 4, 4), flows / weights (N, K, h, w, 2) (an edge a frame lacks has zero weight) and
    iterations per frame (N,). Same steps and stopping rules per frame, vectorised over
    frames. Returns the refined poses (N, 4, 4) float64."""
    N, K, h, w = disp_refs.shape
    dev, dt = disp_refs.device, disp_refs.dtype
    k4 = intr_tensor(intr, dt, dev)
    pw, dk = _lift(T_refs, disp_refs, _rays(h, w, k4), dt)
    pw, d = pw.reshape(N, -1, 3), dk.reshape(N, -1)
    tgt, w0 = targets.reshape(N, -1, 2).to(dt), weights.reshape(N, -1, 2).to(dt)
    dmin = 1e-3 * d.clamp_min(1e-6)
    T = T_cur.to(torch.float64).clone()
    limit = torch.as_tensor(iters, device=dev).reshape(N)
    active = torch.ones(N, dtype=torch.bool, device=dev)
    for it in range(int(limit.max()) if N else 0):
        idx = (active & (limit > it)).nonzero()[:, 0]
        if len(idx) == 0:
            break
        H, g, _, wsum, _ = _pose_only_system(pw[idx], d[idx], tgt[idx], w0[idx], T[idx], k4,
                                             huber, dmin[idx])
        H = H + torch.diag_embed(lm * torch.diagonal(H, dim1=-2, dim2=-1) + ep)
        dx, bad = torch.linalg.solve_ex(H, g)
        ok = (wsum > 0) & (bad == 0) & torch.isfinite(dx).all(-1)
        T[idx[ok]] = T[idx[ok]] @ se3_exp(dx[ok])
        active[idx[~ok | (dx.norm(dim=-1) < 1e-6)]] = False
    return T
