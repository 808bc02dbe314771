"""Mapper: map initialisation, keyframe window rules, Gaussian map bookkeeping,
densification/pruning and optimisation on a tiny rendered scene."""
import numpy as np
import pytest
import torch

from splat_slam_ros.config import MappingConfig, SlamConfig
from splat_slam_ros.evaluation.map_sequence import map_sequence
from splat_slam_ros.evaluation.rendering import evaluate_keyframes, evaluate_map, save_renders
from splat_slam_ros.mapping.gaussian_map import GaussianMap
from splat_slam_ros.geometry import se3_exp, se3_inverse
from splat_slam_ros.mapping.keyframe_window import (KeyframeWindow, covisibility_iou,
                                            overlap_coefficient)
from splat_slam_ros.mapping.map_init import init_gaussians, nn_scale
from splat_slam_ros.mapping.mapper import MapError, Mapper
from splat_slam_ros.mapping.optimise import optimise, view_loss
from splat_slam_ros.mapping.persistence import map_state
from splat_slam_ros.types import Frame, Intrinsics

W, H, F = 48, 36, 42.0
K = Intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)


# ----------------------------------------------------------------- tiny scene
def scene_gaussians(n=40):
    """Ground-truth scene: a textured wall at z = 3 and a floor at y = 1 (camera y down)."""
    u = torch.linspace(-2.2, 2.2, n)
    X, Y = torch.meshgrid(u, torch.linspace(-1.6, 1.0, n), indexing="xy")
    wall = torch.stack([X.flatten(), Y.flatten(), torch.full((n * n,), 3.0)], -1)
    cw = torch.stack([torch.sin(3 * X) * 0.4 + 0.5, torch.cos(4 * Y) * 0.4 + 0.5,
                      ((X.floor() + Y.floor()) % 2) * 0.7 + 0.15], -1).reshape(-1, 3)
    Z, X2 = torch.meshgrid(torch.linspace(0.6, 3.0, n), u, indexing="ij")
    floor = torch.stack([X2.flatten(), torch.full((n * n,), 1.0), Z.flatten()], -1)
    cf = torch.stack([((X2 * 2).floor() % 2) * 0.6 + 0.2, Z * 0.25,
                      torch.full_like(Z, 0.5)], -1).reshape(-1, 3)
    means = torch.cat([wall, floor]).float()
    N = len(means)
    quats = torch.zeros(N, 4)
    quats[:, 3] = 1
    return (means, quats, torch.full((N, 3), 0.07), torch.full((N,), 0.97),
            torch.cat([cw, cf]).float().clamp(0, 1))


def pose_at(tx=0.0, ty=0.0, tz=0.0, yaw=0.0):
    return se3_exp(torch.tensor([tx, ty, tz, 0.0, yaw, 0.0], dtype=torch.float64)).numpy()


def render_view(scene, pose):
    from splat_slam_ros.mapping.rasterizer import rasterize
    V = se3_inverse(torch.as_tensor(pose)).float()
    out = rasterize(*scene, V, (K.fx, K.fy, K.cx, K.cy), W, H)
    img = (out.rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    d = torch.where(out.alpha > 0.5, out.depth / out.alpha.clamp_min(1e-6),
                    torch.zeros_like(out.depth))
    return img, d.numpy().astype(np.float32)


def small_cfg(**kw):
    cfg = SlamConfig()
    cfg.mapping = MappingConfig.fast(**kw)
    return cfg


@pytest.fixture(scope="module")
def scene():
    return scene_gaussians()


def psnr(a, b):
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2) / 255.0 ** 2
    return -10 * np.log10(mse)


