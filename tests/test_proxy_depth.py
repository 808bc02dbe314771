"""Multi-view consistency filter (Eq. 4-6), upsampling, scale/shift fit (Eq. 3), proxy depth
(§3.2) and the stateful estimator, on an analytic multi-view scene with known depth."""
import numpy as np
import pytest
import torch

from splat_slam_ros.config import ConfigError, SlamConfig
from splat_slam_ros.geometry import so3_exp
from splat_slam_ros.tracking.mono_depth import MonoDepthModel
from splat_slam_ros.depth.compose import (SOURCE_BA, SOURCE_EMPTY, SOURCE_MONO,
                                          SOURCE_MULTIVIEW, compose_proxy_depth,
                                          fill_small_holes, fit_scale_shift)
from splat_slam_ros.depth.proxy_depth import ProxyDepthEstimator
from splat_slam_ros.tracking.multiview import (all_pairs, consistency_count, multiview_filter,
                                               parallax_pairs)
from splat_slam_ros.depth.upsample import corner_preference, upsample_disparity
from splat_slam_ros.roles import DepthRole
from splat_slam_ros.types import TRACKER_SEQ_START, Intrinsics, KeyframeData, UpdateEvent

# ----------------------------------------------------------------- the scene
# planes n.X = c (world frame, OpenCV axes: y down), optional axis-aligned bounds of the hit
ROOM = [((0, 0, 1), 5.0, None),                                   # back wall
        ((1, 0, 0), -2.5, None), ((1, 0, 0), 2.5, None),         # side walls
        ((0, 1, 0), 1.2, None), ((0, 1, 0), -1.5, None),         # floor, ceiling
        ((0, 0, 1), 2.5, ((-0.6, -0.5, 2.4), (0.4, 0.3, 2.6)))]  # a panel in front: edges


def raycast(T, intr, H, W, planes=ROOM, uv=None):
    """z-depth (H, W) of the first plane hit by every pixel ray (or by the rays of the
    continuous pixels ``uv`` (2, M))."""
    fx, fy, cx, cy = intr
    if uv is None:
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    else:
        u, v = uv
    dc = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)]).reshape(3, -1)
    dw = T[:3, :3] @ dc
    o = T[:3, 3]
    best = np.full(dw.shape[1], np.inf)
    for n, c, box in planes:
        n = np.asarray(n, float)
        den = n @ dw
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c - n @ o) / den
        ok = np.isfinite(t) & (t > 1e-6)
        if box is not None:
            X = o[:, None] + t * dw
            lo, hi = np.asarray(box[0])[:, None], np.asarray(box[1])[:, None]
            ok &= np.all((X >= lo) & (X <= hi), 0)
        best = np.where(ok & (t < best), t, best)
    return best if uv is not None else best.reshape(H, W)   # dc has z = 1: t is z-depth


def visible_views(poses, depth, intr, i):
    """Ground-truth Eq. 6 count of keyframe i: other views that see its points unoccluded."""
    h, w = depth.shape[1:]
    fx, fy, cx, cy = intr
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    Xc = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)]).reshape(3, -1) * \
        depth[i].reshape(1, -1)
    Xw = poses[i][:3, :3] @ Xc + poses[i][:3, 3:4]
    n = np.zeros(h * w, int)
    for k in range(len(poses)):
        if k == i:
            continue
        Tk = np.linalg.inv(poses[k])
        Xk = Tk[:3, :3] @ Xw + Tk[:3, 3:4]
        uk, vk = fx * Xk[0] / Xk[2] + cx, fy * Xk[1] / Xk[2] + cy
        zk = raycast(poses[k], intr, h, w, uv=(uk, vk))
        n += ((Xk[2] > 0) & (uk >= -0.5) & (uk <= w - 0.5) & (vk >= -0.5) & (vk <= h - 0.5)
              & (np.abs(zk - Xk[2]) < 1e-3 * Xk[2]))
    return n.reshape(h, w)


def pose(i):
    T = np.eye(4)
    T[:3, :3] = so3_exp(torch.tensor([0.02 * np.sin(i), 0.04 * (i - 3), 0.0],
                                     dtype=torch.float64)).numpy()
    T[:3, 3] = [0.12 * (i - 3), 0.03 * np.sin(1.3 * i), 0.08 * i]
    return T


TRACK = Intrinsics(250.0, 250.0, 159.5, 119.5, 320, 240)      # tracking resolution
BA = TRACK.scaled(1 / 8)                                        # 40 x 30


