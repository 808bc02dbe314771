"""Meshes: TSDF fusion of rendered / ground-truth depth, mesh metrics with known answers,
alignment and culling, clear errors, and the ICL-NUIM map mesh end to end."""
import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import torch

from splat_slam_ros.cli.eval import main as eval_main
from splat_slam_ros.config import MappingConfig, SlamConfig
from splat_slam_ros.evaluation.trajectory import ate
from splat_slam_ros.geometry import se3_exp
from splat_slam_ros.io.datasets import open_dataset
from splat_slam_ros.mapping.mapper import Mapper
from splat_slam_ros.mapping.mesh import (MeshError, auto_voxel, fuse_frames, fuse_views,
                                         load_mesh, map_mesh_output, save_mesh)
from splat_slam_ros.evaluation.mesh import (_ray_depth, cull_mesh, evaluate_meshes, mesh_metrics,
                                      seen_vertices, transform_mesh)
from splat_slam_ros.pipeline import run
from splat_slam_ros.types import Intrinsics

K = Intrinsics(40.0, 40.0, 31.5, 23.5, 64, 48)
N_FAST = 30_000


def plane(x0, x1, y0, y1, z, n=21) -> o3d.geometry.TriangleMesh:
    """Grid mesh of the rectangle [x0,x1]x[y0,y1] at height z (normal along z)."""
    X, Y = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, float(z))], 1)
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None]).ravel()
    F = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)])
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F))


def merged(*meshes) -> o3d.geometry.TriangleMesh:
    out = o3d.geometry.TriangleMesh()
    for m in meshes:
        out += m
    return out


def pose(tx=0.0, ty=0.0, tz=0.0, rx=0.0, ry=0.0, rz=0.0) -> np.ndarray:
    return se3_exp(torch.tensor([tx, ty, tz, rx, ry, rz], dtype=torch.float64)).numpy()


# ------------------------------------------------------------ metric answers
def test_plane_shifted_by_2cm_and_6cm():
    gt = plane(0, 1, 0, 1, 2.0)
    m = mesh_metrics(plane(0, 1, 0, 1, 2.02), gt, n_samples=50_000)
    # nearest samples: 2 cm along the normal + ~1 mm in-plane sample spacing
    assert m["accuracy_cm"] == pytest.approx(2.0, abs=0.06)
    assert m["completion_cm"] == pytest.approx(2.0, abs=0.06)
    assert m["completion_ratio_pct"] == 100.0
    m6 = mesh_metrics(plane(0, 1, 0, 1, 1.94), gt, n_samples=50_000)
    assert m6["accuracy_cm"] == pytest.approx(6.0, abs=0.06) and m6["completion_ratio_pct"] == 0.0
    m0 = mesh_metrics(gt, gt, n_samples=50_000)
    assert m0["accuracy_cm"] < 0.4 and m0["completion_ratio_pct"] == 100.0


def test_half_covered_plane_completion():
    # estimate covers x in [0, 0.5] of the 1x1 m GT: GT points at x > 0.5 are x - 0.5 away
    m = mesh_metrics(plane(0, 0.5, 0, 1, 2.0), plane(0, 1, 0, 1, 2.0), n_samples=50_000)
    assert m["accuracy_cm"] < 0.4
    assert m["completion_cm"] == pytest.approx(100 * 0.5 * 0.25, abs=0.4)      # 12.5 cm
    assert m["completion_ratio_pct"] == pytest.approx(100 * (0.5 + 0.05), abs=1.5)
    # the threshold is honoured
    m10 = mesh_metrics(plane(0, 0.5, 0, 1, 2.0), plane(0, 1, 0, 1, 2.0), n_samples=50_000,
                       threshold_m=0.10)
    assert m10["completion_ratio_pct"] == pytest.approx(60.0, abs=1.5)


