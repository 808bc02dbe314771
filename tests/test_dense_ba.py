"""Dense BA (paper Eq. 1): Jacobians, convergence, Schur solve, DSPO normal equations."""
from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from splat_slam_ros.tracking.dense_ba import (_edge_terms, ba_cost, ba_step, bundle_adjust,
                                     disparity_normal_equations, induced_flow_distance,
                                     pose_only_refine, pose_only_refine_batch,
                                     pose_only_refine_multi, reproject)
from splat_slam_ros.geometry import (pixel_grid, project_homogeneous, se3_exp, se3_inverse,
                                     se3_log)
from splat_slam_ros.tracking.frontend import observed_weight

H, W = 24, 32
INTR = torch.tensor([28.0, 28.0, 15.5, 11.5])


def scene(n: int, seed: int = 0, dtype=torch.float32):
    """``n`` cameras moving sideways around a wavy surface ~1 unit away."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.zeros(n, 6, dtype=torch.float64)
    xi[:, 0] = torch.linspace(0, 0.4, n)
    xi[:, 1] = 0.08 * torch.sin(torch.arange(n, dtype=torch.float64))
    xi[:, 2] = 0.05 * torch.cos(torch.arange(n, dtype=torch.float64))
    xi[:, 3:] = 0.03 * torch.randn(n, 3, dtype=torch.float64, generator=g)
    poses = se3_exp(xi)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    base = 0.9 + 0.35 * torch.sin(4 * xx) * torch.cos(3 * yy) + 0.2 * xx
    disps = torch.stack([base * (1 + 0.05 * k) for k in range(n)]).to(dtype)
    return poses, disps


def all_edges(n: int, radius: int):
    ii, jj = zip(*[(i, j) for i in range(n) for j in range(n) if i != j and abs(i - j) <= radius])
    return torch.tensor(ii), torch.tensor(jj)


def test_projection_jacobian_matches_finite_differences():
    X = torch.tensor([[0.3, -0.2, 1.5], [-1.0, 0.4, 2.0]], dtype=torch.float64)
    intr = INTR.double()
    _, J = project_homogeneous(X, intr)
    eps = 1e-6
    for k in range(3):
        dX = torch.zeros(3, dtype=torch.float64)
        dX[k] = eps
        num = (project_homogeneous(X + dX, intr)[0] - project_homogeneous(X - dX, intr)[0]) / (
            2 * eps)
        assert torch.allclose(num, J[..., k], atol=1e-6)


def test_ba_jacobians_match_finite_differences():
    poses, disps = scene(4, dtype=torch.float64)
    ii, jj = all_edges(4, 2)
    tgt, _ = reproject(poses, disps, INTR.double(), ii, jj)
    tgt = tgt + 0.3                                # non-zero residuals
    wgt = torch.ones(len(ii), H, W, 2, dtype=torch.float64)
    rs, _, Jp, Jd = _edge_terms(poses, disps, INTR.double(), ii, jj, tgt, wgt, None)
    eps = 1e-6
    for e in (0, len(ii) - 1):
        for k in range(6):
            dx = torch.zeros(6, dtype=torch.float64)
            dx[k] = eps
            for who, sign in ((ii[e], 1.0), (jj[e], -1.0)):
                p2 = poses.clone()
                p2[who] = se3_exp(dx) @ p2[who]
                p3 = poses.clone()
                p3[who] = se3_exp(-dx) @ p3[who]
                r2 = _edge_terms(p2, disps, INTR.double(), ii, jj, tgt, wgt, None)[0]
                r3 = _edge_terms(p3, disps, INTR.double(), ii, jj, tgt, wgt, None)[0]
                num = -(r2[e] - r3[e]) / (2 * eps)          # d(pixel)/d(xi)
                ana = sign * Jp[e, :, :, k]
                assert torch.allclose(num, ana, atol=1e-5 * (1 + ana.abs().max())), (e, k, who)
        d2, d3 = disps.clone(), disps.clone()
        d2[ii[e]] += eps
        d3[ii[e]] -= eps
        r2 = _edge_terms(poses, d2, INTR.double(), ii, jj, tgt, wgt, None)[0]
        r3 = _edge_terms(poses, d3, INTR.double(), ii, jj, tgt, wgt, None)[0]
        assert torch.allclose(-(r2[e] - r3[e]) / (2 * eps), Jd[e], atol=1e-6)


def _align_scale(P, D, P_true, D_true):
    """Scale that maps the estimate onto the truth (first pose shared)."""
    return float((D.mean() / D_true.mean()))


def test_two_view_converges_up_to_scale():
    poses, disps = scene(2)
    ii, jj = all_edges(2, 1)
    tgt, _ = reproject(poses, disps, INTR, ii, jj)
    wgt = torch.ones(len(ii), H, W, 2)
    g = torch.Generator().manual_seed(3)
    p0 = poses.clone()
    p0[1] = se3_exp(0.03 * torch.randn(6, dtype=torch.float64, generator=g)) @ poses[1]
    d0 = disps * (1 + 0.3 * torch.rand(disps.shape, generator=g))
    P, D, infos = bundle_adjust(p0, d0, INTR, ii, jj, tgt, wgt, iters=12, fixed=1)
    assert infos[-1].rms < 1e-3 < infos[0].rms
    s = _align_scale(P, D, poses, disps)
    # rotation exact; baseline (from the fixed camera 0) up to the monocular scale
    assert torch.allclose(P[1, :3, :3], poses[1, :3, :3], atol=1e-4)
    assert torch.allclose((P[1, :3, 3] - P[0, :3, 3]) * s, poses[1, :3, 3] - poses[0, :3, 3],
                          atol=1e-3)
    assert torch.allclose(D / s, disps, rtol=2e-3, atol=2e-3)


def test_multi_view_converges_with_gauge_fixed():
    n = 6
    poses, disps = scene(n, seed=1)
    ii, jj = all_edges(n, 2)
    tgt, _ = reproject(poses, disps, INTR, ii, jj)
    wgt = torch.ones(len(ii), H, W, 2)
    g = torch.Generator().manual_seed(5)
    p0 = se3_exp(0.02 * torch.randn(n, 6, dtype=torch.float64, generator=g)) @ poses
    p0[:2] = poses[:2]                                         # two fixed poses fix the scale
    d0 = disps * (1 + 0.3 * (torch.rand(disps.shape, generator=g) - 0.5))
    P, D, infos = bundle_adjust(p0, d0, INTR, ii, jj, tgt, wgt, iters=10, fixed=2)
    assert infos[-1].rms < 1e-3
    assert (P[:, :3, 3] - poses[:, :3, 3]).abs().max() < 1e-3
    assert (D - disps).abs().max() < 5e-3
    assert ba_cost(P, D, INTR, ii, jj, tgt, wgt) < 1e-4 * ba_cost(p0, d0, INTR, ii, jj, tgt, wgt)


def test_ba_step_is_the_same_built_in_small_chunks(monkeypatch):
    """The edge blocks (EDGE_CHUNK edges at a time) and the Schur Gram matrices (GRAM_CHUNK
    elements of coupling blocks at a time) bound the BA's memory; the step must not depend
    on how they are cut (uneven source degrees, a chunk boundary inside every group).

    Chunking only changes the order of the sums, so the test runs in float64 end to end
    (disparities, targets, weights, intrinsics): a reordered float64 sum differs by about
    n_terms x eps64 ~ 1e-16 x 1e4 relative, and the reduced camera system here has a
    condition number below 1e4, so the poses (entries <= 1, step ~ 0.02) agree to ~1e-8 of
    the step at worst. The bounds below (1e-9 absolute on the poses, 1e-9 relative on the
    depths and cost) hold with margin on any CPU, SIMD path or thread count; in float32 the
    same reasoning gives ~1e-3 relative, too loose to see a wrong chunk boundary."""
    from splat_slam_ros.tracking import dense_ba
    n = 7
    f64 = torch.float64
    poses, disps = scene(n, seed=3, dtype=f64)
    intr = INTR.double()
    ii, jj = all_edges(n, 3)
    keep = torch.arange(len(ii)) % 4 != 1                   # sources with 2..6 edges
    ii, jj = ii[keep], jj[keep]
    tgt, _ = reproject(poses, disps, intr, ii, jj)
    g = torch.Generator().manual_seed(11)
    wgt = torch.rand(len(ii), H, W, 2, generator=g, dtype=f64)
    p0 = se3_exp(0.02 * torch.randn(n, 6, dtype=f64, generator=g)) @ poses
    d0 = disps * (1 + 0.2 * (torch.rand(disps.shape, generator=g, dtype=f64) - 0.5))
    monkeypatch.setattr(dense_ba, "EDGE_CHUNK", 10 ** 6)
    monkeypatch.setattr(dense_ba, "GRAM_CHUNK", 10 ** 9)
    P1, D1, i1 = ba_step(p0, d0, intr, ii, jj, tgt, wgt, fixed=1, huber=1.0)
    monkeypatch.setattr(dense_ba, "EDGE_CHUNK", 5)
    monkeypatch.setattr(dense_ba, "GRAM_CHUNK", 1)           # one source per batch
    P2, D2, i2 = ba_step(p0, d0, intr, ii, jj, tgt, wgt, fixed=1, huber=1.0)
    assert D1.dtype == f64
    assert (P1 - p0).abs().max() > 1e-4                      # the step moved the poses
    assert (D1 - d0).abs().max() > 1e-4                      # ... and the disparities
    assert torch.allclose(P1, P2, atol=1e-9, rtol=0)
    assert torch.allclose(D1, D2, atol=0, rtol=1e-9)
    assert i1.cost == pytest.approx(i2.cost, rel=1e-9) and i1.n_valid == i2.n_valid


def test_robust_weights_limit_outliers():
    n = 4
    poses, disps = scene(n, seed=2)
    ii, jj = all_edges(n, 1)
    tgt, _ = reproject(poses, disps, INTR, ii, jj)
    bad = tgt.clone()
    g = torch.Generator().manual_seed(0)
    mask = torch.rand(bad.shape[:3], generator=g) < 0.1
    bad[mask] += 6.0                                           # 10 % gross outliers
    wgt = torch.ones(len(ii), H, W, 2)
    p0 = poses.clone()
    p0[2:] = se3_exp(torch.full((2, 6), 0.01, dtype=torch.float64)) @ poses[2:]
    errs = {}
    for huber in (None, 0.5):
        P, D, _ = bundle_adjust(p0, disps.clone(), INTR, ii, jj, bad, wgt, iters=10, fixed=2,
                                huber=huber)
        errs[huber] = float((P[:, :3, 3] - poses[:, :3, 3]).norm(dim=-1).max())
    assert errs[0.5] < 0.5 * errs[None]


def test_disparity_normal_equations_match_ba_with_fixed_poses():
    n = 3
    poses, disps = scene(n, seed=4, dtype=torch.float64)
    ii, jj = all_edges(n, 2)
    tgt, _ = reproject(poses, disps, INTR.double(), ii, jj)
    d0 = disps * 1.1
    wgt = torch.ones(len(ii), H, W, 2, dtype=torch.float64)
    Hdd, gd = disparity_normal_equations(poses, d0, INTR.double(), ii, jj, tgt, wgt)
    assert Hdd.shape == (n, H, W) and gd.shape == (n, H, W)
    # one Newton step on the separable disparity problem lands close to the truth
    d1 = d0 + gd / Hdd
    assert (d1 - disps).abs().max() < 0.1 * (d0 - disps).abs().max()
    # same as a BA step with every pose fixed (no damping)
    _, D, _ = ba_step(poses, d0, INTR.double(), ii, jj, tgt, wgt, fixed=n, disp_damping=0.0)
    assert torch.allclose(D, d1, atol=1e-8)


def test_pose_only_refine_recovers_frame_pose():
    poses, disps = scene(2, seed=6)
    ii, jj = torch.tensor([0]), torch.tensor([1])
    tgt, _ = reproject(poses, disps, INTR, ii, jj)
    wgt = torch.ones(H, W, 2)
    T0 = se3_exp(torch.tensor([0.02, -0.01, 0.015, 0.01, -0.02, 0.005],
                              dtype=torch.float64)) @ poses[1]
    T, info = pose_only_refine(poses[0], disps[0], T0, INTR, tgt[0], wgt, iters=8)
    assert torch.allclose(T, poses[1], atol=1e-4)
    assert info.rms < 1e-3


def test_pose_fit_ignores_keyframe_cells_its_edges_never_observed():
    """A new keyframe's cells that its one edge never saw (the view entering on fast motion)
    carry a filled-in disparity; the frame's flow is right there, so with every cell counted
    the fit bends the pose to that wrong depth. Weighted by the keyframe's confidence
    (observed_weight) they drop out and the pose is the true one."""
    poses, disps = scene(2, seed=6)
    ii, jj = torch.tensor([0]), torch.tensor([1])
    tgt, _ = reproject(poses, disps, INTR, ii, jj)           # the frame's flow: exact
    wgt = torch.ones(H, W, 2)
    conf = torch.ones(H, W)
    conf[:, W // 2:] = 0.0                                   # never observed by its edges ...
    d_ref = disps[0].clone()
    d_ref[:, W // 2:] *= 1.8                                 # ... and filled in wrong
    T0 = se3_exp(torch.tensor([0.01, -0.01, 0.01, 0.01, -0.01, 0.005],
                              dtype=torch.float64)) @ poses[1]
    err = lambda T: float(se3_log(se3_inverse(poses[1]) @ T)[:3].norm())
    T_all, _ = pose_only_refine(poses[0], d_ref, T0, INTR, tgt[0], wgt, iters=10)
    T_obs, info = pose_only_refine(poses[0], d_ref, T0, INTR, tgt[0],
                                   observed_weight(wgt, conf, 0.2), iters=10)
    assert err(T_all) > 0.02                      # bent by the filled-in half
    assert err(T_obs) < 1e-4 and info.rms < 1e-3
    # in proportion below the level, unchanged at and above it, and off at 0
    conf[0, 0], conf[0, 1] = 0.1, 0.5
    w = observed_weight(wgt, conf, 0.2)
    assert w[0, 0].tolist() == [0.5, 0.5] and w[0, 1].tolist() == [1.0, 1.0]
    assert w[0, -1].tolist() == [0.0, 0.0]
    assert torch.equal(observed_weight(wgt, conf, 0.0), wgt)
    assert torch.equal(observed_weight(wgt, None, 0.2), wgt)


def test_pose_only_refine_multi_two_keyframes_and_ba_residual():
    """The frame between two keyframes is found from both flows (one side's weights partly
    zero, noisy targets); the reported residual is the BA's (Eq. 1 with Huber) at the pose
    the iteration started from."""
    poses, disps = scene(3, seed=3)
    ii, jj = torch.tensor([0, 2]), torch.tensor([1, 1])
    tgt, _ = reproject(poses, disps, INTR, ii, jj)
    g = torch.Generator().manual_seed(1)
    tgt = tgt + 0.05 * torch.randn(tgt.shape, generator=g)
    wgt = torch.rand(2, H, W, 2, generator=g)
    wgt[0, : H // 2] = 0.0
    T0 = se3_exp(torch.tensor([0.03, 0.02, -0.02, -0.015, 0.02, 0.01],
                              dtype=torch.float64)) @ poses[1]
    T, info = pose_only_refine_multi(poses[[0, 2]], disps[[0, 2]], T0, INTR, tgt, wgt, iters=10,
                                     huber=0.5)
    assert torch.allclose(T, poses[1], atol=2e-3)
    assert info.rms < 0.1
    # one iteration reports the cost at T0: the same as _edge_terms / ba_cost
    P = torch.cat([poses[[0, 2]], T0[None]])
    _, info1 = pose_only_refine_multi(poses[[0, 2]], disps[[0, 2]], T0, INTR, tgt, wgt, iters=1,
                                      huber=0.5)
    cost = ba_cost(P, disps[[0, 2]], INTR, torch.tensor([0, 1]), torch.tensor([2, 2]), tgt, wgt,
                   huber=0.5)
    assert info1.cost == pytest.approx(cost, rel=1e-4)


def test_pose_only_refine_batch_is_the_per_frame_refinement():
    """The trajectory filler's batched solve gives each frame what pose_only_refine_multi
    gives it alone: frames with two edges, one edge (the other weighted 0), different
    iteration counts (frames stop at their own count while others go on)."""
    poses, disps = scene(5, seed=4)
    g = torch.Generator().manual_seed(2)
    refs, dsp, T0s, tgts, wgts, its, want = [], [], [], [], [], [], []
    for f in range(1, 4):                          # frame f between keyframes f-1 and f+1
        k = torch.tensor([f - 1, f + 1])
        tgt, _ = reproject(poses, disps, INTR, k, torch.tensor([f, f]))
        tgt = tgt + 0.05 * torch.randn(tgt.shape, generator=g)
        wgt = torch.rand(2, H, W, 2, generator=g)
        if f == 2:
            wgt[1] = 0.0                           # one edge only
        T0 = se3_exp(0.02 * torch.randn(6, dtype=torch.float64, generator=g)) @ poses[f]
        n_it = 3 + f
        want.append(pose_only_refine_multi(poses[k], disps[k], T0, INTR, tgt, wgt, iters=n_it,
                                           huber=0.5)[0])
        refs.append(poses[k]); dsp.append(disps[k]); T0s.append(T0)
        tgts.append(tgt); wgts.append(wgt); its.append(n_it)
    T = pose_only_refine_batch(torch.stack(refs), torch.stack(dsp), torch.stack(T0s), INTR,
                               torch.stack(tgts), torch.stack(wgts), torch.tensor(its),
                               huber=0.5)
    for f in range(3):
        assert torch.allclose(T[f], want[f], atol=1e-6), f
        assert not torch.allclose(T[f], T0s[f], atol=1e-3)          # it did move


def test_se3_exp_one_is_se3_exp():
    """The pose-only fit's one-twist exponential equals the batched one (small and large
    rotations, the small-angle branch included)."""
    from splat_slam_ros.geometry import se3_exp_one
    g = torch.Generator().manual_seed(2)
    xs = [torch.zeros(6, dtype=torch.float64), torch.tensor([0.1, -0.2, 0.3, 1e-7, 0, 2e-7],
                                                         dtype=torch.float64)]
    xs += [torch.randn(6, generator=g, dtype=torch.float64) * s for s in (0.01, 0.5, 2.0)]
    for x in xs:
        assert torch.allclose(se3_exp_one(x), se3_exp(x), atol=1e-12)
    assert se3_exp_one(xs[2].float()).dtype == torch.float32


def test_induced_distance_zero_for_identity_and_grows_with_motion():
    poses, disps = scene(3)
    P = poses.clone()
    P[1] = P[0]
    d = induced_flow_distance(P, disps, INTR, torch.tensor([0, 0]), torch.tensor([1, 2]))
    assert d[0] < 1e-4 and d[1] > 1.0


def test_ba_iteration_speed():
    """Reference point (notes/cpu-compute.md): ~25 ms per iteration for 8 keyframes at
    80x60 with 20 edges on 2 cores. Generous bound, the machine is shared."""
    h, w = 60, 80
    n = 8
    intr = torch.tensor([60.0, 60.0, 39.5, 29.5])
    poses = se3_exp(torch.cat([torch.linspace(0, 0.5, n)[:, None], torch.zeros(n, 5)], 1).double())
    disps = torch.ones(n, h, w)
    ii, jj = all_edges(n, 2)
    ii, jj = ii[:20], jj[:20]
    tgt, _ = reproject(poses, disps, intr, ii, jj)
    wgt = torch.ones(20, h, w, 2)
    old = torch.get_num_threads()
    torch.set_num_threads(1)          # what the tracker uses (tracking.threads)
    try:
        ba_step(poses, disps, intr, ii, jj, tgt, wgt, fixed=2)
        t0 = time.perf_counter()
        for _ in range(3):
            ba_step(poses, disps, intr, ii, jj, tgt, wgt, fixed=2)
        dt = (time.perf_counter() - t0) / 3
    finally:
        torch.set_num_threads(old)
    assert dt < 0.25, f"{dt * 1000:.0f} ms per BA iteration"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_ba_runs_on_cuda():
    poses, disps = scene(3)
    ii, jj = all_edges(3, 1)
    tgt, _ = reproject(poses, disps, INTR, ii, jj)
    dev = torch.device("cuda")
    P, D, _ = bundle_adjust(poses.to(dev), disps.to(dev), INTR.to(dev), ii.to(dev), jj.to(dev),
                            tgt.to(dev), torch.ones(len(ii), H, W, 2, device=dev), iters=2)
    assert P.device.type == "cuda" and torch.allclose(P.cpu(), poses, atol=1e-4)


def test_default_huber_resists_wrong_period_flow():
    """Flow matched at the wrong period of a repetitive texture: a block of cells off by a
    period (here 1.5 BA px, all the same way, forward and backward agreeing, so confident).
    With the default threshold (``tracking.robust_huber_px``, tracking px, over the BA
    downsampling) BA is pulled less than with the old 2-px threshold (docs/tracking.md
    "Robust weights")."""
    from splat_slam_ros.config import TrackingConfig
    tc = TrackingConfig()
    n = 4
    poses, disps = scene(n, seed=3)
    ii, jj = all_edges(n, 2)
    tgt, _ = reproject(poses, disps, INTR, ii, jj)
    bad = tgt.clone()
    bad[:, :, : W // 5, 0] += 1.5                  # the left fifth of every view
    wgt = torch.ones(len(ii), H, W, 2)
    p0 = poses.clone()
    p0[2:] = se3_exp(torch.full((2, 6), 0.01, dtype=torch.float64)) @ poses[2:]
    errs = {}
    for px in (2.0, tc.robust_huber_px):
        P, _, _ = bundle_adjust(p0, disps.clone(), INTR, ii, jj, bad, wgt, iters=15, fixed=2,
                                huber=px / tc.ba_downsample)
        errs[px] = float((P[:, :3, 3] - poses[:, :3, 3]).norm(dim=-1).max())
    assert errs[tc.robust_huber_px] < 0.6 * errs[2.0]


@pytest.fixture
def ba_backend():
    """Select tracking.ba_backend for one test, "auto" again after it."""
    from splat_slam_ros.tracking import dense_ba
    yield lambda name: dense_ba.use_backend(name, torch.device("cpu"))
    dense_ba.use_backend("auto", torch.device("cpu"))


def test_cpp_edge_blocks_are_the_torch_reference(ba_backend):
    """The C++ kernel's per-edge blocks (H_e, v_e, couplings, disparity diagonals and
    right-hand sides, cost) are the torch reference's: a width that is no multiple of the
    SIMD lanes (a partial last vector per row), an edge whose target camera looks the other
    way (every point behind it: no term) and one turned by 90 degrees (about half), zero
    weights, the robust weights on, float16 targets as the tracker stores flows."""
    from splat_slam_ros.tracking import dense_ba
    ba_backend("cpp")
    h, w, n = 20, 37, 5
    g = torch.Generator().manual_seed(5)
    xi = 0.05 * torch.randn(n, 6, dtype=torch.float64, generator=g)
    poses = se3_exp(xi)
    poses[3] = poses[0] @ se3_exp(torch.tensor([0, 0, 0, 0, np.pi, 0], dtype=torch.float64))
    poses[4] = poses[0] @ se3_exp(torch.tensor([0, 0, 0, 0, np.pi / 2, 0],
                                               dtype=torch.float64))
    disps = 0.4 + torch.rand(n, h, w, generator=g)
    intr = torch.tensor([30.0, 31.0, 18.0, 9.5])
    ii = torch.tensor([0, 1, 2, 0, 0, 2, 1])
    jj = torch.tensor([1, 2, 0, 3, 4, 1, 0])
    tgt, _ = reproject(se3_exp(0.01 * torch.randn(n, 6, dtype=torch.float64, generator=g))
                       @ poses, disps, intr, ii, jj)
    tgt = torch.nan_to_num(tgt, 0.0).half()
    wgt = torch.rand(len(ii), h, w, 2, generator=g)
    wgt[1, :5] = 0
    got = dense_ba._edge_blocks(poses, disps, intr, ii, jj, tgt, wgt, 0.5)
    ref = dense_ba._edge_blocks_torch(poses, disps, intr, ii, jj, tgt, wgt, 0.5)
    for name, a, b in zip(("H", "v", "a", "c", "b"), got[:5], ref[:5]):
        assert a.shape == b.shape, name
        scale = float(b.abs().max())
        assert scale > 0 and float((a.double() - b.double()).abs().max()) < 1e-4 * scale, name
    assert got[5].n_valid == ref[5].n_valid < len(ii) * h * w - w * 5   # some behind, zeros
    assert got[5].cost == pytest.approx(ref[5].cost, rel=1e-5)
    assert float(got[0][3].abs().max()) == 0.0                          # all behind camera j
    # one BA step either way
    ba_backend("torch")
    P1, D1, _ = ba_step(poses, disps, intr, ii, jj, tgt, wgt, fixed=1, huber=0.5)
    ba_backend("cpp")
    P2, D2, _ = ba_step(poses, disps, intr, ii, jj, tgt, wgt, fixed=1, huber=0.5)
    step = float((P1 - poses).abs().max())
    assert step > 1e-3       # the float32 reference's own rounding: ~2e-4 of the step here
    assert float((P1 - P2).abs().max()) < 1e-3 * step and torch.allclose(D1, D2, rtol=1e-3)


def test_ba_backend_is_chosen_by_config_and_reported(ba_backend):
    from splat_slam_ros.config import ConfigError, SlamConfig, load_config
    from splat_slam_ros.tracking import dense_ba
    from splat_slam_ros.tracking.tracker import Tracker
    from splat_slam_ros.types import Intrinsics
    K = Intrinsics(60.0, 60.0, 39.5, 29.5, 80, 64)
    cfg = SlamConfig()
    assert cfg.tracking.ba_backend == "auto"
    assert Tracker(cfg, K).keyframe_summary()["ba_backend"] == "cpp: auto"
    cfg.tracking.ba_backend = "torch"
    assert Tracker(cfg, K).keyframe_summary()["ba_backend"] == "torch: as configured"
    assert dense_ba.backend_in_use(torch.device("cuda")) == "torch: cuda device"
    with pytest.raises(ConfigError, match="tracking.ba_backend"):
        load_config(None, {"tracking.ba_backend": "cuda"})