def ivec(intr):
    return (intr.fx, intr.fy, intr.cx, intr.cy)


def scene(n=6, intr=BA):
    poses = np.stack([pose(i) for i in range(n)])
    depth = np.stack([raycast(p, ivec(intr), intr.height, intr.width) for p in poses])
    return poses, depth.astype(np.float32)


def keyframe(i, disp, T, img=None):
    img = np.zeros((TRACK.height, TRACK.width, 3), np.uint8) if img is None else img
    return KeyframeData(kf_id=i, frame_index=3 * i, timestamp=0.1 * i, pose=T, image=img,
                        intrinsics=TRACK, disparity=disp.astype(np.float32),
                        confidence=np.ones_like(disp, np.float32))


# ------------------------------------------------------------ Eq. 4-6 filter
def test_filter_keeps_true_depth_rejects_corruption():
    FILT = TRACK.scaled(1 / 4)                                  # 80 x 60 (paper BA size)
    poses, depth = scene(6, FILT)
    rng = np.random.default_rng(0)
    bad = depth.copy()
    corrupt = np.zeros(depth.shape, bool)
    corrupt[2, 10:40, 20:60] = True                              # a wrong patch (+25 %)
    bad[corrupt] *= 1.25
    speck = rng.random(depth.shape) < 0.05                       # random outliers
    bad[speck] *= rng.uniform(0.5, 0.8, speck.sum())
    corrupt |= speck
    # clean scene: valid wherever >= 2 other views see the point (not at the outer borders)
    v0, c0 = multiview_filter(torch.from_numpy(depth), torch.from_numpy(poses), ivec(FILT))
    v0 = v0.numpy()
    assert v0.mean() > 0.85
    for i in (0, 3):    # the count is the number of other views that see the point
        agree = (c0[i].numpy() == visible_views(poses, depth, ivec(FILT), i)).mean()
        assert agree > 0.92, (i, agree)         # rest: occlusion edges at 80x60
    valid, count = multiview_filter(torch.from_numpy(bad), torch.from_numpy(poses), ivec(FILT),
                                    eta=0.01, min_views=2)
    valid = valid.numpy()
    good = ~corrupt & v0
    assert valid[good].mean() > 0.9, valid[good].mean()
    assert valid[corrupt].mean() < 0.01, valid[corrupt].mean()
    # the kept depth is the true one (a corrupted point may by chance land on another
    # surface consistently: allowed for a handful of pixels)
    rel = np.abs(bad[valid] - depth[valid]) / depth[valid]
    assert (rel < 1e-6).mean() > 0.999


def test_views_without_parallax_confirm_no_depth():
    """Eq. 4-5 under a pure rotation: every depth reprojects consistently, so views that only
    rotated would "confirm" a depth 100x too far (what BA leaves on keyframes it cannot
    triangulate). With ``min_parallax_deg`` such views do not count; views with a baseline
    keep the true depth valid."""
    rot = np.stack([np.eye(4) for _ in range(4)])
    for i in range(4):                                   # pan by 2 degrees per view, no baseline
        rot[i, :3, :3] = so3_exp(torch.tensor([0.0, np.radians(2.0 * i), 0.0],
                                              dtype=torch.float64)).numpy()
    depth = np.stack([raycast(p, ivec(BA), BA.height, BA.width) for p in rot])
    wrong = torch.from_numpy((100.0 * depth).astype(np.float32))
    P = torch.from_numpy(rot)
    v_any, _ = multiview_filter(wrong, P, ivec(BA), max_depth_ratio=0)
    assert v_any.numpy().mean() > 0.8                    # the wrong depth passes Eq. 6 ...
    v_par, count = multiview_filter(wrong, P, ivec(BA), max_depth_ratio=0, min_parallax_deg=1.0)
    assert not v_par.any() and not count.any()           # ... not without parallax
    pairs = all_pairs(4)
    assert len(parallax_pairs(wrong, P, pairs, 1.0)) == 0
    assert len(parallax_pairs(wrong, P, pairs, 0.0)) == len(pairs)
    # a translating sequence (baselines 0.12 m at ~2 m: > 3 degrees) is unaffected
    poses, d = scene(6)
    a, ca = multiview_filter(torch.from_numpy(d), torch.from_numpy(poses), ivec(BA))
    b, cb = multiview_filter(torch.from_numpy(d), torch.from_numpy(poses), ivec(BA),
                             min_parallax_deg=1.0)
    assert torch.equal(a, b) and torch.equal(ca, cb) and a.numpy().mean() > 0.5


