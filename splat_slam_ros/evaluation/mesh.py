"""Mesh reconstruction metrics as the paper reports them (§4 "Evaluation Metrics").

Accuracy [cm]: mean distance from points sampled on the estimated mesh to the nearest
point sampled on the ground-truth mesh. Completion [cm]: mean distance from ground-truth
samples to the nearest estimated sample. Completion ratio [%]: share of ground-truth samples
within 5 cm of the estimate. This follows the NICE-SLAM / Point-SLAM evaluation the paper
uses: both meshes are sampled uniformly by area (200k points each by default), the estimate
is first brought into the ground-truth frame with the trajectory alignment (Sim(3) or SE(3)
from :func:`~splat_slam_ros.evaluation.trajectory.ate`), and mesh parts no camera saw are
culled: a face is kept when one of its vertices projects into some camera's image in front
of it and is not hidden behind the ground-truth surface (depth ray-cast on the ground-truth
mesh, tolerance ``occlusion_tol``).

    from splat_slam_ros.evaluation.mesh import evaluate_meshes
    m = evaluate_meshes("est.ply", "gt.ply", align=(s, R, t), poses=gt_c2w, K=intrinsics)
    m["accuracy_cm"], m["completion_cm"], m["completion_ratio_pct"]
"""
from __future__ import annotations

from typing import Dict, Optional, Sequence, Tuple, Union

import numpy as np
import open3d as o3d
import torch
from scipy.spatial import cKDTree
from tqdm import tqdm

from splat_slam_ros.io.datasets import DatasetError, load_intrinsics
from splat_slam_ros.mapping.mesh import MeshError, load_mesh
from splat_slam_ros.types import Intrinsics

DEFAULT_SAMPLES = 200_000
DEFAULT_THRESHOLD_M = 0.05
DEFAULT_OCCLUSION_TOL_M = 0.05

MeshLike = Union[str, "o3d.geometry.TriangleMesh"]


def _mesh(m: MeshLike, name: str) -> o3d.geometry.TriangleMesh:
    if isinstance(m, o3d.geometry.TriangleMesh):
        if len(m.vertices) == 0 or len(m.triangles) == 0:
            raise MeshError(f"the {name} mesh is empty (0 vertices or 0 faces)")
        return m
    return load_mesh(m)


def _arrays(mesh) -> Tuple[torch.Tensor, torch.Tensor]:
    V = torch.from_numpy(np.asarray(mesh.vertices, dtype=np.float64).copy())
    F = torch.from_numpy(np.asarray(mesh.triangles, dtype=np.int64).copy())
    return V, F


def _from_arrays(V: torch.Tensor, F: torch.Tensor) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V.cpu().numpy()),
                                     o3d.utility.Vector3iVector(F.cpu().numpy().astype(np.int32)))


# ------------------------------------------------------------------ sampling
def sample_surface(mesh, n: int, seed: int = 0) -> torch.Tensor:
    """``n`` points uniformly distributed over the mesh surface (area-weighted faces, uniform
    barycentric coordinates), float64 (n, 3)."""
    V, F = _arrays(mesh)
    tri = V[F]                                                       # (F, 3, 3)
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=1)
    if not float(area.sum()) > 0:
        raise MeshError("the mesh has zero surface area: nothing to sample")
    g = torch.Generator().manual_seed(int(seed))
    face = torch.multinomial(area / area.sum(), int(n), replacement=True, generator=g)
    r1 = torch.rand(int(n), generator=g, dtype=torch.float64).sqrt()
    r2 = torch.rand(int(n), generator=g, dtype=torch.float64)
    t = tri[face]
    return ((1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1]
            + (r1 * r2)[:, None] * t[:, 2])


def transform_mesh(mesh, s: float, R, t) -> o3d.geometry.TriangleMesh:
    """A copy of the mesh with vertices mapped by x -> s R x + t (the ATE alignment)."""
    V, F = _arrays(mesh)
    R = torch.as_tensor(np.asarray(R, dtype=np.float64))
    t = torch.as_tensor(np.asarray(t, dtype=np.float64))
    return _from_arrays(float(s) * V @ R.T + t, F)


