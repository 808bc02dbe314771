"""Triangle meshes from the Gaussian map: TSDF fusion of rendered depth + colour.

The paper extracts meshes with marching cubes after fusing the map's rendered depth at the
keyframe poses into a TSDF (the reference uses Open3D's ScalableTSDFVolume, voxel 5/512 m,
truncation 0.04 m; see shared/notes/reference-defaults.md); here Open3D's hashed
VoxelBlockGrid does the same fusion, and the voxel size follows the scene scale unless
``mapping.mesh_voxel_m`` fixes it, so monocular runs of any scale work.

    from splat_slam_ros.mapping.mesh import write_map_mesh
    info = write_map_mesh(mapper, "out/map_mesh.ply")      # vertices, faces, voxel_m, ...

``map_mesh_output`` is what a run / the save service calls: a map that yields no surface is
reported in the returned dict instead of failing the run.

``fuse_views`` is the generic fusion (any RGB-D views with camera-to-world poses): the tests
and ``fuse_frames`` use it to build a reference mesh from ground-truth depth.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Iterable, Optional, Sequence, Tuple

import numpy as np
import open3d as o3d
import open3d.core as o3c
import torch
from tqdm import tqdm

from splat_slam_ros.config import MappingConfig
from splat_slam_ros.geometry import se3_inverse
from splat_slam_ros.types import Intrinsics

log = logging.getLogger(__name__)

AUTO_VOXEL_PER_DEPTH = 0.005     # voxel = 0.005 x median depth: ~1 cm at 2 m (reference 5/512 m)
MAX_AUTO_SAMPLES = 200_000       # depth samples used for the median
BLOCK_RESOLUTION = 8             # voxels per hashed block edge
INITIAL_BLOCKS = 20_000          # hash map capacity at start (grows on demand)
MIN_WEIGHT = 0.5                 # mesh voxels observed at least once (weights count views)


class MeshError(ValueError):
    """A mesh cannot be built, read or written (empty map, bad file, bad settings)."""


# ------------------------------------------------------------------ settings
def check_settings(m: MappingConfig) -> None:
    if m.mesh_voxel_m < 0 or not np.isfinite(m.mesh_voxel_m):
        raise MeshError(f"mapping.mesh_voxel_m must be >= 0 (0 = auto), got {m.mesh_voxel_m}")
    if not m.mesh_trunc_voxels >= 1.0:
        raise MeshError(f"mapping.mesh_trunc_voxels must be >= 1, got {m.mesh_trunc_voxels}")
    if m.mesh_max_depth_m < 0:
        raise MeshError(f"mapping.mesh_max_depth_m must be >= 0 (0 = no limit), "
                        f"got {m.mesh_max_depth_m}")
    if not 0.0 <= m.mesh_min_alpha < 1.0:
        raise MeshError(f"mapping.mesh_min_alpha must be in [0, 1), got {m.mesh_min_alpha}")


def auto_voxel(depths: Sequence[torch.Tensor]) -> float:
    """Voxel edge (m) from the median valid depth of the views (the scene scale)."""
    vals = [d[d > 0].flatten() for d in depths]
    vals = torch.cat([v.float().cpu() for v in vals]) if vals else torch.zeros(0)
    if len(vals) == 0:
        raise MeshError("no valid depth in any view: nothing to fuse into a mesh")
    if len(vals) > MAX_AUTO_SAMPLES:
        # integer positions: a float32 linspace rounds past the last index above 2^24 values
        idx = torch.arange(MAX_AUTO_SAMPLES, dtype=torch.int64) * (len(vals) - 1) \
            // (MAX_AUTO_SAMPLES - 1)
        vals = vals[idx]
    return float(vals.median()) * AUTO_VOXEL_PER_DEPTH


# ------------------------------------------------------------------- fusion
def _as_intrinsics(K) -> Tuple[float, float, float, float, int, int]:
    if isinstance(K, Intrinsics):
        K = (K.fx, K.fy, K.cx, K.cy, K.width, K.height)
    fx, fy, cx, cy, w, h = K
    if fx <= 0 or fy <= 0:
        raise MeshError(f"TSDF fusion needs positive focal lengths, got fx={fx} fy={fy} "
                        "(open the data with datasets.open_dataset, which converts them)")
    return float(fx), float(fy), float(cx), float(cy), int(w), int(h)


def fuse_views(views: Iterable[Tuple[np.ndarray, np.ndarray, np.ndarray]], K,
               voxel_m: float, trunc_m: float, max_depth_m: float = 0.0,
               progress: bool = False, total: Optional[int] = None) -> o3d.geometry.TriangleMesh:
    """TSDF-fuse RGB-D views and extract a coloured triangle mesh (marching cubes).

    ``views``: (rgb HxWx3 uint8, depth HxW float metres with 0 = invalid, camera-to-world 4x4
    pose in OpenCV axes). ``K``: Intrinsics or (fx, fy, cx, cy, width, height). Open3D's
    hashed voxel-block TSDF (VoxelBlockGrid, the successor of ScalableTSDFVolume, whose
    legacy class returns empty meshes in open3d 0.20); every voxel seen once is meshed."""
    fx, fy, cx, cy, w, h = _as_intrinsics(K)
    if not voxel_m > 0 or not trunc_m > 0:
        raise MeshError(f"voxel and truncation must be > 0, got {voxel_m} and {trunc_m}")
    dev = o3c.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32), attr_channels=(1, 1, 3),
        voxel_size=float(voxel_m), block_resolution=BLOCK_RESOLUTION,
        block_count=INITIAL_BLOCKS, device=dev)
    intr = o3c.Tensor(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), o3c.float64)
    far = float(max_depth_m) if max_depth_m > 0 else 1e6
    mult = float(trunc_m) / float(voxel_m)
    n = 0
    for rgb, depth, pose in tqdm(views, total=total, desc="mesh (TSDF)", unit="view",
                                 disable=not progress, dynamic_ncols=True):
        rgb = np.asarray(rgb, dtype=np.uint8)
        depth = np.nan_to_num(np.asarray(depth, dtype=np.float32), posinf=0.0, neginf=0.0)
        if rgb.shape[:2] != (h, w) or depth.shape != (h, w):
            raise MeshError(f"view {n}: image {rgb.shape[:2]} / depth {depth.shape} do not "
                            f"match the intrinsics size {h}x{w}")
        n += 1
        depth[depth < 0] = 0.0
        if not (depth > 0).any():
            continue
        d_img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth), device=dev))
        c_img = o3d.t.geometry.Image(o3c.Tensor(
            np.ascontiguousarray(rgb.astype(np.float32) / 255.0), device=dev))
        w2c = o3c.Tensor(se3_inverse(torch.as_tensor(np.asarray(pose, np.float64))).numpy())
        blocks = grid.compute_unique_block_coordinates(d_img, intr, w2c, 1.0, far, mult)
        grid.integrate(blocks, d_img, c_img, intr, intr, w2c, 1.0, far, mult)
    if n == 0:
        raise MeshError("no views to fuse into a mesh")
    mesh = grid.extract_triangle_mesh(weight_threshold=MIN_WEIGHT).to_legacy()
    if len(mesh.vertices):
        mesh.compute_vertex_normals()
        mesh.vertex_colors = o3d.utility.Vector3dVector(
            np.clip(np.asarray(mesh.vertex_colors), 0.0, 1.0))
    return mesh


def fuse_frames(frames: Iterable, K, voxel_m: float = 0.0, trunc_voxels: float = 4.0,
                progress: bool = False) -> o3d.geometry.TriangleMesh:
    """Mesh from frames' own ground-truth depth and poses (``Frame.gt_depth``, ``gt_pose``):
    a reference mesh for data sets that ship none. ``voxel_m = 0``: automatic."""
    frames = list(frames)
    for f in frames:
        if f.gt_depth is None or f.gt_pose is None:
            raise MeshError(f"frame {f.index} has no ground-truth depth/pose to fuse")
    if voxel_m <= 0:
        voxel_m = auto_voxel([torch.as_tensor(np.asarray(f.gt_depth)) for f in frames])
    return fuse_views(((f.image, f.gt_depth, f.gt_pose) for f in frames), K, voxel_m,
                      voxel_m * trunc_voxels, progress=progress, total=len(frames))


# ------------------------------------------------------------ from the map
@torch.no_grad()
def render_keyframe_views(mapper, min_alpha: float = 0.5, renders=None):
    """Per mapped keyframe: (rgb uint8, depth float32 with 0 where alpha < ``min_alpha``,
    pose). Depth is the alpha-blended depth divided by alpha (the surface depth).
    ``renders``: :meth:`Mapper.keyframe_renders`, rendered here when not given."""
    views = []
    renders = mapper.keyframe_renders() if renders is None else renders
    for k, kf in sorted(mapper.keyframes.items()):
        out = renders[k]
        a = out.alpha.float()
        d = torch.where(a > max(min_alpha, 1e-6), out.depth.float() / a.clamp_min(1e-6),
                        torch.zeros_like(a))
        rgb = (out.rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8)
        views.append((rgb.cpu().numpy(), d.cpu().numpy(), kf.pose))
    return views


def map_mesh(mapper, progress: bool = False,
             renders=None) -> Tuple[o3d.geometry.TriangleMesh, dict]:
    """Mesh of the Gaussian map: rendered depth + colour at every keyframe pose (``renders``:
    :meth:`Mapper.keyframe_renders` when already made), TSDF fusion with the ``mapping.mesh_*``
    settings. Returns (mesh, info)."""
    m = mapper.mcfg
    check_settings(m)
    if not mapper.keyframes or len(mapper.map) == 0:
        raise MeshError("the map is empty: no keyframes or Gaussians to mesh")
    t0 = time.perf_counter()
    views = render_keyframe_views(mapper, m.mesh_min_alpha, renders)
    voxel = float(m.mesh_voxel_m) or auto_voxel([torch.from_numpy(v[1]) for v in views])
    trunc = voxel * float(m.mesh_trunc_voxels)
    mesh = fuse_views(views, (*mapper.intr, mapper.W, mapper.H), voxel, trunc,
                      m.mesh_max_depth_m, progress=progress, total=len(views))
    info = {"vertices": len(mesh.vertices), "faces": len(mesh.triangles),
            "voxel_m": round(voxel, 5), "trunc_m": round(trunc, 5), "views": len(views),
            "mesh_s": round(time.perf_counter() - t0, 3)}
    return mesh, info


def save_mesh(path, mesh: o3d.geometry.TriangleMesh) -> None:
    """Binary PLY with vertex colours and normals."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_triangle_mesh(str(p), mesh, write_ascii=False):
        raise MeshError(f"could not write the mesh to {p}")