def test_filter_rejects_far_depth_by_median():
    far = [((0, 0, 1), 2.0, ((-9, -9, 1.9), (0.6, 9, 2.1))),     # near wall on the left
           ((0, 0, 1), 12.0, None)]                              # far wall (> 3x median)
    poses = np.stack([pose(i) for i in range(4)])
    d = np.stack([raycast(p, ivec(BA), 30, 40, far) for p in poses]).astype(np.float32)
    valid, count = multiview_filter(torch.from_numpy(d), torch.from_numpy(poses), ivec(BA))
    near = d < 3
    far_consistent = ~near & (count.numpy() >= 2)
    assert far_consistent.sum() > 100                            # far wall is consistent ...
    assert not valid.numpy()[~near].any()                        # ... but > 3x median
    assert valid.numpy()[near].mean() > 0.8                     # (borders: < 2 views)
    v_off, _ = multiview_filter(torch.from_numpy(d), torch.from_numpy(poses), ivec(BA),
                                max_depth_ratio=0)
    assert v_off.numpy()[far_consistent].all()                  # the median rule did it


def test_consistency_pairs_and_missing_depth():
    poses, depth = scene(4)
    d = torch.from_numpy(depth)
    d[1] = 0                                                      # keyframe 1 has no depth
    pairs = torch.tensor([[0, 1], [0, 2], [0, 3]])
    c = consistency_count(d, torch.from_numpy(poses), ivec(BA), 0.01, pairs)
    assert c[1:].sum() == 0                                       # only target 0 counted
    assert c[0].max() == 2                                        # view 1 never consistent


# ------------------------------------------------------------ upsampling
def test_upsample_exact_on_planes_no_bleeding_at_edges():
    _, depth = scene(1)
    disp = torch.from_numpy(1.0 / depth[0])
    valid = torch.ones_like(disp, dtype=torch.bool)
    up, ok = upsample_disparity(disp, valid, (240, 320), disc=0.1)
    true = 1.0 / raycast(pose(0), ivec(TRACK), 240, 320)
    up, ok = up.numpy(), ok.numpy()
    assert ok.all()
    rel = np.abs(up - true) / true
    # bilinear pixels on planes (no edge within their cell) are exact
    interior = rel[8:-8, 8:-8]
    assert np.median(interior) < 1e-4
    assert np.percentile(interior, 90) < 0.02          # nearest on steep / edge cells
    # a step (two planes, 2 m vs 5 m): cells across the step take the nearest BA value,
    # never an in-between ("flying") depth
    ramp = torch.linspace(0.0, 0.01, 40)[None, :].expand(30, 40)
    step = torch.where(torch.arange(40)[None, :] < 17, 0.5 + ramp, 0.2 + ramp).contiguous()
    up2, ok2 = upsample_disparity(step, valid, (240, 320), disc=0.1)
    up2 = up2.numpy()
    assert ok2.all()
    left, right = up2[:, :17 * 8], up2[:, 17 * 8:]          # BA pixel 17 starts at x=136
    assert left.min() >= 0.499 and right.max() <= 0.2 + 0.0102  # (linear at the border)
    edge_cols = up2[:, 132:140]                          # the cell between BA 16 and 17
    assert np.isin(edge_cols, step.numpy()).all()      # exactly one of the BA values
    # invalid BA pixels never bleed: upsampled validity is exactly nearest-neighbour validity
    v2 = valid.clone()
    v2[10:20, 10:20] = False
    _, ok2 = upsample_disparity(disp, v2, (240, 320))
    assert not ok2.numpy()[84:156, 84:156].any() and ok2.numpy()[:80].all()