def test_alignment_from_the_trajectory_alignment():
    """The estimate lives in another Sim(3) frame; the ATE alignment of its trajectory brings
    its mesh back onto the ground truth."""
    gt = merged(plane(-1, 1, -1, 1, 2.0), plane(-1, 1, 0, 2, 0.0).rotate(
        pose(rx=np.pi / 2)[:3, :3], center=(0, 0, 0)))
    s, R, t = 0.5, pose(rz=0.7, rx=0.2)[:3, :3], np.array([0.3, -1.0, 2.0])
    est = transform_mesh(gt, s, R, t)                          # est frame = s R gt + t
    P_gt = np.stack([pose(0.2 * np.cos(a), 0.1 * np.sin(2 * a), 0.3 * a, ry=0.1 * a)
                     for a in np.linspace(0, 3, 12)])
    P_est = P_gt.copy()
    P_est[:, :3, :3] = R @ P_gt[:, :3, :3]
    P_est[:, :3, 3] = s * P_gt[:, :3, 3] @ R.T + t
    ts = np.arange(12) * 0.1
    a = ate(ts, P_gt, ts, P_est, align="sim3")
    assert a["rmse_cm"] < 1e-6 and a["scale"] == pytest.approx(2.0)
    m = evaluate_meshes(est, gt, align=(a["scale"], a["rotation"], a["translation"]),
                        n_samples=N_FAST)
    same = mesh_metrics(gt, gt, n_samples=N_FAST)             # sampling floor (~0.8 cm here)
    assert m["aligned"] and m["accuracy_cm"] < same["accuracy_cm"] + 0.1
    assert m["completion_cm"] < same["completion_cm"] + 0.1
    raw = evaluate_meshes(est, gt, n_samples=N_FAST)
    assert raw["accuracy_cm"] > 30


# ------------------------------------------------------------------- culling
def test_ray_depth_is_camera_z():
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(plane(-9, 9, -9, 9, 2.0)))
    T = pose(0.1, -0.2, 0.3, rx=0.15, ry=-0.1)
    d = _ray_depth(scene, torch.from_numpy(T), K).numpy()
    # analytic: pixel ray r = R K^-1 (u, v, 1) from c hits z = 2 at camera z (2 - c_z) / r_z
    v, u = np.mgrid[0:K.height, 0:K.width]
    r = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1) @ T[:3, :3].T
    np.testing.assert_allclose(d, (2.0 - T[2, 3]) / r[..., 2], rtol=1e-4)


def test_seen_vertices_frustum_and_occlusion():
    wall = plane(-3, 3, -3, 3, 2.0)
    V = torch.tensor([[0.0, 0.0, 1.0],      # in front of the wall, in view
                      [0.0, 0.0, 2.03],     # just behind it (within the 5 cm tolerance)
                      [0.0, 0.0, 3.0],      # hidden by the wall
                      [0.0, 0.0, -1.0],     # behind the camera
                      [5.0, 0.0, 2.0]],     # outside the image
                     dtype=torch.float64)
    P = pose()[None]
    assert seen_vertices(V, P, K).tolist() == [True, True, True, False, False]
    assert seen_vertices(V, P, K, occluder=wall).tolist() == [True, True, False, False, False]
    # a second camera looking at x = 5 sees the last vertex
    P2 = np.stack([pose(), pose(5.0, 0.0, 0.0)])
    assert seen_vertices(V, P2, K, occluder=wall).tolist() == [True, True, False, False, True]


def test_culling_removes_unseen_parts():
    gt = plane(-3, 3, -3, 3, 2.0, n=41)
    hidden = plane(-0.5, 0.5, -0.5, 0.5, 3.0)                  # behind the wall
    behind = plane(-0.5, 0.5, -0.5, 0.5, -1.0)                 # behind the camera
    est = merged(plane(-3, 3, -3, 3, 2.0, n=41), hidden, behind)
    P = pose()[None]
    raw = evaluate_meshes(est, gt, n_samples=N_FAST)
    frustum = evaluate_meshes(est, gt, poses=P, K=K, occlusion=False, n_samples=N_FAST)
    full = evaluate_meshes(est, gt, poses=P, K=K, n_samples=N_FAST)
    assert raw["accuracy_cm"] > frustum["accuracy_cm"] > full["accuracy_cm"]
    floor = evaluate_meshes(gt, gt, poses=P, K=K, n_samples=N_FAST)   # sampling noise only
    assert full["accuracy_cm"] < floor["accuracy_cm"] + 0.1 < 1.5
    assert full["completion_cm"] < floor["completion_cm"] + 0.1
    # the 64x48 camera at f=40 sees |x|, |y| < ~1.6 m of the 6x6 m wall: the rest is culled
    assert 5 < full["gt_faces_kept_pct"] < 30
    c = cull_mesh(est, P, K, occluder=gt)
    Vk = np.asarray(c.vertices)[np.unique(np.asarray(c.triangles))]
    assert np.allclose(Vk[:, 2], 2.0)                           # only the wall survives