# ------------------------------------------------------------------- map init
def test_map_init_counts_positions_colours_scales():
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, : W // 2] = 0.0                                   # left half missing
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = np.arange(W)[None, :] * 5
    img[..., 1] = np.arange(H)[:, None] * 7
    pose = pose_at(0.5, -0.2, 1.0)
    g = init_gaussians(img, depth, None, pose, (K.fx, K.fy, K.cx, K.cy), downsample=16,
                       generator=torch.Generator().manual_seed(0))
    n_valid = H * W // 2
    assert g["means"].shape == (n_valid // 16, 3)
    # all on the plane z_cam = 2 in the right half, colours read from their pixels
    X = (g["means"].double() - torch.tensor(pose[:3, 3])) @ torch.tensor(pose[:3, :3])
    assert torch.allclose(X[:, 2], torch.full_like(X[:, 2], 2.0), atol=1e-5)
    u = X[:, 0] / X[:, 2] * K.fx + K.cx
    v = X[:, 1] / X[:, 2] * K.fy + K.cy
    assert torch.allclose(u, u.round(), atol=1e-3) and (u >= W // 2 - 1e-3).all()
    ui, vi = u.round().long(), v.round().long()
    assert torch.allclose(g["colors"][:, 0], torch.from_numpy(img[vi, ui, 0] / 255.).float())
    assert torch.allclose(g["colors"][:, 1], torch.from_numpy(img[vi, ui, 1] / 255.).float())
    # isotropic scale = sqrt(mean squared distance to the 3 nearest neighbours)
    P = g["means"].double().numpy()
    d2 = ((P[:, None] - P[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    expect = np.sqrt(np.sort(d2, 1)[:, :3].mean(1))
    np.testing.assert_allclose(g["log_scales"].exp().numpy(), np.repeat(expect[:, None], 3, 1),
                               rtol=1e-5)
    assert torch.allclose(g["quats"], torch.tensor([0.0, 0, 0, 1]).expand(len(P), 4))
    assert torch.allclose(torch.sigmoid(g["opacity_logits"]), torch.tensor(0.5))
    # mapping.init_scale: the same seeds, their scales times the factor
    half = init_gaussians(img, depth, None, pose, (K.fx, K.fy, K.cx, K.cy), downsample=16,
                          generator=torch.Generator().manual_seed(0), scale=0.5)
    assert torch.equal(half["means"], g["means"])
    np.testing.assert_allclose(half["log_scales"].exp().numpy(),
                               0.5 * g["log_scales"].exp().numpy(), rtol=1e-6)
    # the valid mask is honoured as well as depth == 0; nothing valid -> nothing
    valid = np.zeros((H, W), bool)
    valid[:4, -4:] = True
    g2 = init_gaussians(img, depth, valid, pose, (K.fx, K.fy, K.cx, K.cy), downsample=4)
    assert len(g2["means"]) == 4
    g3 = init_gaussians(img, np.zeros((H, W), np.float32), None, pose,
                        (K.fx, K.fy, K.cx, K.cy), downsample=4)
    assert len(g3["means"]) == 0


def test_nn_scale_against_brute_force():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(50, 3))
    d = np.linalg.norm(P[:, None] - P[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    np.testing.assert_allclose(nn_scale(P), np.sqrt((np.sort(d, 1)[:, :3] ** 2).mean(1)))


# -------------------------------------------------------------- window rules
def test_iou_and_overlap_coefficient():
    a = torch.arange(0, 10)
    b = torch.arange(5, 25)
    assert covisibility_iou(a, b) == pytest.approx(5 / 25)
    assert overlap_coefficient(a, b) == pytest.approx(5 / 10)
    assert covisibility_iou(a, torch.arange(0)) == 0.0


def test_keyframe_selection_rules():
    w = KeyframeWindow(size=8, k_fcov=0.9, k_fm=0.08, k_fc=0.3)
    poses = {0: np.eye(4)}
    assert w.decide(torch.arange(100), np.eye(4), 2.0, poses).reason == "first"
    w.add(0, torch.arange(100), poses)
    near = np.eye(4)
    near[0, 3] = 0.1                               # 0.1 m < 0.08 x 2.0 m
    d = w.decide(torch.arange(3, 100), near, 2.0, poses)        # IOU 0.97
    assert not d.mapped and d.reason == "redundant"
    d = w.decide(torch.arange(20, 100), near, 2.0, poses)       # IOU 0.8 < 0.9
    assert d.mapped and d.reason == "covisibility" and d.iou == pytest.approx(0.8)
    far = np.eye(4)
    far[2, 3] = 0.2                                # 0.2 m > 0.16 m
    d = w.decide(torch.arange(100), far, 2.0, poses)
    assert d.mapped and d.reason == "translation"


def test_window_overlap_cutoff_and_size_limit():
    w = KeyframeWindow(size=3, k_fcov=0.9, k_fm=0.08, k_fc=0.3)
    poses = {i: np.eye(4) for i in range(6)}
    for i in range(6):
        poses[i][0, 3] = 0.1 * i
    w.add(0, torch.arange(0, 100), poses)
    w.add(1, torch.arange(50, 150), poses)
    w.add(2, torch.arange(60, 160), poses)
    assert w.window == [2, 1, 0]
    # keyframe 3 overlaps 0 by 20 % (< k_fc) -> 0 leaves; 1 and 2 stay
    removed = w.add(3, torch.arange(80, 180), poses)
    assert removed == [0] and w.window == [3, 2, 1]
    # no OC removal, but the window is over-full: one of the older ones goes, newest two stay
    removed = w.add(4, torch.arange(80, 180), poses)
    assert len(removed) == 1 and w.window[:2] == [4, 3] and len(w) == 3
    # the two newest are kept even without overlap
    removed = w.add(5, torch.arange(1000, 1100), poses)
    assert w.window[:2] == [5, 4] and 3 in removed


# -------------------------------------------------------------- Gaussian map
def test_gaussian_map_add_remove_keeps_adam_state_aligned():
    g = GaussianMap(lrs={"means": 0.1})
    g.add(torch.zeros(3, 3), torch.zeros(3, 3), torch.zeros(3, 3), kf_id=7, created=0)
    (g.means * torch.tensor([[1.0], [2.0], [3.0]])).sum().backward()
    g.step()
    st = g.optimizer.state[g.means]
    row = st["exp_avg"].clone()
    uid_before = g.uid.clone()
    g.add(torch.ones(2, 3), torch.zeros(2, 3), torch.zeros(2, 3), kf_id=9, created=1)
    assert len(g) == 5 and g.optimizer.state[g.means]["exp_avg"].shape == (5, 3)
    assert torch.equal(g.optimizer.state[g.means]["exp_avg"][:3], row)
    assert (g.optimizer.state[g.means]["exp_avg"][3:] == 0).all()
    assert g.kf_id.tolist() == [7, 7, 7, 9, 9] and g.created.tolist() == [0, 0, 0, 1, 1]
    g.remove(torch.tensor([False, True, False, True, False]))
    assert torch.equal(g.optimizer.state[g.means]["exp_avg"][:2], row[[0, 2]])
    assert g.uid.tolist() == [uid_before[0].item(), uid_before[2].item(), 4]
    # the optimiser updates the new tensors, with the per-group learning rate
    before = g.means.detach().clone()
    g.zero_grad()
    g.means.sum().backward()
    g.step()
    assert not torch.equal(before, g.means.detach())
    assert [grp["lr"] for grp in g.optimizer.param_groups if grp["name"] == "means"] == [0.1]


def test_densify_clone_and_split():
    mp = Mapper(small_cfg(scene_extent=1.0, percent_dense=0.01), K)
    g = mp.map
    ls = torch.log(torch.tensor([[0.005] * 3, [0.05] * 3, [0.05] * 3]))
    g.add(torch.zeros(3, 3), torch.full((3, 3), 0.5), ls, kf_id=3, created=0)
    g.grad_accum[:] = torch.tensor([1.0, 1.0, 0.0])      # third: no gradient
    g.grad_count[:] = 1
    n_clone, n_split = mp.strategy.densify(mp)
    assert (n_clone, n_split) == (1, 1)
    # small one cloned (2 copies), big one replaced by 2 smaller ones, third untouched
    assert len(g) == 1 + 1 + 1 + 2
    s = g.scales()[:, 0]
    assert torch.isclose(s, torch.tensor(0.005)).sum() == 2
    assert torch.isclose(s, torch.tensor(0.05 / 1.6)).sum() == 2
    assert (g.kf_id == 3).all()


def test_prune_opacity_and_size():
    mp = Mapper(small_cfg(scene_extent=1.0, prune_opacity=0.7, prune_min_age=10), K)
    g = mp.map
    logit = lambda p: float(np.log(p / (1 - p)))  # noqa: E731
    g.add(torch.zeros(4, 3), torch.zeros(4, 3),
          torch.log(torch.tensor([[0.01] * 3, [0.01] * 3, [0.5] * 3, [0.01] * 3])),
          opacity_logits=torch.tensor([logit(0.9), logit(0.3), logit(0.9), logit(0.3)]),
          born=torch.tensor([0, 0, 0, 15]))
    mp.iteration = 20
    assert mp.strategy.prune(mp) == 2     # low opacity (old enough) + oversized; young one spared
    assert len(g) == 2 and torch.isclose(g.opacities(), torch.tensor([0.9, 0.3])).all()
    # a loaded map's Gaussians (uid < settled_uid) are spared too, new ones are not
    mp.settled_uid = g.next_uid
    g.add(torch.zeros(1, 3), torch.zeros(1, 3), torch.log(torch.full((1, 3), 0.01)),
          opacity_logits=torch.tensor([logit(0.3)]), born=0)
    mp.iteration = 40
    assert mp.strategy.prune(mp) == 1 and len(g) == 2 and (g.uid < mp.settled_uid).all()


# ---------------------------------------------------------------- mapping
def test_optimisation_lowers_loss_and_improves_render(scene):
    pose = pose_at()
    img, depth = render_view(scene, pose)
    mp = Mapper(small_cfg(iters_first=0, downsample_first=4), K)
    mp.add_keyframe(0, img, pose, depth)
    kf = mp.keyframes[0]

    def loss():
        with torch.no_grad():
            return float(view_loss(kf, mp._raster(kf.pose), mp.expose, mp.mcfg.rgb_weight))
    l0 = loss()
    p0 = psnr(mp.render(pose)[0], img)
    optimise(mp, 80)
    assert loss() < 0.5 * l0
    p1 = psnr(mp.render(pose)[0], img)
    assert p1 > p0 + 3 and p1 > 24, (p0, p1)
    st = mp.stats()
    assert st["iterations"] == 80 and st["gaussians"] == len(mp.map) > 0


def test_add_keyframe_decides_window_membership(scene):
    mp = Mapper(small_cfg(iters_first=30, iters_per_keyframe=5), K)
    p0 = pose_at()
    img, d = render_view(scene, p0)
    st = mp.add_keyframe(0, img, p0, d)
    assert st["mapped"] and st["reason"] == "first" and st["new_gaussians"] > 0
    # the same view again adds nothing
    st = mp.add_keyframe(1, img, p0, d)
    assert not st["mapped"] and st["reason"] == "redundant" and st["keyframes"] == 1
    # a large move is mapped
    p2 = pose_at(0.8, 0, 0.3)
    img2, d2 = render_view(scene, p2)
    st = mp.add_keyframe(2, img2, p2, d2)
    assert st["mapped"] and st["keyframes"] == 2 and mp.window.window == [2, 0]
    with pytest.raises(MapError, match="already mapped"):
        mp.add_keyframe(2, img2, p2, d2)
    with pytest.raises(MapError, match="image"):
        mp.add_keyframe(3, img2[:10], p2, d2)
    with pytest.raises(MapError, match="pose"):
        mp.add_keyframe(3, img2, np.eye(3), d2)


def test_depth_weights_scale_the_depth_loss_and_follow_updates(scene):
    from splat_slam_ros.types import ProxyDepth
    mp = Mapper(small_cfg(iters_first=1, iters_per_keyframe=1), K)
    p0 = pose_at()
    img, d = render_view(scene, p0)
    src = np.where(d > 0, ProxyDepth.SOURCE_MULTIVIEW, ProxyDepth.SOURCE_EMPTY).astype(np.uint8)
    src[:, : W // 2][d[:, : W // 2] > 0] = ProxyDepth.SOURCE_BA    # left half: BA-filled holes
    pd = ProxyDepth(0, d, src, p0)
    assert pd.depth_weight(1.0).dtype == bool                       # weight 1: a plain mask
    w = pd.depth_weight(0.25)
    assert set(np.unique(w)) <= {0.0, 0.25, 1.0} and (w[src == ProxyDepth.SOURCE_BA] == 0.25).all()
    mp.add_keyframe(0, img, p0, d * 1.1, w)                     # 10 % off: a depth loss
    kf = mp.keyframes[0]
    assert (kf.valid.numpy() == (src > 0)).all()                # BA pixels have depth ...
    m = mp.map.means.detach().numpy()                           # ... but seed no Gaussian
    u = K.fx * m[:, 0] / m[:, 2] + K.cx
    assert len(m) > 10 and (u > W // 2 - 1).all()
    with torch.no_grad():
        out = mp._raster(p0)
        lw = view_loss(kf, out, mp.expose, mp.mcfg.rgb_weight)
        kf.weight = None
        l1 = view_loss(kf, out, mp.expose, mp.mcfg.rgb_weight)
        kf.weight = torch.from_numpy(w.astype(np.float32) * 0)
        l0 = view_loss(kf, out, mp.expose, mp.mcfg.rgb_weight)
    assert l0 < lw < l1
    e = (out.depth - kf.depth).abs().numpy() * (src > 0)
    frac = (w * e).sum() / e.sum()                              # the weighted share of |dD|
    assert float((lw - l0) / (l1 - l0)) == pytest.approx(float(frac), rel=1e-3)
    # an update with a plain mask drops the weights; 0 weight is no depth
    mp.apply_update(0, p0, d, d > 0)
    assert kf.weight is None
    mp.apply_update(0, p0, d, np.where(d > 0, 0.0, 1.0))
    assert not kf.valid.any()
    with pytest.raises(MapError, match="ba_depth_weight"):
        Mapper(small_cfg(ba_depth_weight=1.5), K)
    with pytest.raises(MapError, match="init_scale"):
        Mapper(small_cfg(init_scale=0.0), K)


def test_negative_focal_length_is_rejected_clearly():
    with pytest.raises(MapError, match="positive focal"):
        Mapper(small_cfg(), Intrinsics(100, -100, 10, 10, 20, 20))


def test_map_sequence_gt_poses_and_depth(scene, tmp_path):
    frames = []
    for i in range(4):
        p = pose_at(0.15 * i, 0, 0.1 * i, 0.05 * i)
        img, d = render_view(scene, p)
        frames.append(Frame(i, 0.1 * i, img, K, gt_pose=p, gt_depth=d))
    cfg = small_cfg(iters_first=60, iters_per_keyframe=10, final_refine_iters=10,
                    downsample_first=4, downsample=8)
    mapper, m = map_sequence(frames, cfg, K, progress=False, keyframe_every=2)
    assert m["keyframes"] == 2 and sorted(mapper.keyframes) == [0, 2]
    assert m["psnr"] > 22 and m["depth_l1_cm"] < 10, m
    assert m["gaussians"] == len(mapper.map) and m["map_mb"] > 0
    ts, P = mapper.keyframe_trajectory()
    np.testing.assert_allclose(ts, [0.0, 0.2])
    # every frame offered: the rules pick at least the first one
    cfg.mapping.iters_first, cfg.mapping.iters_per_keyframe = 5, 2
    mapper2, m2 = map_sequence(frames, cfg, K, progress=False, keyframe_every=0,
                               refine_iters=0)
    assert 1 <= m2["keyframes"] <= 4 and m2["frames_offered"] == 4
    # novel views (all frames, at their ground-truth poses)
    ev = evaluate_map(mapper, frames)
    assert ev["views"] == 4 and ev["psnr"] > 18
    # PLY round trip renders the same image
    mapper.save_ply(tmp_path / "m.ply")
    loaded = Mapper.load_ply(tmp_path / "m.ply", cfg, K)
    a = mapper.render(frames[1].gt_pose)[0].astype(int)
    b = loaded.render(frames[1].gt_pose)[0].astype(int)
    assert np.abs(a - b).max() <= 1
    assert save_renders(mapper, tmp_path / "r") == 2 and (tmp_path / "r" / "kf_00002.png").is_file()
    with pytest.raises(MapError, match="ground-truth pose"):
        map_sequence([Frame(0, 0.0, frames[0].image, K, gt_depth=frames[0].gt_depth)], cfg, K,
                      progress=False)


def _vignetted(img, v1):
    ys, xs = np.mgrid[0:H, 0:W]
    r2 = ((xs - K.cx) ** 2 + (ys - K.cy) ** 2) / (0.25 * (W * W + H * H))
    return np.clip(img * (1.0 + v1 * r2)[..., None] + 0.5, 0, 255).astype(np.uint8)


def test_learned_vignetting_explains_a_radial_falloff(scene):
    """mapping.vignetting: a camera whose corners are 30 % darker; the map learns the falloff
    (v1 < 0) from views that see the same wall at different radii, renders the keyframes
    better than a map without it, and keeps it through its saved state (map_state)."""
    poses = [pose_at(), pose_at(0.6, 0, 0), pose_at(-0.6, 0, 0), pose_at(0, -0.4, 0.4),
             pose_at(0.3, 0.3, -0.3)]
    views = [render_view(scene, p) for p in poses]
    res = {}
    for on in (True, False):
        mp = Mapper(small_cfg(iters_first=60, iters_per_keyframe=40, final_refine_iters=100,
                              downsample_first=2, downsample=2, kf_covisibility=1.0,
                              vignetting=on), K)
        for i, (p, (img, d)) in enumerate(zip(poses, views)):
            mp.add_keyframe(i, _vignetted(img, -0.3), p, d)
        mp.final_refine()
        assert len(mp.keyframes) == len(poses)
        res[on] = (evaluate_keyframes(mp)["psnr"], mp.vignette.detach().clone(), mp)
    assert float(res[True][1][0]) < -0.1 and res[False][1].abs().max() == 0, res
    assert res[True][0] > res[False][0] + 1.0, (res[True][0], res[False][0])
    mp = res[True][2]
    with torch.no_grad():
        v = mp.camera.vignetting(H, W, mp.intr)[..., 0]
    corner = 1 + float(mp.vignette.detach().sum())          # r = 1 at a corner (centred camera)
    assert float(v[int(K.cy), int(K.cx)]) == pytest.approx(1.0, abs=1e-3)
    assert float(v[0, 0]) == pytest.approx(corner, abs=0.03)
    K2 = K.scaled(2.0, 2.0)                                   # the same falloff at any size
    with torch.no_grad():
        v2 = mp.camera.vignetting(2 * H, 2 * W, (K2.fx, K2.fy, K2.cx, K2.cy))[..., 0]
    assert float(v2[0, 0]) == pytest.approx(corner, abs=0.03)
    arrays, meta = map_state(mp)
    assert meta["vignette"] == pytest.approx(mp.vignette.tolist())


# -------------------------------------------------------------- lattice steps
def test_a_lattice_render_is_the_full_render_at_its_pixels(scene):
    from splat_slam_ros.mapping.optimise import lattice
    from splat_slam_ros.mapping.rasterizer import rasterize
    V = se3_inverse(torch.as_tensor(pose_at(0.1, 0.0, 0.2))).float()
    intr = (K.fx, K.fy, K.cx, K.cy)
    full = rasterize(*scene, V, intr, W, H)
    for n, dx, dy in [(2, 0, 0), (2, 1, 1), (3, 2, 1)]:
        li, w, h = lattice(intr, W, H, n, dx, dy)
        # lattice pixel (i, j) is full pixel (n i + dx, n j + dy), filtered as in the full image
        out = rasterize(*scene, V, li, w, h, low_pass=0.3 / n ** 2)
        assert out.rgb.shape == full.rgb[dy::n, dx::n].shape
        assert (out.rgb - full.rgb[dy::n, dx::n]).abs().max() < 1e-4, (n, dx, dy)
        assert (out.depth - full.depth[dy::n, dx::n]).abs().max() < 1e-4, (n, dx, dy)
        torch.testing.assert_close(out.means2d, (full.means2d - torch.tensor([dx, dy])) / n)
        # with the lattice's own filter (0.3 of its pixels^2) the ~1 px Gaussians blur
        blurred = rasterize(*scene, V, li, w, h)
        assert (blurred.rgb - full.rgb[dy::n, dx::n]).abs().mean() > 0.02


def test_lattice_steps_train_the_map_like_full_steps(scene):
    from splat_slam_ros.mapping.optimise import _step
    pose = pose_at()
    img, depth = render_view(scene, pose)

    def fresh(n):
        mp = Mapper(small_cfg(iters_first=0, downsample_first=4, step_subsample=n), K)
        mp.add_keyframe(0, img, pose, depth)
        return mp
    # one step's densification statistic (NDC positional gradient) in the same units
    grads = []
    for n in (1, 2):
        mp = fresh(n)
        _step(mp, [0], densify=True, subsample=n)
        seen = mp.map.grad_count > 0
        grads.append(float((mp.map.grad_accum[seen] / mp.map.grad_count[seen]).mean()))
    assert 0.7 < grads[1] / grads[0] < 1.4, grads
    # lattice steps alone fit the view at full resolution, the exposure included
    mp = fresh(2)
    p0 = psnr(mp.render(pose)[0], img)
    optimise(mp, 80, subsample=2)
    p1 = psnr(mp.render(pose)[0], img)
    assert p1 > p0 + 3 and p1 > 24, (p0, p1)
    with pytest.raises(MapError, match="step_subsample"):
        Mapper(small_cfg(step_subsample=0), K)


def test_lattice_steps_keep_full_resolution_visible_sets(scene):
    # a lattice render misses small Gaussians: the window's visible sets come from full renders
    pose = pose_at()
    img, depth = render_view(scene, pose)
    mp = Mapper(small_cfg(iters_first=20, iters_per_keyframe=5, step_subsample=3), K)
    mp.add_keyframe(0, img, pose, depth)
    with torch.no_grad():
        full = set(mp.map.uid[mp._raster(pose).visible].tolist())
    assert set(mp.window.visibility[0].tolist()) == full
    assert not mp.add_keyframe(1, img, pose, depth)["mapped"]       # the same view: redundant


def test_the_newest_keyframe_can_keep_full_resolution_steps(scene, monkeypatch):
    """mapping.step_subsample_newest: the first view of a keyframe step (the newest keyframe)
    at its own lattice (1 = full resolution), the other views on step_subsample's."""
    from splat_slam_ros.mapping import mapper as mapper_mod
    p0, p1 = pose_at(), pose_at(0.3, 0, 0.1)
    sizes = []
    real = mapper_mod.Mapper._raster

    def spy(self, pose, intr=None, width=None, height=None, **kw):
        if kw.get("attrs") is not None:             # a training render
            sizes.append(width or self.W)
        return real(self, pose, intr, width, height, **kw)
    monkeypatch.setattr(mapper_mod.Mapper, "_raster", spy)
    for newest, expect in ((0, [W // 2, W // 2]), (1, [W, W // 2])):
        mp = Mapper(small_cfg(iters_first=2, iters_per_keyframe=1, step_subsample=2,
                              step_subsample_newest=newest, random_views_per_iter=0), K)
        for k, p in enumerate((p0, p1)):
            img, d = render_view(scene, p)
            mp.add_keyframe(k, img, p, d, force=True)
        assert sizes[-2:] == expect, (newest, sizes)
        sizes.clear()
    with pytest.raises(MapError, match="step_subsample_newest"):
        Mapper(small_cfg(step_subsample_newest=9), K)


def test_keyframes_mapped_without_a_step_share_one_visibility_pruning(scene, monkeypatch):
    """Live input waiting: a keyframe mapped without an optimisation step changed no Gaussian
    but its own, so its visibility pruning (which renders every stale window view first)
    waits for a later keyframe, at most prune_recent_kfs - 1 of them: every such keyframe's
    Gaussians are still among the candidates of a pruning after it. Keyframes with steps
    prune each time, as offline."""
    poses = [pose_at(0.08 * k, 0.0, 0.02 * k) for k in range(10)]
    views = [render_view(scene, p) for p in poses]

    def run(min_steps):
        calls = []                   # (newest keyframe index, candidate lower bound)
        mp = Mapper(small_cfg(iters_first=5, iters_per_keyframe=2, window_size=3,
                              prune_covis_min=1, prune_recent_kfs=3, time_budget=True), K)
        strategy = type(mp.strategy)
        real = strategy.visibility_prune

        def spy(self, m):
            calls.append((m.next_index - 1, m.next_index - m.mcfg.prune_recent_kfs))
            return real(self, m)
        monkeypatch.setattr(strategy, "visibility_prune", spy)
        steps = []
        for k, (p, (img, d)) in enumerate(zip(poses, views)):
            st = mp.add_keyframe(k, img, p, d, force=True, yield_to=lambda: True,
                                 min_steps=min_steps)
            steps.append(st["steps"])
        monkeypatch.undo()
        return mp, calls, steps
    _, calls_with, steps_with = run(1)
    assert min(steps_with[1:]) >= 1
    full = [i for i, _ in calls_with]
    assert full == list(range(full[0], 10))          # every keyframe once the window is full
    mp, calls, steps = run(0)
    assert steps[1:] == [0] * 9
    assert 0 < len(calls) <= len(calls_with) // 3 + 1, (calls, calls_with)
    # every keyframe from the first pruning on is judged by a pruning at or after it
    for k in range(calls[0][0], calls[-1][0] + 1):
        assert any(i >= k >= lo for i, lo in calls), (k, calls)