def test_guided_upsampling_puts_the_edge_on_the_image_edge():
    """A depth edge at x = 130 (inside the BA cell 123.5..131.5): unguided, the step lands
    half-way between BA centres (x = 128); colour-guided, on the image edge."""
    H, W = 240, 320
    xs = np.arange(W)
    true_disp = np.where(xs < 130, 0.5, 0.2)[None, :].repeat(H, 0).astype(np.float32)
    img = np.where(xs[None, :, None] < 130, 200, 40).repeat(H, 0).astype(np.uint8)
    img = np.broadcast_to(img, (H, W, 3)).copy()
    # BA disparity: each cell's majority surface
    ba = torch.from_numpy(np.where(np.arange(40) * 8 + 4 < 130, 0.5, 0.2)[None, :]
                          .repeat(30, 0).astype(np.float32))
    valid = torch.ones_like(ba, dtype=torch.bool)
    plain, _ = upsample_disparity(ba, valid, (H, W))
    guided, ok = upsample_disparity(ba, valid, (H, W), guide=corner_preference(img, 30, 40))
    assert ok.all()
    wrong = ~np.isclose(plain.numpy(), true_disp, rtol=1e-5)
    assert list(np.nonzero(wrong.any(axis=0))[0]) == [128, 129]
    np.testing.assert_allclose(guided.numpy(), true_disp, rtol=1e-5)


# ------------------------------------------------------------ scale / shift
def test_fit_scale_shift_recovers_affine():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(60, 80, generator=g) * 3 + 0.5
    y = 1.7 * x - 0.4
    mask = torch.rand(60, 80, generator=g) > 0.3
    y_bad = torch.where(mask, y, torch.full_like(y, 100.0))     # outside the mask: ignored
    th, ga = fit_scale_shift(x, y_bad, mask)
    assert th == pytest.approx(1.7, rel=1e-6) and ga == pytest.approx(-0.4, abs=1e-6)
    assert np.isnan(fit_scale_shift(x, y, torch.zeros_like(mask))[0])
    assert np.isnan(fit_scale_shift(torch.ones_like(x), y, mask)[0])   # degenerate x


def test_compose_mono_fill_depth_and_disparity_space():
    true = torch.from_numpy(raycast(pose(0), ivec(TRACK), 240, 320).astype(np.float32))
    valid = torch.zeros_like(true, dtype=torch.bool)
    valid[:, :200] = True
    # depth-space model: D_mono = (D - 0.3) / 2
    mono = (true - 0.3) / 2.0
    d, s, th, ga = compose_proxy_depth(true, valid, mono, "depth")
    assert th == pytest.approx(2.0, rel=1e-4) and ga == pytest.approx(0.3, abs=1e-3)
    assert (s[:, :200] == SOURCE_MULTIVIEW).all() and (s[:, 200:] == SOURCE_MONO).all()
    np.testing.assert_allclose(d, true.numpy(), rtol=1e-4)
    # disparity-space model: 1/D_mono = (1/D - 0.05) / 4
    mono_disp = (1.0 / true - 0.05) / 4.0
    d2, s2, th2, ga2 = compose_proxy_depth(true, valid, 1.0 / mono_disp, "disparity")
    assert th2 == pytest.approx(4.0, rel=1e-4) and ga2 == pytest.approx(0.05, abs=1e-4)
    np.testing.assert_allclose(d2, true.numpy(), rtol=1e-4)
    # without mono: holes stay holes
    d3, s3, _, _ = compose_proxy_depth(true, valid, None)
    assert (s3[:, 200:] == SOURCE_EMPTY).all() and (d3[:, 200:] == 0).all()
    # ... unless a BA depth is given: it fills them, except beyond 3x the median depth
    ba = true * 1.1
    ba[:, 300:] = 100.0
    d4, s4, _, _ = compose_proxy_depth(true, valid, None, ba_depth=ba)
    assert (s4[:, :200] == SOURCE_MULTIVIEW).all() and (d4[:, :200] == true[:, :200].numpy()).all()
    assert (s4[:, 200:300] == SOURCE_BA).all()
    np.testing.assert_allclose(d4[:, 200:300], ba[:, 200:300].numpy())
    assert (s4[:, 300:] == SOURCE_EMPTY).all() and (d4[:, 300:] == 0).all()
    # a mono model takes precedence (the paper's fill); nothing consistent: nothing filled
    _, s5, _, _ = compose_proxy_depth(true, valid, mono, "depth", ba_depth=ba)
    assert not (s5 == SOURCE_BA).any()
    _, s6, _, _ = compose_proxy_depth(true, torch.zeros_like(valid), None, ba_depth=ba)
    assert (s6 == SOURCE_EMPTY).all()