# -------------------------------------------------------------------- fusion
def test_fuse_views_tilted_plane_and_settings():
    Kf = Intrinsics(160.0, 160.0, 127.5, 95.5, 256, 192)     # 1.25 cm pixels at 2 m
    n = np.array([0.2, -0.1, -1.0])
    n /= np.linalg.norm(n)
    views = []
    for T in (pose(), pose(0.2, 0.05, 0.1, ry=0.1)):
        v, u = np.mgrid[0:Kf.height, 0:Kf.width]
        r = np.stack([(u - Kf.cx) / Kf.fx, (v - Kf.cy) / Kf.fy, np.ones_like(u, float)], -1)
        rw = r @ T[:3, :3].T                                    # plane n.x = -2 in the world
        z = (-2.0 - n @ T[:3, 3]) / (rw @ n)                    # camera z of the hit
        rgb = np.zeros((Kf.height, Kf.width, 3), np.uint8)
        rgb[..., 0], rgb[..., 2] = 200, 40
        views.append((rgb, z.astype(np.float32), T))
    assert auto_voxel([torch.from_numpy(v[1]) for v in views]) == pytest.approx(
        0.005 * np.median(np.concatenate([v[1].ravel() for v in views])), rel=1e-3)
    mesh = fuse_views(views, Kf, voxel_m=0.02, trunc_m=0.08)
    V = np.asarray(mesh.vertices)
    assert len(mesh.triangles) > 1000
    dev = np.abs(V @ n + 2.0)                                  # distance to the plane
    assert np.median(dev) < 0.002 and np.quantile(dev, 0.98) < 0.01, np.quantile(dev, [.5, .98, 1])
    np.testing.assert_allclose(np.asarray(mesh.vertex_colors).mean(0), [200 / 255, 0, 40 / 255],
                               atol=0.01)
    with pytest.raises(MeshError, match="positive focal"):
        fuse_views(views, Intrinsics(160, -160, 127.5, 95.5, 256, 192), 0.02, 0.08)
    with pytest.raises(MeshError, match="do not match"):
        fuse_views([(views[0][0][:10], views[0][1], views[0][2])], Kf, 0.02, 0.08)
    with pytest.raises(MeshError, match="no views"):
        fuse_views([], K, 0.02, 0.08)
    with pytest.raises(MeshError, match="no valid depth"):
        auto_voxel([torch.zeros(4, 4)])


def test_map_mesh_output_small_map_and_failures(tmp_path):
    """A one-keyframe map of a wall at 2 m meshes onto the wall; a map that renders nothing
    opaque reports an error instead of failing the run; bad settings still raise."""
    cfg = SlamConfig()
    cfg.mapping = MappingConfig.fast(iters_first=30, downsample_first=2)
    mp = Mapper(cfg, K)
    img = np.full((K.height, K.width, 3), 120, np.uint8)
    img[:, ::8] = 230
    mp.add_keyframe(0, img, pose(), np.full((K.height, K.width), 2.0, np.float32))
    info = map_mesh_output(mp, tmp_path / "m.ply")
    assert info["faces"] > 100 and info["views"] == 1 and info["file"] == "m.ply"
    assert info["voxel_m"] == pytest.approx(0.01, rel=0.05)             # 0.005 x 2 m
    V = np.asarray(load_mesh(tmp_path / "m.ply").vertices)
    assert np.median(np.abs(V[:, 2] - 2.0)) < 0.03
    cfg.mapping.mesh_voxel_m = -1.0
    with pytest.raises(MeshError, match="mesh_voxel_m"):
        map_mesh_output(mp, tmp_path / "bad.ply")
    cfg.mapping.mesh_voxel_m = 0.0
    with torch.no_grad():
        mp.map.opacity_logits.fill_(-30.0)                        # nothing opaque any more
    assert "no valid depth" in map_mesh_output(mp, tmp_path / "none.ply")["error"]
    assert not (tmp_path / "none.ply").exists()


