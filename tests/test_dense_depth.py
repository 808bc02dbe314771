"""Dense multi-view proxy depth (depth/dense_depth.py): triangulation from flow, the per-pixel
agreement of Eq. 6, and the estimator using it, on a textured plane seen from known poses."""
import cv2
import numpy as np
import torch

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.depth.dense_depth import (FlowCache, dense_depth, fuse_views,
                                              select_views, triangulate_flow)
from splat_slam_ros.depth.compose import SOURCE_MULTIVIEW
from splat_slam_ros.depth.proxy_depth import ProxyDepthEstimator
from splat_slam_ros.geometry import so3_exp
from splat_slam_ros.types import Intrinsics, KeyframeData, UpdateEvent

W, H = 192, 144
INTR = Intrinsics(fx=160.0, fy=160.0, cx=95.5, cy=71.5, width=W, height=H)
N = np.array([0.25, -0.1, 1.0]) / np.linalg.norm([0.25, -0.1, 1.0])   # plane n.X = D (world)
D = 2.0


def _K(fx, cx, cy):
    return np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1.0]])


def _texture(seed=0):
    """The plane's texture as seen by a wide reference camera at the world origin."""
    rng = np.random.default_rng(seed)
    t = rng.random((2 * H, 2 * W, 3)).astype(np.float32) * 255
    t = cv2.GaussianBlur(t, (0, 0), 1.2)
    return np.clip(t, 0, 255).astype(np.uint8)


def view(T, tex):
    """Image and true z-depth of the plane from camera-to-world pose T."""
    Tinv = np.linalg.inv(T)                      # world (= reference camera) -> camera
    R, t = Tinv[:3, :3], Tinv[:3, 3]
    Kr = _K(INTR.fx, W - 0.5, H - 0.5)
    Hm = _K(INTR.fx, INTR.cx, INTR.cy) @ (R + np.outer(t, N) / D) @ np.linalg.inv(Kr)
    img = cv2.warpPerspective(tex, Hm, (W, H), flags=cv2.INTER_LINEAR)
    nc, dc = R @ N, D + (R @ N) @ t
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], -1)
    return img, (dc / (rays @ nc)).astype(np.float32)


def pose(x, y, rot=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, :3] = so3_exp(torch.tensor(rot, dtype=torch.float64)).numpy()
    T[:3, 3] = [x, y, 0.0]
    return T


POSES = [pose(0, 0), pose(0.12, 0.0, (0, 0.02, 0)), pose(-0.12, 0.02), pose(0.0, 0.1),
         pose(0.06, -0.1, (0.01, 0, 0)), pose(0.2, 0.05)]


def grey(img):
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


def test_triangulate_exact_flow_gives_the_true_depth():
    tex = _texture()
    _, d0 = view(POSES[0], tex)
    _, _ = view(POSES[1], tex)
    # exact flow 0 -> 1 from the true depth
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    X = np.stack([(u - INTR.cx) / INTR.fx * d0, (v - INTR.cy) / INTR.fy * d0, d0], -1)
    rel = np.linalg.inv(POSES[1]) @ POSES[0]
    Y = X @ rel[:3, :3].T + rel[:3, 3]
    flow = np.stack([INTR.fx * Y[..., 0] / Y[..., 2] + INTR.cx - u,
                     INTR.fy * Y[..., 1] / Y[..., 2] + INTR.cy - v], -1)
    d, par = triangulate_flow(torch.from_numpy(flow).float(), torch.from_numpy(POSES[0]),
                              torch.from_numpy(POSES[1]), INTR)
    ok = d > 0
    assert ok.float().mean() > 0.8                  # the rest leaves image 1
    assert torch.allclose(d[ok], torch.from_numpy(d0)[ok], rtol=1e-3)
    assert float(par[ok].min()) > np.radians(1.0)
    # a match outside image k, or a point behind it, gives no depth
    bad = torch.from_numpy(flow).float().clone()
    bad[..., 0] += 10 * W
    assert (triangulate_flow(bad, torch.from_numpy(POSES[0]), torch.from_numpy(POSES[1]),
                             INTR)[0] == 0).all()


def test_fuse_views_keeps_pixels_where_enough_views_agree():
    true = 2.0
    depths = torch.full((4, 2, 3), true)
    par = torch.full((4, 2, 3), 0.05)
    depths[0, 0, 0] = 3.0                   # one outlier: ignored, 3 views agree
    depths[1:, 0, 1] = torch.tensor([2.5, 3.0, 3.5])    # nobody agrees with anybody
    par[1:, 0, 2] = 0.001                   # only one view has enough parallax
    depths[2, 1, 0] = 2.02                  # within eta: averaged, weighted by parallax^2
    par[2, 1, 0] = 0.1
    d, cnt = fuse_views(depths, par, eta=0.02, min_views=2, min_parallax=0.01)
    assert cnt[0, 0] == 3 and d[0, 0] == torch.tensor(true)
    assert cnt[0, 1] <= 1 and d[0, 1] == 0
    assert cnt[0, 2] == 1 and d[0, 2] == 0
    expect = (3 * 0.05 ** 2 * 2.0 + 0.1 ** 2 * 2.02) / (3 * 0.05 ** 2 + 0.1 ** 2)
    assert cnt[1, 0] == 4 and abs(float(d[1, 0]) - expect) < 1e-5