def test_fill_small_holes_only_planar_enclosed_small():
    true = raycast(pose(0), ivec(TRACK), 240, 320).astype(np.float32)
    valid = np.ones_like(true, bool)
    valid[100:104, 250:254] = False          # 16 px on the back wall -> filled exactly
    valid[10:40, 10:40] = False              # 900 px: too big
    valid[0:3, 150:153] = False              # touches the border
    # a hole straddling the panel edge (the panel spans x ~ [-0.6, 0.4] m at 2.5 m)
    col = int(np.argmax(np.abs(np.diff(true[120])) > 0.5))
    valid[118:122, col - 1:col + 3] = False
    d = np.where(valid, true, 0).astype(np.float32)
    filled = fill_small_holes(d, valid, max_px=64, plane_tol=0.02)
    assert filled[100:104, 250:254].all()
    np.testing.assert_allclose(d[100:104, 250:254], true[100:104, 250:254], rtol=1e-4)
    assert not filled[10:40, 10:40].any() and not filled[0:3, 150:153].any()
    assert not filled[118:122, col - 1:col + 3].any()
    assert filled.sum() == 16


# ------------------------------------------------------------ estimator
class AffineMono(MonoDepthModel):
    """Test double: ground-truth depth through a known affine map (relative depth)."""
    kind = "depth"

    def __init__(self, poses):
        self.poses = poses
        self.i = 0

    def predict(self, image):
        T = self.poses[int(image[0, 0, 0])]
        return ((raycast(T, ivec(TRACK), 240, 320) - 0.5) / 3.0).astype(np.float32)


def run_estimator(n=8, mono=None, **depth_cfg):
    cfg = SlamConfig()
    for k, v in depth_cfg.items():
        cfg.set(f"depth.{k}", v)
    est = ProxyDepthEstimator(cfg, TRACK, mono_model=mono)
    poses, depth = scene(n)
    out = []
    for i in range(n):
        img = np.zeros((240, 320, 3), np.uint8)
        img[0, 0, 0] = i
        out.append(est.add_keyframe(keyframe(i, 1.0 / depth[i], poses[i], img)))
    return est, poses, depth, out


def test_estimator_multiview_only_and_with_mono():
    est, poses, _, out = run_estimator(8, fill_holes_from_ba=False)
    assert out[5].n_views == 5 and est.get(5).n_views == 7     # refreshed by kf 6, 7
    r = est.get(5)
    true = raycast(poses[5], ivec(TRACK), 240, 320)
    ok = r.source == SOURCE_MULTIVIEW
    assert r.depth.shape == (240, 320) and r.depth.dtype == np.float32
    assert r.source.dtype == np.uint8 and set(np.unique(r.source)) <= {0, 1}
    assert ok.mean() > 0.6
    assert np.median(np.abs(r.depth[ok] - true[ok])) < 0.005
    assert (r.depth[~ok] == 0).all()
    np.testing.assert_array_equal(r.pose, poses[5])
    assert est.get(99) is None and r.update_seq == 0
    # the first keyframe had no views when added; later keyframes refresh it
    assert out[0].valid.sum() == 0
    refreshed = dict((new.kf_id, new) for _, new in est.take_refreshed())
    assert 0 in refreshed and refreshed[0].valid.mean() > 0.5 and est.take_refreshed() == []
    # full method: mono fill gives (almost) full coverage at the right depth
    est2, _, _, out2 = run_estimator(8, mono=AffineMono(poses))
    r2 = est2.get(5)
    assert (r2.source > 0).mean() > 0.99 and (r2.source == SOURCE_MONO).any()
    assert r2.mono_scale == pytest.approx(3.0, rel=1e-2)
    assert r2.mono_shift == pytest.approx(0.5, abs=3e-2)
    err = np.abs(r2.depth - true)
    for src in (SOURCE_MULTIVIEW, SOURCE_MONO):       # (the tail: edges at 1/8 resolution)
        assert np.median(err[r2.source == src]) < 0.01
        assert np.percentile(err[r2.source == src], 90) < 0.02
    assert not (r2.source == SOURCE_BA).any()


def test_estimator_fills_multiview_holes_with_the_ba_depth_by_default():
    est, poses, _, out = run_estimator(8)
    holes, _, _, _ = run_estimator(8, fill_holes_from_ba=False)
    r, r0 = est.get(5), holes.get(5)
    true = raycast(poses[5], ivec(TRACK), 240, 320)
    mv, ba = r.source == SOURCE_MULTIVIEW, r.source == SOURCE_BA
    np.testing.assert_array_equal(mv, r0.source == SOURCE_MULTIVIEW)   # multi-view untouched
    np.testing.assert_array_equal(r.depth[mv], r0.depth[mv])
    assert (ba == (r0.source == SOURCE_EMPTY)).mean() > 0.99 and ba.mean() > 0.05
    assert np.median(np.abs(r.depth[ba] - true[ba])) < 0.01       # the BA depth is exact here
    assert out[0].valid.sum() == 0                # the first keyframe, no view yet: it waits


