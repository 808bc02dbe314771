"""DSPO (Eq. 2-3) on a synthetic window: scale/shift recovery and a textureless wall."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.tracking.dense_ba import bundle_adjust, reproject
from splat_slam_ros.tracking.dspo import DspoPrior, dspo_step, make_depth_prior
from splat_slam_ros.tracking.mono_depth import MonoDepthModel
from test_proxy_depth import BA, TRACK, pose  # the same cameras and trajectory

ROOM = [((0, 0, 1), 5.0, None), ((1, 0, 0), -2.5, None), ((1, 0, 0), 2.5, None),
        ((0, 1, 0), 1.2, None), ((0, 1, 0), -1.5, None),
        ((0, 0, 1), 2.5, ((-0.6, -0.5, 2.4), (0.4, 0.3, 2.6)))]
THETA0, GAMMA0 = 2.0, 0.08                    # mono disparity = (d - GAMMA0) / THETA0


def raycast(T, intr, H, W):
    fx, fy, cx, cy = intr.fx, intr.fy, intr.cx, intr.cy
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    dw = T[:3, :3] @ np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)]).reshape(3, -1)
    o = T[:3, 3]
    best = np.full(dw.shape[1], np.inf)
    for n, c, box in ROOM:
        n = np.asarray(n, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c - n @ o) / (n @ dw)
        ok = np.isfinite(t) & (t > 1e-6)
        if box is not None:
            X = o[:, None] + t * dw
            ok &= np.all((X >= np.asarray(box[0])[:, None]) & (X <= np.asarray(box[1])[:, None]), 0)
        best = np.where(ok & (t < best), t, best)
    return best.reshape(H, W)


class StandInMono(MonoDepthModel):
    """Test double: ground truth through a known affine map in disparity, plus 1 % noise.
    The image's first pixel carries the keyframe index."""

    def __init__(self, noise=0.01, seed=0):
        self.noise = noise
        self.rng = np.random.default_rng(seed)

    def predict(self, image):
        i = int(image[0, 0, 0])
        d = 1.0 / raycast(pose(i), TRACK, 240, 320)
        md = (d - GAMMA0) / THETA0 * (1 + self.noise * self.rng.standard_normal(d.shape))
        return (1.0 / md).astype(np.float32)


def window(n=6, seed=0):
    """GT poses/disparities at BA res, flow edges with a textureless wall (bad, low weight)."""
    g = torch.Generator().manual_seed(seed)
    poses = torch.from_numpy(np.stack([pose(i) for i in range(n)]))
    depth = np.stack([raycast(pose(i), BA, 30, 40) for i in range(n)])
    d_gt = torch.from_numpy(1.0 / depth).float()
    # wall = the right part of the back wall, in world coordinates
    v, u = np.mgrid[0:30, 0:40].astype(np.float64)
    wall = []
    for i in range(n):
        Xc = np.stack([(u - BA.cx) / BA.fx, (v - BA.cy) / BA.fy, np.ones_like(u)]) * depth[i]
        Xw = np.einsum("ab,bhw->ahw", pose(i)[:3, :3], Xc) + pose(i)[:3, 3][:, None, None]
        wall.append((np.abs(Xw[2] - 5.0) < 1e-6) & (Xw[0] > 0.6))
    wall = torch.from_numpy(np.stack(wall))
    ii, jj = [], []
    for i in range(n):
        for j in range(n):
            if i != j and abs(i - j) <= 2:
                ii.append(i)
                jj.append(j)
    ii, jj = torch.tensor(ii), torch.tensor(jj)
    uv, _ = reproject(poses, d_gt, (BA.fx, BA.fy, BA.cx, BA.cy), ii, jj)
    wl = wall[ii][..., None]
    noise = torch.randn(uv.shape, generator=g)
    target = uv + torch.where(wl, 2.0 * noise + 1.5, 0.1 * noise)        # flow fails on the wall
    weight = torch.where(wl, torch.full_like(uv, 0.01), torch.ones_like(uv))
    d0 = d_gt * (1 + 0.03 * torch.randn(d_gt.shape, generator=g))
    d0 = torch.where(wall, d_gt * 0.7, d0)                               # wrong init there
    return poses, d_gt, d0, wall, ii, jj, target, weight


def cfg():
    c = SlamConfig()
    c.depth.mono_model = "stand-in"
    return c


def images(n):
    out = {}
    for i in range(n):
        im = np.zeros((240, 320, 3), np.uint8)
        im[0, 0, 0] = i
        out[i] = im
    return out