def test_dense_depth_from_real_flow_on_a_textured_plane():
    tex = _texture()
    imgs = [view(T, tex) for T in POSES]
    views = [(k, grey(imgs[k][0]), POSES[k]) for k in range(1, len(POSES))]
    cache = FlowCache()
    d, cnt = dense_depth(grey(imgs[0][0]), POSES[0], views, INTR, eta=0.02, min_views=3,
                         min_parallax=np.radians(1.0), cache=cache, kf_id=0)
    true = torch.from_numpy(imgs[0][1])
    ok = d > 0
    assert ok.float().mean() > 0.6
    rel = ((d - true).abs() / true)[ok]
    assert float(rel.median()) < 0.01 and float(torch.quantile(rel, 0.9)) < 0.03
    assert int(cnt.max()) == len(views) and len(cache) == len(views)
    # flows are cached per (kf, view): a second call computes none
    f = cache.get(0, 1, None, None)
    assert f.dtype == np.float16 and f.shape == (H, W, 2)
    cache.drop(1)
    assert len(cache) == len(views) - 1


def test_select_views_prefers_wide_baselines_within_the_overlap_limit():
    cands = [(1, pose(0.05, 0)), (2, pose(0.3, 0)), (3, pose(0.15, 0)), (4, pose(1.5, 0))]
    assert select_views(pose(0, 0), cands, depth=2.0, n=2) == [2, 3]      # 4: ratio 0.75
    assert select_views(pose(0, 0), cands, depth=2.0, n=0) == []


def _kf(k, T, img, disp):
    return KeyframeData(kf_id=k, frame_index=k, timestamp=float(k), pose=T, image=img,
                        intrinsics=INTR, disparity=disp, confidence=np.ones_like(disp))


def _estimate(dense_views, noise=0.15):
    cfg = SlamConfig()
    cfg.depth.device = "cpu"
    cfg.depth.dense_views = dense_views
    cfg.depth.upsample_guided = False
    cfg.depth.fill_holes_from_ba = False       # the dense layer's own coverage
    est = ProxyDepthEstimator(cfg, INTR)
    tex = _texture()
    rng = np.random.default_rng(1)
    kfs, trues = [], []
    for k, T in enumerate(POSES):
        img, true = view(T, tex)
        ba = cv2.resize(true, (W // 8, H // 8), interpolation=cv2.INTER_AREA)
        disp = (1.0 / ba) * (1 + noise * rng.standard_normal(ba.shape))   # poor BA depth
        kfs.append(_kf(k, T, img, disp.astype(np.float32)))
        trues.append(true)
    est.add_keyframes(kfs)
    return est, trues


def test_estimator_dense_depth_replaces_and_fills_the_ba_grid_depth():
    base, trues = _estimate(0)
    dense, _ = _estimate(4)
    rb, rd = base.get(0), dense.get(0)
    true = trues[0]
    assert rd.valid.mean() > max(0.6, rb.valid.mean() + 0.2)
    assert set(np.unique(rd.source)) <= {0, SOURCE_MULTIVIEW}
    err_d = np.abs(rd.depth - true)[rd.valid] / true[rd.valid]
    assert np.median(err_d) < 0.01
    if rb.valid.any():
        assert np.median(err_d) < np.median(np.abs(rb.depth - true)[rb.valid] / true[rb.valid])
    assert dense.timings["dense_ms"] > 0 and base.timings["dense_ms"] == 0
    # a BA update (a pose moves) recomputes with the cached flows: no new flow
    n_flows = len(dense.dense.flows)
    moved = POSES[0].copy()
    moved[:3, 3] += [0.01, 0, 0]
    out = dense.apply_update(UpdateEvent(seq=3, reason="local_ba", kf_ids=[0],
                                         poses=moved[None]))
    assert any(new.kf_id == 0 for _, new in out) and len(dense.dense.flows) == n_flows


def test_estimator_reuses_the_dense_depth_for_tiny_pose_changes():
    est, _ = _estimate(4)
    before = est.dense._last[0]
    nudged = POSES[0].copy()
    nudged[:3, 3] += [1e-6, 0, 0]
    est.apply_update(UpdateEvent(seq=3, reason="local_ba", kf_ids=[0], poses=nudged[None]))
    assert est.dense._last[0] is before
    est.dense.drop(0)
    assert 0 not in est.dense._last
