"""Tests for the synthetic RGB-D sequence generator (splat_slam_synth, splat-slam-synth)."""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

import splat_slam_synth as synth
from splat_slam_synth.cli import main as synth_main
from splat_slam_ros.io.trajectory_io import read_trajectory
from splat_slam_ros.types import Intrinsics

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
TRAJ = SHARED / "trajectories"


def _traj(name: str) -> Path:
    p = TRAJ / name
    if not p.is_file():
        pytest.skip(f"{p} not found (shared data only present in the dev setup)")
    return p


# ------------------------------------------------------------------ helpers
def load_seq(out: Path):
    """Read a generated sequence back with plain OpenCV / numpy (independent of synth)."""
    rows = [l.split() for l in (out / "rgb.txt").read_text().splitlines() if not l.startswith("#")]
    drows = [l.split() for l in (out / "depth.txt").read_text().splitlines()
             if not l.startswith("#")]
    stamps = np.array([float(r[0]) for r in rows])
    rgb = [cv2.cvtColor(cv2.imread(str(out / r[1]), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB)
           for r in rows]
    depth_raw = [cv2.imread(str(out / r[1]), cv2.IMREAD_UNCHANGED) for r in drows]
    ts, poses = read_trajectory(out / "groundtruth.txt", fmt="tum")
    K = Intrinsics.from_yaml(out / "intrinsics.yaml")
    return stamps, rgb, depth_raw, ts, poses, K, [float(r[0]) for r in drows]


def jittery_trajectory(duration=4.0, rate=100.0, seed=1, yaw_rate=0.4, speed=0.15):
    """A z-up hand-held-like path sampled with timestamp jitter, one duplicated stamp and
    rows out of order (like motion-capture files)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, duration, 1 / rate) + rng.uniform(-0.002, 0.002, int(round(duration * rate)))
    t[0] = 0.0
    t = np.sort(t)
    yaw = yaw_rate * t + 0.1 * np.sin(2 * t)
    pitch = -0.3 + 0.05 * np.sin(3 * t)
    P = np.tile(np.eye(4), (len(t), 1, 1))
    base = Rotation.from_euler("xyz", [-np.pi / 2, 0, -np.pi / 2])   # cam z -> world +x, y -> -z
    for i in range(len(t)):
        R = Rotation.from_euler("zy", [yaw[i], -pitch[i]]) * base
        P[i, :3, :3] = R.as_matrix()
        P[i, :3, 3] = [speed * t[i], 0.1 * np.sin(t[i]), 1.4 + 0.02 * np.sin(5 * t[i])]
    # repeat a stamp with a jittered pose (the first copy must win) and swap two rows
    dup = P[50].copy()
    dup[:3, 3] += 0.008
    t, P = np.insert(t, 51, t[50]), np.insert(P, 51, dup, axis=0)
    t[[10, 11]], P[[10, 11]] = t[[11, 10]], P[[11, 10]].copy()
    return t, P


def gen(tmp_path, name, trajectory="builtin", frames=4, size="64x48", **kw):
    return synth.generate_sequence(trajectory, frames, size, tmp_path / name, progress=False, **kw)


@pytest.fixture(scope="module")
def clean_seq(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "clean"
    return synth.generate_sequence("builtin", 8, "160x120", out, progress=False, seed=3, fps=10.0)


# -------------------------------------------------------------- layout / formats
def test_layout_and_formats(clean_seq):
    out = clean_seq
    for p in ("rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.yaml"):
        assert (out / p).exists(), p
    stamps, rgb, depth_raw, ts, poses, K, dstamps = load_seq(out)
    assert len(rgb) == len(depth_raw) == len(ts) == 8
    assert np.allclose(stamps, dstamps) and np.allclose(stamps, ts)
    assert all(im.shape == (120, 160, 3) and im.dtype == np.uint8 for im in rgb)
    assert all(d.shape == (120, 160) and d.dtype == np.uint16 for d in depth_raw)
    assert sorted(p.name for p in (out / "rgb").iterdir()) == [f"{t:.6f}.png" for t in stamps]
    # intrinsics round trip + extra keys
    assert (K.width, K.height) == (160, 120)
    assert K.fx == pytest.approx(525 * 160 / 640) and K.fy == K.fx
    assert (K.cx, K.cy) == (79.5, 59.5)
    import yaml
    y = yaml.safe_load((out / "intrinsics.yaml").read_text())
    assert y["depth_scale"] == 5000.0 and y["fps"] == 10.0
    assert y["generation"]["frames"] == 8 and y["generation"]["seed"] == 3
    # depth png = round(depth * 5000) of the exact render
    plan = synth.plan_sequence("builtin", 8, "160x120", seed=3, fps=10.0)
    assert np.allclose(plan.poses, poses, atol=1e-8)
    for k in (0, 7):
        _, depth = synth.render_frame(plan.scene, plan.poses[k], K)
        assert np.array_equal(depth_raw[k], np.round(depth.astype(np.float64) * 5000))
        assert 0.3 < np.median(depth) < 4.0


def test_depth_png_range():
    d = np.array([[0.0, 1.0, 13.1, 13.2, np.inf, np.nan]])
    assert synth.depth_to_png16(d).tolist() == [[0, 5000, 65500, 0, 0, 0]]


# ------------------------------------------------------- stamps and ground truth
def _interp_reference(t, P, stamps):
    """Independent linear/SLERP interpolation (scipy) after sorting and dropping
    repeated stamps (first kept)."""
    order = np.argsort(t, kind="stable")
    t, P = t[order], P[order]
    keep = np.concatenate([[True], np.diff(t) > 1e-6])
    t, P = t[keep], P[keep]
    slerp = Slerp(t, Rotation.from_matrix(P[:, :3, :3]))
    R = slerp(stamps).as_matrix()
    xyz = np.stack([np.interp(stamps, t, P[:, i, 3]) for i in range(3)], 1)
    return xyz, R


def _check_gt(out, t, P, fps, t0):
    stamps, _, _, ts, poses, _, _ = load_seq(out)
    assert stamps[0] == pytest.approx(t0, abs=1e-6)
    assert np.allclose(np.diff(stamps), 1 / fps, atol=2e-6)
    xyz, R = _interp_reference(t, P, ts)
    assert np.abs(poses[:, :3, 3] - xyz).max() < 2e-6
    dR = Rotation.from_matrix(np.einsum("nji,njk->nik", R, poses[:, :3, :3])).magnitude()
    assert dR.max() < 1e-6


def test_groundtruth_is_interpolated_pose_jittery(tmp_path):
    t, P = jittery_trajectory()
    out = gen(tmp_path, "jit", (t, P), frames=20, fps=15.0, start=0.25)
    _check_gt(out, t, P, 15.0, t.min() + 0.25)


def test_groundtruth_is_interpolated_pose_fr1(tmp_path):
    path = _traj("freiburg1_xyz-groundtruth.txt")
    t, P = read_trajectory(path)
    out = gen(tmp_path, "fr1", str(path), frames=6, size="32x24", start=2.0)
    _check_gt(out, t, P, 30.0, t[0] + 2.0)


def test_gap_warning_names_a_clean_window(capsys):
    t = np.concatenate([np.arange(0, 2, 0.01), np.arange(5, 9, 0.01)])   # 3 s gap
    P = np.tile(np.eye(4), (len(t), 1, 1))
    P[:, 0, 3] = 0.05 * t
    it = synth.PoseInterpolator(t, P)
    a, b = it.longest_gap_free()
    assert a == pytest.approx(5.0) and b == pytest.approx(8.99)
    plan = synth.plan_sequence((t, P), 10, "16x12", start=2.5, fps=10.0)
    err = capsys.readouterr().err
    assert "10 of 10 frames fall in ground-truth gaps" in err and "--start 5.0" in err
    assert plan.record["gt_gap_frames"] == 10


def test_interpolator_handles_mocap_artifacts():
    t, P = jittery_trajectory()
    it = synth.PoseInterpolator(t, P)
    assert it.dropped_duplicates == 1
    q = np.linspace(0, 3.9, 57)
    xyz, R = _interp_reference(t, P, q)
    Tq = it(q)
    assert np.abs(Tq[:, :3, 3] - xyz).max() < 1e-9
    assert np.allclose(Tq[:, :3, :3], R, atol=1e-9)
    # exactly at the rows: the rows themselves; outside the range: clamped
    assert np.allclose(it(t[60:65]), P[60:65], atol=1e-9)
    assert np.allclose(it([-5.0])[0], it([it.t_start])[0])


# -------------------------------------------------------------- analytic depth
def _rays(K):
    v, u = np.mgrid[0:K.height, 0:K.width].astype(float)
    return np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], -1)


def test_depth_fronto_parallel_wall_is_plane_distance():
    scene = synth.make_scene([-2, -2.5, -1.2], [3, 2.5, 1.5], seed=0)
    K = synth.default_intrinsics(64, 48)
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)   # looks along +x
    T[:3, 3] = [0.4, 0.2, 0.1]
    rgb, depth = synth.render_frame(scene, T, K)
    X = (_rays(K) * depth[..., None]) @ T[:3, :3].T + T[:3, 3]
    on_wall = np.abs(X[..., 0] - 3.0) < 1e-4
    assert on_wall[10:38, 10:54].all()          # the image centre sees the x = 3 wall
    assert np.allclose(depth[on_wall], 3.0 - 0.4, atol=1e-5)
    assert rgb.std() > 5                        # textured, not flat


def test_depth_generic_view_lies_on_room_planes_and_box():
    lo, hi = np.array([-2, -2.5, -1.2]), np.array([3, 2.5, 1.5])
    blo, bhi = np.array([[1.0, -0.3, -1.2]]), np.array([[1.6, 0.4, -0.2]])
    scene = synth.make_scene(lo, hi, blo, bhi, seed=1)
    K = synth.default_intrinsics(80, 60)
    R = Rotation.from_euler("xyz", [-np.pi / 2 - 0.5, 0.1, -np.pi / 2 + 0.2]).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [0.0, 0.1, 0.3]
    _, depth = synth.render_frame(scene, T, K)
    d = _rays(K) @ R.T
    X = (_rays(K) * depth[..., None]) @ R.T + T[:3, 3]
    # independent analytic nearest hit: min positive distance over the 6 room planes and
    # the box (point-in-face test on each box plane)
    o = T[:3, 3]
    cand = []
    for a in range(3):
        for plane in (lo[a], hi[a]):
            cand.append(np.where(d[..., a] != 0, (plane - o[a]) / d[..., a], np.inf))
        for plane in (blo[0, a], bhi[0, a]):
            tt = (plane - o[a]) / d[..., a]
            P = o + tt[..., None] * d
            others = [b for b in range(3) if b != a]
            inside = np.all([(P[..., b] >= blo[0, b]) & (P[..., b] <= bhi[0, b]) for b in others], 0)
            cand.append(np.where(inside & (tt > 0), tt, np.inf))
    cand = np.stack(cand)
    cand[cand <= 0] = np.inf
    t_ref = cand.min(0)
    assert np.isfinite(t_ref).all()
    assert np.allclose(depth, t_ref, rtol=1e-5, atol=1e-5)
    box_px = np.all((X >= blo[0] - 1e-4) & (X <= bhi[0] + 1e-4), -1)
    assert 0.05 < box_px.mean() < 0.9           # the box occludes part of the view


@pytest.mark.parametrize("model,dist", [("plumb_bob", [-0.25, 0.08, 0.001, -0.001, 0.0]),
                                        ("equidistant", [0.05, -0.02, 0.01, 0.0])])
def test_distorted_camera(model, dist):
    """Distorted intrinsics: each pixel's 3D point projects back onto it with OpenCV's model,
    and a fronto-parallel wall still has constant z-depth."""
    scene = synth.make_scene([-2, -2.5, -1.2], [3, 2.5, 1.5], seed=0)
    K = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48, model, dist)
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    T[:3, 3] = [0.4, 0.2, 0.1]
    rgb, depth = synth.render_frame(scene, T, K)
    Kp = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    rgb_p, _ = synth.render_frame(scene, T, Kp)
    assert np.abs(rgb.astype(float) - rgb_p).mean() > 2      # distortion changes the image
    # pixels seeing the x = 3 wall: constant z-depth; 3D points reproject onto their pixels
    v, u = np.mgrid[8:40, 8:56]
    z = depth[v, u]
    assert np.allclose(z, 2.6, atol=1e-5)
    pts = np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if model == "equidistant":
        xy = cv2.fisheye.undistortPoints(pts, K.K, np.array(dist), criteria=crit).reshape(-1, 2)
        X = np.concatenate([xy, np.ones((len(xy), 1))], 1) * z.reshape(-1, 1)
        uv = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K.K,
                                       np.array(dist))[0]
    else:
        xy = cv2.undistortPoints(pts, K.K, np.array(dist), criteria=crit).reshape(-1, 2)
        X = np.concatenate([xy, np.ones((len(xy), 1))], 1) * z.reshape(-1, 1)
        uv = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K.K, np.array(dist))[0]
    assert np.abs(uv.reshape(-1, 2) - pts.reshape(-1, 2)).max() < 1e-3


# ------------------------------------------------------ photometric consistency
def _warp_error(rgbA, dA, rgbB, dB, TA, TB, K):
    """Project frame A's pixels into B with A's depth and the GT poses; return the median
    colour difference over pixels visible in both (depth-consistent) and that fraction."""
    X = _rays(K) * dA[..., None]
    T_BA = np.linalg.inv(TB) @ TA
    Xb = X @ T_BA[:3, :3].T + T_BA[:3, 3]
    z = Xb[..., 2]
    u = K.fx * Xb[..., 0] / np.maximum(z, 1e-6) + K.cx
    v = K.fy * Xb[..., 1] / np.maximum(z, 1e-6) + K.cy
    H, W = dA.shape
    ok = (z > 0.1) & (u > 1) & (u < W - 2) & (v > 1) & (v < H - 2) & (dA > 0)
    ui, vi = np.round(u[ok]).astype(int), np.round(v[ok]).astype(int)
    vis = np.abs(dB[vi, ui] - z[ok]) < 0.02 * z[ok]
    mapx, mapy = u.astype(np.float32), v.astype(np.float32)
    warped = cv2.remap(rgbB.astype(np.float32), mapx, mapy, cv2.INTER_LINEAR)
    diff = np.abs(warped[ok][vis] - rgbA[ok][vis].astype(np.float32)).mean(-1)
    return float(np.median(diff)), float(vis.mean() * ok.mean())


def test_photometric_consistency_of_written_sequence(clean_seq):
    """A 3D point seen in frame A has the same colour where the GT poses/depth put it in B:
    catches camera-to-world vs world-to-camera and axis-convention bugs in what is written."""
    _, rgb, depth_raw, _, poses, K, _ = load_seq(clean_seq)
    dA, dB = depth_raw[0] / 5000.0, depth_raw[7] / 5000.0
    moved = np.linalg.norm(poses[7, :3, 3] - poses[0, :3, 3])
    assert moved > 0.05
    err, frac = _warp_error(rgb[0], dA, rgb[7], dB, poses[0], poses[7], K)
    assert frac > 0.6 and err < 2.5, (err, frac)
    # the same check with the inverse (world-to-camera) convention fails clearly
    bad, bad_frac = _warp_error(rgb[0], dA, rgb[7], dB, np.linalg.inv(poses[0]),
                                np.linalg.inv(poses[7]), K)
    assert bad > 6 * err and bad_frac < 0.8 * frac, (bad, err, bad_frac, frac)
    # and a 3 cm pose error is visible too
    Tb = poses[7].copy()
    Tb[:3, 3] += [0.03, 0, 0]
    off, _ = _warp_error(rgb[0], dA, rgb[7], dB, poses[0], Tb, K)
    assert off > 3 * err, (off, err)


def test_flow_is_trackable_with_dis():
    """The procedural textures carry enough detail for DIS optical flow."""
    plan = synth.plan_sequence("builtin", 3, "160x120", seed=5)
    K = plan.intrinsics
    a, dA = synth.render_frame(plan.scene, plan.poses[0], K)
    b, _ = synth.render_frame(plan.scene, plan.poses[2], K)
    X = _rays(K) * dA[..., None]
    T = np.linalg.inv(plan.poses[2]) @ plan.poses[0]
    Xb = X @ T[:3, :3].T + T[:3, 3]
    u = K.fx * Xb[..., 0] / Xb[..., 2] + K.cx
    v = K.fy * Xb[..., 1] / Xb[..., 2] + K.cy
    gt = np.stack([u - np.arange(160)[None], v - np.arange(120)[:, None]], -1)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(cv2.cvtColor(a, cv2.COLOR_RGB2GRAY), cv2.cvtColor(b, cv2.COLOR_RGB2GRAY), None)
    inner = (slice(10, 110), slice(10, 150))
    epe = np.linalg.norm(flow - gt, axis=-1)[inner]
    assert np.linalg.norm(gt, axis=-1)[inner].mean() > 0.5       # the camera moved
    assert np.median(epe) < 0.5, np.median(epe)


# ------------------------------------------------------------------- realism
def _grad_energy(img):
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)
    return float((np.diff(g, axis=0) ** 2).mean() + (np.diff(g, axis=1) ** 2).mean())


@pytest.fixture(scope="module")
def fast_plan_args():
    t, P = jittery_trajectory(duration=2.0, yaw_rate=2.5, speed=0.8)   # fast pan
    return dict(trajectory=(t, P), frames=3, size="96x72", seed=2)


def test_realism_changes_images_as_expected(fast_plan_args):
    a = dict(fast_plan_args)
    clean = synth.plan_sequence(**a)
    rgb0, d0 = clean.render(2)

    def with_options(**kw):       # same scene and poses, other camera effects
        return replace(clean, realism=synth.resolve_realism(**kw).validate(clean.fps))

    blur = synth.plan_sequence(**a, motion_blur=6, exposure_ms=30)
    assert np.array_equal(blur.poses, clean.poses)
    rgb_b, d_b = blur.render(2)
    assert _grad_energy(rgb_b) < 0.8 * _grad_energy(rgb0)
    assert np.array_equal(d_b, d0)                      # depth stays exact
    noisy = with_options(noise=6.0).render(2)[0]
    resid = noisy.astype(float) - rgb0
    assert 3.0 < resid.std() < 9.0 and abs(resid.mean()) < 1.0
    # shot noise: brighter pixels are noisier
    bright = rgb0.astype(float) > 150
    dark = rgb0.astype(float) < 60
    if bright.sum() > 200 and dark.sum() > 200:
        assert resid[bright].std() > resid[dark].std()
    jp = with_options(jpeg=30).render(2)[0]
    mad = np.abs(jp.astype(float) - rgb0).mean()
    assert 0.5 < mad < 20
    vig = with_options(vignetting=0.5).render(2)[0].astype(float)
    ratio = vig / np.maximum(rgb0.astype(float), 1)
    assert ratio[30:42, 42:54].mean() > 0.95 and ratio[:6, :6].mean() < 0.6
    ae = with_options(auto_exposure=0.2)
    eff = synth.CameraEffects(ae.realism, ae.intrinsics, ae.seed)
    gains = [eff.gain_offset(t)[0] for t in np.linspace(0, 20, 200)]
    assert 0.8 - 1e-9 <= min(gains) < 0.97 and 1.03 < max(gains) <= 1.2 + 1e-9
    assert np.abs(np.diff(gains)).max() < 0.02          # slow, smooth drift
    g, b = eff.gain_offset(float(ae.stamps[2] - ae.stamps[0]))
    assert abs(g - 1) > 1e-3
    x0 = clean.render(2)[0].astype(float)
    unclipped = (x0 > 20) & (x0 < 200)
    assert np.abs(ae.render(2)[0][unclipped] - (g * x0[unclipped] + b)).max() <= 1.1  # 2 roundings
    # the preset switches the effects on, explicit options override it
    r = synth.resolve_realism("realistic", noise=0.0)
    assert r.motion_blur > 1 and r.jpeg > 0 and r.vignetting > 0 and r.noise == 0.0


def test_realistic_sequence_keeps_depth_and_poses(tmp_path):
    a = gen(tmp_path, "a", frames=3, seed=4)
    b = gen(tmp_path, "b", frames=3, seed=4, realism="realistic")
    _, ra, da, _, pa, _, _ = load_seq(a)
    _, rb, db, _, pb, _, _ = load_seq(b)
    assert all(np.array_equal(x, y) for x, y in zip(da, db))
    assert np.array_equal(pa, pb)
    assert not np.array_equal(ra[1], rb[1])


def test_device_option():
    import torch
    if not torch.cuda.is_available():
        with pytest.raises(synth.SynthError, match="CUDA"):
            synth.plan_sequence("builtin", 2, "32x24", device="cuda")
        return
    plan = synth.plan_sequence("builtin", 2, "64x48", device="cuda")
    rgb_g, d_g = plan.render(1)
    rgb_c, d_c = replace(plan, device="cpu").render(1)
    assert np.abs(d_g - d_c).max() < 1e-4
    assert np.median(np.abs(rgb_g.astype(float) - rgb_c)) <= 1


def test_plan_frames_are_the_written_frames(tmp_path):
    """``SequencePlan.frames``: in memory, the same images, stamps and camera as the files."""
    from splat_slam_ros.io.datasets import open_dataset
    plan = synth.plan_sequence("builtin", 3, "64x48", realism="realistic", warn=False)
    frames = plan.frames()
    assert [f.index for f in frames] == [0, 1, 2] and len(plan.frames(2)) == 2
    out = gen(tmp_path, "w", frames=3, size="64x48", realism="realistic")
    written = list(open_dataset(out))
    for f, w in zip(frames, written):
        assert abs(f.timestamp - w.timestamp) < 1e-6 and f.intrinsics.fx == w.intrinsics.fx
        assert np.abs(f.image.astype(int) - np.asarray(w.image, int)).max() <= 1


# --------------------------------------------------------------- determinism
def test_deterministic_with_seed(tmp_path):
    a = gen(tmp_path, "a", frames=3, seed=7, noise=2.0)
    b = gen(tmp_path, "b", frames=3, seed=7, noise=2.0)
    c = gen(tmp_path, "c", frames=3, seed=8, noise=2.0)
    ra, rb, rc = (load_seq(x)[1] for x in (a, b, c))
    assert all(np.array_equal(x, y) for x, y in zip(ra, rb))
    assert not np.array_equal(ra[0], rc[0])
    assert (a / "groundtruth.txt").read_text() == (b / "groundtruth.txt").read_text()


# ------------------------------------------------------- scene fit on real paths
@pytest.mark.parametrize("name,start", [("freiburg1_xyz-groundtruth.txt", 0.0),
                                        ("fr2_desk_groundtruth.txt", 50.0)])
def test_scene_fits_real_trajectories(name, start):
    path = _traj(name)
    plan = synth.plan_sequence(str(path), 150, "40x30", start=start, seed=0, warn=False)
    sc = plan.scene
    T = sc.T_room_world
    cams = plan.poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    dense = plan.interpolator.positions_between(plan.stamps[0] - 1 / 30, plan.stamps[-1])
    dense = dense @ T[:3, :3].T + T[:3, 3]
    assert np.all(cams > sc.room_lo + 1.0) and np.all(cams < sc.room_hi - 0.8)
    assert sc.n_boxes >= 6
    for lo, hi in zip(sc.boxes_lo, sc.boxes_hi):
        dist = np.linalg.norm(np.maximum(np.maximum(lo - dense, 0), dense - hi), axis=1)
        assert dist.min() >= 0.5 - 1e-9
    empty = sc.without_boxes()
    box_frac, med = [], []
    for k in range(0, 150, 15):
        _, d = synth.render_frame(sc, plan.poses[k], plan.intrinsics)
        _, d_room = synth.render_frame(empty, plan.poses[k], plan.intrinsics)
        med.append(np.median(d))
        assert np.percentile(d, 1) > 0.3
        box_frac.append(np.mean(d < d_room - 1e-3))
    assert 0.5 < min(med) and max(med) < 4.0, med
    assert np.mean(box_frac) > 0.15, box_frac          # boxes where the cameras look


def test_kitti_and_euroc_load(tmp_path):
    k = gen(tmp_path, "kitti", str(_traj("KITTI_00_gt.txt")), frames=3, size="32x24")
    stamps = load_seq(k)[0]
    assert stamps[0] == 0.0 and np.allclose(np.diff(stamps), 1 / 30, atol=2e-6)
    import yaml
    assert yaml.safe_load((k / "intrinsics.yaml").read_text())["generation"]["scene"][
        "up_world"] == [0.0, -1.0, 0.0]
    e = gen(tmp_path, "euroc", str(_traj("V102_groundtruth.csv")), frames=2, size="32x24")
    assert len(load_seq(e)[1]) == 2


# -------------------------------------------------------------------- errors
def _cli(capsys, *args):
    rc = synth_main(list(args) + ["--quiet"])
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("size", ["64x", "abc", "0x48", "64x48x3"])
def test_cli_bad_size(tmp_path, capsys, size):
    rc, err = _cli(capsys, "--frames", "2", "--size", size, "--out", str(tmp_path / "o"))
    assert rc == 2 and err.startswith("error:") and "size" in err


@pytest.mark.parametrize("n", ["0", "-3"])
def test_cli_bad_frames(tmp_path, capsys, n):
    rc, err = _cli(capsys, "--frames", n, "--size", "32x24", "--out", str(tmp_path / "o"))
    assert rc == 2 and "error:" in err and "frames" in err


def test_cli_unreadable_trajectory(tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text("this is not a trajectory\n")
    rc, err = _cli(capsys, "--trajectory", str(bad), "--frames", "2", "--size", "32x24",
                   "--out", str(tmp_path / "o"))
    assert rc == 2 and err.startswith("error:") and "Traceback" not in err
    rc, err = _cli(capsys, "--trajectory", str(tmp_path / "missing.txt"), "--frames", "2",
                   "--out", str(tmp_path / "o"))
    assert rc == 2 and "not found" in err


def test_cli_too_many_frames_says_max(tmp_path, capsys):
    t, P = jittery_trajectory(duration=2.0)
    f = tmp_path / "t.txt"
    from splat_slam_ros.io.trajectory_io import write_tum
    write_tum(f, t[:150], P[:150])           # ~1.49 s of trajectory
    ts = read_trajectory(f)[0]
    expect = int(math.floor((ts[-1] - ts[0]) * 30 + 1e-6)) + 1
    rc, err = _cli(capsys, "--trajectory", str(f), "--frames", "100", "--size", "32x24",
                   "--out", str(tmp_path / "o"))
    assert rc == 2 and f"max --frames is {expect}" in err
    rc, _ = _cli(capsys, "--trajectory", str(f), "--frames", str(expect), "--size", "32x24",
                 "--out", str(tmp_path / "o2"))
    assert rc == 0


def test_cli_nonempty_out_needs_overwrite(tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    rc, err = _cli(capsys, "--frames", "2", "--size", "32x24", "--out", str(out))
    assert rc == 2 and "--overwrite" in err and not (out / "rgb").exists()
    rc, _ = _cli(capsys, "--frames", "2", "--size", "32x24", "--out", str(out), "--overwrite")
    assert rc == 0 and len(list((out / "rgb").iterdir())) == 2


def test_cli_bad_realism_values(tmp_path, capsys):
    for args in (["--jpeg", "101"], ["--exposure", "50"], ["--motion-blur", "0"],
                 ["--vignetting", "1.5"], ["--noise", "-1"]):
        rc, err = _cli(capsys, "--frames", "2", "--size", "32x24", "--out",
                       str(tmp_path / "o"), *args)
        assert rc == 2 and err.startswith("error:"), args


def test_cli_help_documents_options(capsys):
    with pytest.raises(SystemExit):
        synth_main(["--help"])
    text = capsys.readouterr().out
    for opt in ("--trajectory", "--frames", "--size", "--out", "--fps", "--start", "--fov",
                "--intrinsics", "--textures", "--seed", "--realism", "--motion-blur",
                "--exposure", "--auto-exposure", "--vignetting", "--noise", "--jpeg",
                "--overwrite"):
        assert opt in text, opt


def test_cli_writes_sequence_with_textures_and_intrinsics(tmp_path, capsys):
    tex = SHARED / "tum_fr3_long_office_17"
    if not tex.is_dir():
        pytest.skip(f"{tex} not found")
    k = tmp_path / "k.yaml"
    Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480).to_yaml(k)
    rc = synth_main(["--frames", "2", "--size", "64x48", "--intrinsics", str(k), "--textures",
                     str(tex), "--out", str(tmp_path / "o"), "--quiet"])
    assert rc == 0
    K = Intrinsics.from_yaml(tmp_path / "o" / "intrinsics.yaml")
    assert K.width == 64 and K.fx == pytest.approx(53.54)
    import yaml
    names = yaml.safe_load((tmp_path / "o" / "intrinsics.yaml").read_text())["generation"][
        "scene"]["textures"]
    assert any(n.startswith("image:") for n in names)