def test_run_outputs_share_one_render_per_keyframe(tmp_path, monkeypatch):
    """write_map_outputs renders each keyframe once for the mesh and the metrics, with the
    same mesh and metrics as when each renders its own."""
    from splat_slam_ros.evaluation.rendering import evaluate_keyframes
    from splat_slam_ros.mapper_role import write_map_outputs
    cfg = SlamConfig()
    cfg.mapping = MappingConfig.fast(iters_first=30, iters_per_keyframe=5, downsample_first=2)
    mp = Mapper(cfg, K)
    img = np.full((K.height, K.width, 3), 120, np.uint8)
    img[:, ::8] = 230
    for k, tx in enumerate((0.0, 0.1)):
        mp.add_keyframe(k, img, pose(tx=tx), np.full((K.height, K.width), 2.0, np.float32),
                        force=True)
    own_mesh = map_mesh_output(mp, tmp_path / "own.ply")
    own = evaluate_keyframes(mp, tmp_path / "own_renders")
    calls = []
    raster = mp._raster
    monkeypatch.setattr(mp, "_raster", lambda *a, **k: calls.append(1) or raster(*a, **k))
    out = tmp_path / "run"
    out.mkdir()
    m = write_map_outputs(mp, cfg, out)
    assert len(calls) == len(mp.keyframes) == 2
    assert m["psnr"] == own["psnr"] and m["ssim"] == own["ssim"] and m["views"] == 2
    assert (m["mesh"]["vertices"], m["mesh"]["faces"]) == (own_mesh["vertices"],
                                                          own_mesh["faces"])
    assert (out / "map.ply").is_file() and (out / "map_mesh.ply").is_file()
    for name in ("kf_00000.png", "kf_00001_depth.png"):
        assert np.array_equal(cv2.imread(str(out / "renders" / name), cv2.IMREAD_UNCHANGED),
                              cv2.imread(str(tmp_path / "own_renders" / name),
                                         cv2.IMREAD_UNCHANGED))


# -------------------------------------------------------------------- errors
def test_mesh_file_errors_and_cli(tmp_path, capsys):
    with pytest.raises(MeshError, match="not found"):
        load_mesh(tmp_path / "nope.ply")
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.rand(50, 3)))
    o3d.io.write_point_cloud(str(tmp_path / "points.ply"), pc)
    with pytest.raises(MeshError, match="no triangle mesh"):
        load_mesh(tmp_path / "points.ply")
    (tmp_path / "junk.ply").write_text("this is not a ply file\n")
    with pytest.raises(MeshError, match="no triangle mesh"):
        load_mesh(tmp_path / "junk.ply")
    with pytest.raises(MeshError, match="empty"):
        mesh_metrics(o3d.geometry.TriangleMesh(), plane(0, 1, 0, 1, 0))
    gt = tmp_path / "gt.ply"
    save_mesh(gt, plane(0, 1, 0, 1, 2.0))
    cases = [
        (["--mesh", str(tmp_path / "nope.ply"), "--mesh-gt", str(gt)], "mesh file not found"),
        (["--mesh", str(tmp_path / "points.ply"), "--mesh-gt", str(gt)], "no triangle mesh"),
        (["--mesh", str(gt)], "go together"),
        (["--mesh", str(tmp_path), "--mesh-gt", str(gt)], "map_mesh.ply"),     # run dir
        ([], "give --gt and --est"),
        (["--mesh", str(gt), "--mesh-gt", str(gt), "--samples", "0"], "--samples"),
        (["--mesh", str(gt), "--mesh-gt", str(gt), "--gt", "a.txt", "--est", "b.txt"],
         "--intrinsics"),
    ]
    for argv, msg in cases:
        assert eval_main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("error: ") and msg in err and "Traceback" not in err, err
    # a good call: identical meshes, numbers on stdout and in the JSON
    assert eval_main(["--mesh", str(gt), "--mesh-gt", str(gt), "--samples", "5000",
                      "--json", str(tmp_path / "m.json")]) == 0
    out = capsys.readouterr().out
    assert "MESH_accuracy_cm" in out and "not aligned" in out
    j = json.loads((tmp_path / "m.json").read_text())["mesh"]
    assert j["accuracy_cm"] < 1.0 and j["completion_ratio_pct"] == 100.0