# ------------------------------------------------------------------- culling
def _ray_depth(scene, pose: torch.Tensor, K: Intrinsics) -> torch.Tensor:
    """Camera-z depth (H, W) of the first hit of each pixel's ray; inf where none."""
    v, u = torch.meshgrid(torch.arange(K.height, dtype=torch.float64),
                          torch.arange(K.width, dtype=torch.float64), indexing="ij")
    d_cam = torch.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, torch.ones_like(u)], -1)
    d_world = d_cam @ pose[:3, :3].T                                 # z_cam = 1 per unit t
    rays = torch.cat([pose[:3, 3].expand_as(d_world), d_world], -1).float()
    hit = scene.cast_rays(o3d.core.Tensor(rays.numpy()))
    return torch.from_numpy(hit["t_hit"].numpy()).double()           # = camera z


def seen_vertices(V: torch.Tensor, poses, K: Intrinsics, occluder=None,
                  occlusion_tol: float = DEFAULT_OCCLUSION_TOL_M,
                  progress: bool = False) -> torch.Tensor:
    """(V,) bool: the vertex projects inside some camera's image, in front of it and (with an
    ``occluder`` mesh) no more than ``occlusion_tol`` behind the occluder's surface there."""
    P = torch.as_tensor(np.asarray(poses, dtype=np.float64))
    scene = None
    if occluder is not None:
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(occluder))
    seen = torch.zeros(len(V), dtype=torch.bool)
    for T in tqdm(P, desc="culling", unit="view", disable=not progress, dynamic_ncols=True):
        Xc = (V - T[:3, 3]) @ T[:3, :3]                              # world -> camera
        z = Xc[:, 2]
        front = z > 1e-6
        zs = z.clamp_min(1e-6)
        u = torch.round(K.fx * Xc[:, 0] / zs + K.cx)
        v = torch.round(K.fy * Xc[:, 1] / zs + K.cy)
        ok = front & (u >= 0) & (u <= K.width - 1) & (v >= 0) & (v <= K.height - 1)
        if scene is not None and bool(ok.any()):
            depth = _ray_depth(scene, T, K)
            idx = ok.nonzero().squeeze(1)
            d = depth[v[idx].long(), u[idx].long()]
            ok[idx] = ~(z[idx] > d + occlusion_tol)                  # inf depth: nothing hides it
        seen |= ok
    return seen


def cull_mesh(mesh, poses, K: Intrinsics, occluder=None,
              occlusion_tol: float = DEFAULT_OCCLUSION_TOL_M,
              progress: bool = False) -> o3d.geometry.TriangleMesh:
    """The mesh without the faces none of whose vertices any camera saw (``seen_vertices``)."""
    V, F = _arrays(mesh)
    keep = seen_vertices(V, poses, K, occluder, occlusion_tol, progress)[F].any(dim=1)
    return _from_arrays(V, F[keep])


# ------------------------------------------------------------------- metrics
def mesh_metrics(est, gt, n_samples: int = DEFAULT_SAMPLES,
                 threshold_m: float = DEFAULT_THRESHOLD_M, seed: int = 0) -> Dict[str, float]:
    """Accuracy / completion (cm) and completion ratio (%, distance < ``threshold_m``) between
    two meshes already in the same frame."""
    if int(n_samples) < 1:
        raise MeshError(f"the number of samples must be >= 1, got {n_samples}")
    est, gt = _mesh(est, "estimated"), _mesh(gt, "ground-truth")
    pe = sample_surface(est, n_samples, seed).numpy()
    pg = sample_surface(gt, n_samples, seed + 1).numpy()
    d_acc = torch.from_numpy(cKDTree(pg).query(pe, workers=-1)[0])   # estimate -> GT
    d_com = torch.from_numpy(cKDTree(pe).query(pg, workers=-1)[0])   # GT -> estimate
    return {"accuracy_cm": 100.0 * float(d_acc.mean()),
            "completion_cm": 100.0 * float(d_com.mean()),
            "completion_ratio_pct": 100.0 * float((d_com < threshold_m).double().mean()),
            "threshold_cm": 100.0 * float(threshold_m), "samples": int(n_samples)}