def load_mesh(path) -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh (PLY, OBJ, ...); missing, unreadable or empty -> MeshError."""
    p = Path(path)
    if not p.is_file():
        raise MeshError(f"mesh file not found: {p}")
    mesh = o3d.io.read_triangle_mesh(str(p))
    if len(mesh.vertices) == 0 or len(mesh.triangles) == 0:
        raise MeshError(f"{p} holds no triangle mesh (0 vertices or 0 faces; a point cloud "
                        "or Gaussian map PLY is not a mesh)")
    return mesh


def write_map_mesh(mapper, path, progress: bool = False, renders=None) -> dict:
    """``map_mesh.ply`` of the map at ``path``; returns the info dict (with its file name)."""
    mesh, info = map_mesh(mapper, progress=progress, renders=renders)
    if info["faces"] == 0:
        raise MeshError("TSDF fusion produced no surface (check mapping.mesh_voxel_m)")
    save_mesh(path, mesh)
    info["file"] = Path(path).name
    return info


def map_mesh_output(mapper, path, progress: bool = False, renders=None) -> dict:
    """``write_map_mesh`` for the end of a run / the save service: a map that yields no mesh
    (e.g. nothing opaque rendered) is reported as ``{"error": ...}`` and logged, so the run's
    other outputs are still written. Invalid ``mapping.mesh_*`` settings still raise."""
    check_settings(mapper.mcfg)
    try:
        return write_map_mesh(mapper, path, progress=progress, renders=renders)
    except MeshError as e:
        log.warning("map_mesh.ply not written: %s", e)
        return {"error": str(e)}