def run(prior, rounds=4, iters=2):
    poses, d_gt, d0, wall, ii, jj, target, weight = window()
    intr = torch.tensor([BA.fx, BA.fy, BA.cx, BA.cy], dtype=torch.float32)
    P, D = poses.clone(), d0.clone()
    for _ in range(rounds):
        P, D, _ = bundle_adjust(P, D, intr, ii, jj, target, weight, iters=iters, fixed=2)
        if prior is not None:
            st = SimpleNamespace(kf_ids=list(range(len(P))), poses=P, disps=D, intr=intr,
                                 ii=ii, jj=jj, target=target, weight=weight,
                                 images=images(len(P)), fixed=2)
            out = prior(st)
            if out is not None:
                D = out
    rel = ((D - d_gt).abs() / d_gt)
    return rel, wall


def test_dspo_recovers_scale_shift_and_beats_dba_on_textureless_wall():
    rel_dba, wall = run(None)
    prior = make_depth_prior(cfg(), TRACK, mono_model=StandInMono())
    assert isinstance(prior, DspoPrior)
    rel_dspo, _ = run(prior)
    info = prior.last_info
    used = info.used
    assert used.sum() >= 4, info.used
    th, ga = info.theta[used], info.gamma[used]
    assert torch.all((th / THETA0 - 1).abs() < 0.02), th
    # the shift is an offset on disparity: within 2 % of the mean disparity (its own relative
    # error is larger because GAMMA0 is small next to d: the fit sees DBA's errors of d^l)
    mean_d = float(window()[1].mean())
    assert torch.all((ga - GAMMA0).abs() < 0.02 * mean_d), ga
    # the Eq. 3 initialisation was already close
    assert torch.all((info.theta0[used] / THETA0 - 1).abs() < 0.05)
    e_dba, e_dspo = rel_dba[wall].mean().item(), rel_dspo[wall].mean().item()
    assert e_dspo < 0.5 * e_dba, (e_dba, e_dspo)
    assert e_dspo < 0.03
    # elsewhere DSPO does not hurt
    assert rel_dspo[~wall].median() <= rel_dba[~wall].median() * 1.1 + 1e-3
    # the full-resolution mono depth is handed out once, for KeyframeData.mono_depth
    md = prior.take_mono_depth(3)
    assert md is not None and md.shape == (240, 320) and prior.take_mono_depth(3) is None


def test_dspo_step_limits():
    """No flow information -> d^h = theta m + gamma exactly (Eq. 3 fit on d^l); a strong flow
    term keeps the flow optimum; an unfitting mono depth leaves the keyframe alone."""
    poses, d_gt, d0, wall, ii, jj, target, weight = window()
    intr = torch.tensor([BA.fx, BA.fy, BA.cx, BA.cy], dtype=torch.float32)
    m = (d_gt - GAMMA0) / THETA0
    low = ~wall
    d_in = torch.where(wall, d_gt * 0.5, d_gt)
    zero_w = torch.zeros_like(weight)
    d, info = dspo_step(poses, d_in, intr, ii, jj, target, zero_w, m, low)
    assert info.used.all()
    np.testing.assert_allclose(d[wall].numpy(), d_gt[wall].numpy(), rtol=1e-4)
    np.testing.assert_array_equal(d[~wall].numpy(), d_in[~wall].numpy())      # d^l fixed
    np.testing.assert_allclose(info.theta.numpy(), THETA0, rtol=1e-4)
    np.testing.assert_allclose(info.gamma.numpy(), GAMMA0, rtol=1e-3)
    # strong, exact flow on the "wall" pixels: the flow wins over a wrong mono prior
    uv, _ = reproject(poses, d_gt, intr, ii, jj)
    strong = torch.full_like(weight, 100.0)
    m_bad = torch.where(wall, m * 1.3, m)
    d2, _ = dspo_step(poses, d_in, intr, ii, jj, uv, strong, m_bad, low, iters=4)
    err = ((d2 - d_gt).abs() / d_gt)[wall]
    assert err.max() < 0.01
    # mono unrelated to the scene: gate (Eq. 3 residual > mono_thresh) -> unchanged
    m_rand = torch.rand(d_gt.shape, generator=torch.Generator().manual_seed(1)) + 0.1
    d3, info3 = dspo_step(poses, d_in, intr, ii, jj, target, zero_w, m_rand, low)
    assert not info3.used.any()
    assert torch.equal(d3, d_in)


def test_dspo_off_without_mono_model():
    c = SlamConfig()
    assert make_depth_prior(c, TRACK) is None                 # no mono model configured
    c.depth.mono_model = "x.onnx"
    c.tracking.dspo = False
    assert make_depth_prior(c, TRACK) is None


def test_dspo_missing_model_is_a_clear_error(tmp_path):
    from splat_slam_ros.tracking.mono_depth import MonoDepthError
    c = SlamConfig()
    c.depth.mono_model = str(tmp_path / "missing.onnx")
    with pytest.raises(MonoDepthError, match="not found"):
        make_depth_prior(c, TRACK)