def test_apply_update_returns_exactly_the_affected_keyframes():
    est, poses, depth, _ = run_estimator(10, mv_neighbors=2)
    est.take_refreshed()
    before = {k: est.get(k) for k in range(10)}
    # no change -> nothing returned
    ev = UpdateEvent(seq=7, reason="local_ba", kf_ids=[3, 4], poses=poses[[3, 4]],
                     disparities=(1.0 / depth[[3, 4]]).astype(np.float32))
    assert est.apply_update(ev) == []
    # kf 5 moves by 30 cm: 5 itself, and 4 and 6 (they use 5 as one of their two views)
    bad = poses[5].copy()
    bad[:3, 3] += [0.3, 0.0, 0.0]
    ev = UpdateEvent(seq=8, reason="loop_closure", kf_ids=[5], poses=bad[None])
    pairs = est.apply_update(ev)
    ids = sorted(new.kf_id for _, new in pairs)
    assert ids == [4, 5, 6]
    for old, new in pairs:
        assert old is before[new.kf_id] and new.update_seq == 8 and est.get(new.kf_id) is new
        assert not np.array_equal(old.source, new.source)
    np.testing.assert_array_equal(est.get(5).pose, bad)
    for k in (0, 1, 2, 3, 7, 8, 9):
        assert est.get(k) is before[k]
    # a disparity-only update of kf 8 (one corrupted region)
    d8 = (1.0 / depth[8]).astype(np.float32)
    d8[5:15, 5:20] *= 1.5
    ev = UpdateEvent(seq=9, reason="global_ba", kf_ids=[8], poses=poses[8][None],
                     disparities=d8[None])
    pairs = est.apply_update(ev)
    got = {new.kf_id: (old, new) for old, new in pairs}
    assert 8 in got and set(got) <= {7, 8, 9}
    old, new = got[8]
    mv = lambda r: (r.source == SOURCE_MULTIVIEW)[40:120, 40:160]
    assert mv(new).sum() < mv(old).sum()      # the filter drops the corrupted region ...
    assert (new.source[40:120, 40:160][~mv(new)] == SOURCE_BA).all()   # ... the BA fills it
    # unknown keyframes are ignored
    assert est.apply_update(UpdateEvent(10, "final", [42], np.eye(4)[None])) == []


def test_small_moves_send_the_new_pose_with_the_same_depth():
    """depth.update_tol: a local BA update that moves a keyframe less than the tolerance
    since its proxy depth was computed (camera by that fraction of its median depth,
    disparity by that median relative change) sends the new pose with the same depth and
    recomputes nothing; moves that add up past it recompute the keyframe and its viewers, as
    the loop closer's updates always do; 0 recomputes every change."""
    est, poses, depth, _ = run_estimator(10, mv_neighbors=2)
    est.take_refreshed()
    n0 = est.timings["n"]
    tol = est.dc.update_tol
    assert tol > 0                                      # on by default
    med = float(np.median(depth[5][depth[5] > 0]))
    before = est.get(5)
    step = np.eye(4)
    step[:3, 3] = [0.3 * tol * med, 0.0, 0.0]           # 0.3 x the tolerance
    p = poses[5] @ step
    pairs = est.apply_update(UpdateEvent(8, "local_ba", [5], p[None]))
    assert est.timings["n"] == n0 and [new.kf_id for _, new in pairs] == [5]
    old, new = pairs[0]
    assert old is before and new.update_seq == 8 and est.get(5) is new
    np.testing.assert_array_equal(new.pose, p)
    np.testing.assert_array_equal(new.depth, before.depth)
    np.testing.assert_array_equal(new.source, before.source)
    # a disparity change of 0.1 x the tolerance and the same pose: nothing to send or compute
    d5 = (1.0 / depth[5]).astype(np.float32) * np.float32(1 + 0.1 * tol)
    assert est.apply_update(UpdateEvent(9, "local_ba", [5], p[None], disparities=d5[None])) == []
    assert est.timings["n"] == n0
    # the same step three more times: 0.6 and 0.9 x the tolerance since the computation
    # (kept), then 1.2 x: kf 5 and the two keyframes using it as a view are recomputed
    for seq, computed in ((10, 0), (11, 0), (12, 3)):
        p = p @ step
        pairs = est.apply_update(UpdateEvent(seq, "local_ba", [5], p[None], disparities=d5[None]))
        assert est.timings["n"] == n0 + computed
    assert sorted(new.kf_id for _, new in pairs) == [4, 5, 6]
    assert not np.array_equal(est.get(5).depth, before.depth)
    # a disparity change above the tolerance recomputes at once
    n1 = est.timings["n"]
    est.apply_update(UpdateEvent(13, "local_ba", [5], p[None], disparities=(d5 * (1 + 2 * tol))[None]))
    assert est.timings["n"] == n1 + 3
    # the loop closer's updates recompute whatever they move, however little
    n2 = est.timings["n"]
    pairs = est.apply_update(UpdateEvent(14, "global_ba", [5], (p @ step)[None]))
    assert est.timings["n"] == n2 + 3 and sorted(new.kf_id for _, new in pairs) == [4, 5, 6]
    # update_tol 0: the first small step already recomputes
    est0, _, _, _ = run_estimator(10, mv_neighbors=2, update_tol=0.0)
    est0.take_refreshed()
    m0 = est0.timings["n"]
    pairs = est0.apply_update(UpdateEvent(8, "local_ba", [5], (poses[5] @ step)[None]))
    assert est0.timings["n"] == m0 + 3 and sorted(new.kf_id for _, new in pairs) == [4, 5, 6]
    # out of range: a configuration error when the depth stage is set up, before any keyframe
    cfg = SlamConfig()
    cfg.set("depth.update_tol", -0.01)
    with pytest.raises(ConfigError, match="depth.update_tol"):
        DepthRole(cfg, loop_closure=False)