def evaluate_meshes(est: MeshLike, gt: MeshLike,
                    align: Optional[Tuple[float, Sequence, Sequence]] = None,
                    poses=None, K: Optional[Intrinsics] = None, occlusion: bool = True,
                    occlusion_tol: float = DEFAULT_OCCLUSION_TOL_M,
                    n_samples: int = DEFAULT_SAMPLES, threshold_m: float = DEFAULT_THRESHOLD_M,
                    seed: int = 0, progress: bool = False) -> Dict[str, object]:
    """Full evaluation: align the estimate (``align = (s, R, t)``, est -> GT frame), cull both
    meshes to what the cameras at ``poses`` (GT camera-to-world) with intrinsics ``K`` saw,
    then ``mesh_metrics``. Without poses nothing is culled."""
    est, gt = _mesh(est, "estimated"), _mesh(gt, "ground-truth")
    out: Dict[str, object] = {"aligned": align is not None, "culled": poses is not None}
    if align is not None:
        est = transform_mesh(est, *align)
        out["scale"] = float(align[0])
    if poses is not None:
        if K is None:
            raise MeshError("culling needs the camera intrinsics with the poses")
        n_est, n_gt = len(est.triangles), len(gt.triangles)
        occ = gt if occlusion else None
        est = cull_mesh(est, poses, K, occ, occlusion_tol, progress)
        gt = cull_mesh(gt, poses, K, occ, occlusion_tol, progress)
        out.update({"est_faces_kept_pct": 100.0 * len(est.triangles) / n_est,
                    "gt_faces_kept_pct": 100.0 * len(gt.triangles) / n_gt,
                    "cull_views": len(poses), "occlusion": bool(occlusion)})
        if len(est.triangles) == 0:
            raise MeshError("no face of the estimated mesh is seen by the cameras: wrong "
                            "alignment, poses or intrinsics?")
        if len(gt.triangles) == 0:
            raise MeshError("no face of the ground-truth mesh is seen by the cameras: wrong "
                            "poses or intrinsics?")
    out.update(mesh_metrics(est, gt, n_samples, threshold_m, seed))
    return out


def evaluate_mesh_files(est: str, gt: str, ate_result: Optional[dict] = None, gt_poses=None,
                        intrinsics: Optional[str] = None, cull: bool = True, cull_every: int = 1,
                        occlusion: bool = True, occlusion_tol: float = DEFAULT_OCCLUSION_TOL_M,
                        n_samples: int = DEFAULT_SAMPLES, threshold_m: float = DEFAULT_THRESHOLD_M,
                        progress: bool = True) -> Dict:
    """:func:`evaluate_meshes` of two mesh files as ``splat-slam-eval --mesh`` runs it: aligned
    with the trajectory's ATE alignment (``ate_result``, or not aligned), culled to every
    ``cull_every``-th ground-truth pose with the intrinsics file ``intrinsics``."""
    align = None
    if ate_result is not None:
        align = (ate_result["scale"], ate_result["rotation"], ate_result["translation"])
    poses, K = None, None
    if gt_poses is not None and cull:
        try:
            K, _ = load_intrinsics(intrinsics)
        except DatasetError as e:
            raise MeshError(str(e)) from None
        poses = gt_poses[::cull_every]
    return evaluate_meshes(est, gt, align=align, poses=poses, K=K,
                           occlusion=occlusion, occlusion_tol=occlusion_tol,
                           n_samples=n_samples, threshold_m=threshold_m,
                           progress=progress)