# ------------------------------------------------------ ICL-NUIM end to end
def _small_posefolder(src: Path, dst: Path, scale: float) -> None:
    """The ICL-NUIM frames resized by ``scale`` (area colour, nearest depth), same poses."""
    (dst / "color").mkdir(parents=True)
    (dst / "depth").mkdir()
    for p in sorted((src / "color").glob("*.png")):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        d = cv2.imread(str(src / "depth" / p.name), cv2.IMREAD_UNCHANGED)
        size = (int(round(img.shape[1] * scale)), int(round(img.shape[0] * scale)))
        cv2.imwrite(str(dst / "color" / p.name), cv2.resize(img, size, interpolation=cv2.INTER_AREA))
        cv2.imwrite(str(dst / "depth" / p.name), cv2.resize(d, size, interpolation=cv2.INTER_NEAREST))
    (dst / "pose.txt").write_text((src / "pose.txt").read_text())
    k = Intrinsics(481.2, -480.0, 319.5, 239.5, 640, 480).scaled(scale)
    (dst / "intrinsics.yaml").write_text(
        f"fx: {k.fx}\nfy: {k.fy}\ncx: {k.cx}\ncy: {k.cy}\nwidth: {k.width}\n"
        f"height: {k.height}\ndepth_scale: 5000\n")


def test_icl_map_mesh_against_gt_depth_mesh(shared_data, tmp_path, capsys):
    """Map ICL-NUIM on ground-truth poses + depth at 160x120 (fast mapping preset), write
    map_mesh.ply with the run's outputs, fuse a reference mesh from the full-resolution
    ground-truth depth and evaluate with splat-slam-eval (alignment + culling)."""
    src = shared_data / "icl_nuim_living_room_5"
    if not src.is_dir():
        pytest.skip(f"{src} not found")
    _small_posefolder(src, tmp_path / "icl_small", 0.25)
    cfg = SlamConfig()
    cfg.mapping = MappingConfig.fast(keyframe_every=1)
    out = tmp_path / "run"
    res = run(open_dataset(tmp_path / "icl_small"), cfg, out, mode="gt_mapping", progress=False)
    info = res.metrics["mesh"]
    assert (out / "map_mesh.ply").is_file() and info["faces"] > 10_000
    assert 0.005 < info["voxel_m"] < 0.02 and info["views"] == 5      # ~1 cm at 2 m
    assert json.loads((out / "metrics.json").read_text())["mesh"]["file"] == "map_mesh.ply"
    est = load_mesh(out / "map_mesh.ply")
    assert len(est.vertex_colors) == len(est.vertices)

    kfull = tmp_path / "icl.yaml"
    kfull.write_text("fx: 481.2\nfy: -480.0\ncx: 319.5\ncy: 239.5\nwidth: 640\nheight: 480\n"
                     "depth_scale: 5000\n")
    full = open_dataset(src, intrinsics=kfull)          # poses/intrinsics with positive fy
    save_mesh(tmp_path / "gt_mesh.ply", fuse_frames(full, full.intrinsics))
    kpos = tmp_path / "icl_pos.yaml"
    k = full.intrinsics
    kpos.write_text(f"fx: {k.fx}\nfy: {k.fy}\ncx: {k.cx}\ncy: {k.cy}\nwidth: 640\nheight: 480\n")
    rc = eval_main(["--gt", str(out / "trajectory_full.txt"), "--est",
                    str(out / "trajectory_keyframes.txt"), "--mesh-gt",
                    str(tmp_path / "gt_mesh.ply"), "--mesh", str(out),     # the run directory
                    "--intrinsics", str(kpos),
                    "--json", str(tmp_path / "eval.json")])
    printed = capsys.readouterr()
    assert rc == 0, printed.err
    m = json.loads((tmp_path / "eval.json").read_text())
    mesh = m["mesh"]
    print(mesh)
    assert m["ate"]["rmse_cm"] < 1e-3 and mesh["aligned"] and mesh["culled"]
    assert mesh["accuracy_cm"] < 5.0 and mesh["completion_cm"] < 5.0
    assert mesh["completion_ratio_pct"] > 60.0
    assert mesh["gt_faces_kept_pct"] > 80.0


def test_auto_voxel_on_more_depth_samples_than_float32_counts():
    """70 M valid depths (300 keyframes at 640x480 with ground-truth depth): the subsampling
    positions must stay inside the array (a float32 linspace rounded past its end)."""
    from splat_slam_ros.mapping.mesh import AUTO_VOXEL_PER_DEPTH
    n = 70_348_551
    d = torch.full((n,), 2.0)
    assert auto_voxel([d]) == pytest.approx(2.0 * AUTO_VOXEL_PER_DEPTH)