def test_small_hole_policy_in_estimator():
    _, _, _, out0 = run_estimator(6)
    _, _, _, out1 = run_estimator(6, fill_small_holes=64)
    a, b = out0[4], out1[4]
    assert (b.source > 0).sum() >= (a.source > 0).sum()
    # filled pixels only where there was a hole, and existing depth untouched
    np.testing.assert_array_equal(b.depth[a.source > 0], a.depth[a.source > 0])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_filter_cuda_matches_cpu():
    poses, depth = scene(5)
    a, _ = multiview_filter(torch.from_numpy(depth), torch.from_numpy(poses), ivec(BA))
    b, _ = multiview_filter(torch.from_numpy(depth).cuda(), torch.from_numpy(poses).cuda(),
                            ivec(BA))
    assert (a == b.cpu()).float().mean() > 0.999


def test_deferred_updates_recompute_once_with_the_newest_poses():
    """A node with several updates queued defers all but the newest: one recomputation of
    everything they moved, equal to applying the newest poses directly."""
    est, poses, depth, _ = run_estimator(10, mv_neighbors=2)
    ref, _, _, _ = run_estimator(10, mv_neighbors=2)
    est.take_refreshed()
    ref.take_refreshed()
    p2, p5a, p5b = poses[2].copy(), poses[5].copy(), poses[5].copy()
    p2[:3, 3] += [0.2, 0.0, 0.0]
    p5a[:3, 3] += [0.3, 0.0, 0.0]
    p5b[:3, 3] += [0.0, 0.1, 0.0]
    n0 = est.timings["n"]
    assert est.apply_update(UpdateEvent(8, "loop_closure", [5], p5a[None]), defer=True) == []
    assert est.apply_update(UpdateEvent(9, "loop_closure", [2], p2[None]), defer=True) == []
    assert est.timings["n"] == n0 and est.dirty == {2, 5}         # nothing computed yet
    pairs = est.apply_update(UpdateEvent(10, "global_ba", [5], p5b[None]))
    assert sorted(new.kf_id for _, new in pairs) == [0, 1, 2, 3, 4, 5, 6]   # + their viewers
    assert est.timings["n"] == n0 + 7 and not est.dirty
    ref.apply_update(UpdateEvent(10, "global_ba", [2, 5], np.stack([p2, p5b])))
    for _, new in pairs:
        assert new.update_seq == 10
        np.testing.assert_array_equal(new.depth, ref.get(new.kf_id).depth)
        np.testing.assert_array_equal(new.pose, ref.get(new.kf_id).pose)
    assert est.flush() == []


def test_depth_role_defers_queued_updates_and_flushes_before_anything_else():
    from splat_slam_ros.roles import DepthRole
    cfg = SlamConfig()
    cfg.set("depth.mv_neighbors", 2)
    role = DepthRole(cfg, loop_closure=False)
    poses, depth = scene(7)
    for i in range(6):
        assert [p.revision for p in role.on_keyframe(keyframe(i, 1.0 / depth[i], poses[i]))
                .proxy_depths][-1:] == [0]
    rev = dict(role.revision)
    moved = poses[3].copy()
    moved[:3, 3] += [0.2, 0.0, 0.0]
    out = role.on_update(UpdateEvent(TRACKER_SEQ_START + 1, "local_ba", [3], moved[None]),
                         defer=True)
    assert out.proxy_depths == [] and role.revision == rev and role.meta()["dirty"] == [3]
    # the next keyframe: the deferred update's depths go out first, at their next revision
    out = role.on_keyframe(keyframe(6, 1.0 / depth[6], poses[6]))
    sent = [(p.kf_id, p.revision) for p in out.proxy_depths]
    assert sent[-1] == (6, 0) and sorted(sent[:-1]) == [(k, rev[k] + 1) for k in (2, 3, 4, 5)]
    # a deferred update when the tracker's final arrives: flushed, then the digest
    moved[:3, 3] += [0.0, 0.1, 0.0]
    assert role.on_update(UpdateEvent(TRACKER_SEQ_START + 2, "local_ba", [3], moved[None]),
                          defer=True).final is None
    out = role.on_final("tracker", {"last_seq": TRACKER_SEQ_START + 2})
    assert {p.kf_id for p in out.proxy_depths} >= {3} and out.final is not None
    assert out.final["digest"]["3"] == rev[3] + 2 and role.meta()["dirty"] == []


def test_merged_keyframes_follow_rigidly_without_recomputation():
    """The loop closer's poses-only updates move the keyframes it merged: their proxy depth
    is sent again at the new pose, unchanged and not recomputed; they stop serving as views
    (their kept keyframe has that view) and are not recomputed when a neighbour moves."""
    from splat_slam_ros.roles import DepthRole
    from splat_slam_ros.types import LOOP_SEQ_START
    cfg = SlamConfig()
    cfg.set("depth.mv_neighbors", 2)
    role = DepthRole(cfg, loop_closure=True)
    poses, depth = scene(10)
    for i in range(10):
        role.on_keyframe(keyframe(i, 1.0 / depth[i], poses[i]))
    est = role.est
    before = {k: est.get(k) for k in range(10)}
    rev = dict(role.revision)
    moved = poses[5].copy()
    moved[:3, 3] += [0.3, 0.0, 0.0]
    n0 = est.timings["n"]
    out = role.on_update(UpdateEvent(LOOP_SEQ_START + 1, "global_ba", [5], moved[None]))
    assert [(p.kf_id, p.revision) for p in out.proxy_depths] == [(5, rev[5] + 1)]
    assert est.timings["n"] == n0                                   # nothing recomputed
    np.testing.assert_array_equal(out.proxy_depths[0].depth, before[5].depth)
    np.testing.assert_array_equal(out.proxy_depths[0].pose, moved)
    assert est.followers == {5} and all(5 not in est.neighbours(k) for k in range(10))
    assert est._kfs[5].grey is None and est._kfs[5].guide is None     # inputs released
    # a neighbour moves: it and the keyframes that use it as a view are recomputed, the
    # follower is not; a disparity update that lists the follower leaves it alone
    p4 = poses[4].copy()
    p4[:3, 3] += [0.1, 0.0, 0.0]
    d = (1.0 / depth[[4, 5]]).astype(np.float32) * 1.1
    out = role.on_update(UpdateEvent(LOOP_SEQ_START + 2, "loop_closure", [4, 5],
                                     np.stack([p4, moved]), d))
    got = {p.kf_id for p in out.proxy_depths}
    assert 4 in got and 5 not in got
    np.testing.assert_array_equal(est.get(5).depth, before[5].depth)
    # the same poses-only update from the tracker (not a merge) recomputes as before
    role2 = DepthRole(cfg, loop_closure=True)
    for i in range(10):
        role2.on_keyframe(keyframe(i, 1.0 / depth[i], poses[i]))
    out = role2.on_update(UpdateEvent(TRACKER_SEQ_START + 1, "local_ba", [5], moved[None]))
    assert {p.kf_id for p in out.proxy_depths} == {4, 5, 6} and not role2.est.followers
