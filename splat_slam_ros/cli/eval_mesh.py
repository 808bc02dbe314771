"""The mesh part of ``splat-slam-eval``: accuracy / completion / completion ratio.

    splat-slam-eval --mesh-gt GT.ply --mesh runs/x/map_mesh.ply \
        [--gt groundtruth.txt --est runs/x --intrinsics K.yaml]   # alignment + culling

With ``--gt/--est`` the estimated mesh is moved into the ground-truth frame by the same
Umeyama alignment as the ATE (``--align``), and both meshes are culled to what the
ground-truth cameras saw (``--intrinsics`` needed; ``--no-cull`` to skip).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional

from splat_slam_ros.evaluation.files import write_mesh_json
from splat_slam_ros.evaluation.mesh import (DEFAULT_OCCLUSION_TOL_M, DEFAULT_SAMPLES,
                                            DEFAULT_THRESHOLD_M, evaluate_mesh_files)
from splat_slam_ros.mapping.mesh import MeshError

MESH_KEYS = ("accuracy_cm", "completion_cm", "completion_ratio_pct")
RUN_DIR_MESH = "map_mesh.ply"


def add_mesh_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("mesh evaluation (paper: accuracy, completion, completion ratio)")
    g.add_argument("--mesh", metavar="EST.ply",
                   help=f"estimated mesh, or a run directory (uses DIR/{RUN_DIR_MESH})")
    g.add_argument("--mesh-gt", metavar="GT.ply", help="ground-truth mesh")
    g.add_argument("--intrinsics", metavar="K.yaml",
                   help="camera intrinsics of the --gt poses (culling unseen parts)")
    g.add_argument("--no-cull", action="store_true", help="do not cull unseen mesh parts")
    g.add_argument("--no-occlusion", action="store_true",
                   help="cull by camera frustum only (no depth test against the GT mesh)")
    g.add_argument("--occlusion-tol", type=float, default=DEFAULT_OCCLUSION_TOL_M,
                   help=f"metres behind the GT surface still counted as seen "
                        f"(default {DEFAULT_OCCLUSION_TOL_M})")
    g.add_argument("--cull-every", type=int, default=1,
                   help="use every k-th ground-truth pose for culling (default 1)")
    g.add_argument("--samples", type=int, default=DEFAULT_SAMPLES,
                   help=f"points sampled on each mesh (default {DEFAULT_SAMPLES})")
    g.add_argument("--mesh-threshold", type=float, default=DEFAULT_THRESHOLD_M,
                   help=f"completion-ratio distance in metres (default {DEFAULT_THRESHOLD_M})")


def check_mesh_args(args) -> bool:
    """Validate the mesh options; True when a mesh evaluation was asked for."""
    if (args.mesh is None) != (args.mesh_gt is None):
        raise MeshError("--mesh and --mesh-gt go together")
    if args.mesh is None:
        return False
    if Path(args.mesh).is_dir():
        args.mesh = str(Path(args.mesh) / RUN_DIR_MESH)
    if args.samples < 1:
        raise MeshError(f"--samples must be >= 1, got {args.samples}")
    if not args.mesh_threshold > 0:
        raise MeshError(f"--mesh-threshold must be > 0, got {args.mesh_threshold}")
    if args.cull_every < 1:
        raise MeshError(f"--cull-every must be >= 1, got {args.cull_every}")
    if not args.occlusion_tol >= 0:
        raise MeshError(f"--occlusion-tol must be >= 0, got {args.occlusion_tol}")
    if args.gt is not None and not args.no_cull and args.intrinsics is None:
        raise MeshError("culling the meshes to the ground-truth cameras needs --intrinsics "
                        "K.yaml (or pass --no-cull)")
    return True


def run_mesh_eval(args, ate_result: Optional[dict], gt_poses=None) -> dict:
    """Evaluate (:func:`~splat_slam_ros.evaluation.mesh.evaluate_mesh_files`), print the table and
    ``MESH_*`` lines, merge into ``--json``; returns numbers."""
    m = evaluate_mesh_files(args.mesh, args.mesh_gt, ate_result, gt_poses, args.intrinsics,
                            cull=not args.no_cull, cull_every=args.cull_every,
                            occlusion=not args.no_occlusion, occlusion_tol=args.occlusion_tol,
                            n_samples=args.samples, threshold_m=args.mesh_threshold,
                            progress=True)
    how = (f"aligned with the trajectory ({args.align}, scale {m['scale']:.4f})"
           if ate_result is not None else "not aligned (no --gt/--est)")
    cull = (f"culled to {m['cull_views']} GT views"
            + (" with occlusion" if m["occlusion"] else " (frustum only)")
            + f": kept {m['est_faces_kept_pct']:.1f}% est / {m['gt_faces_kept_pct']:.1f}% GT faces"
            if m["culled"] else "not culled")
    print("\n".join([
        "Mesh evaluation",
        f"  estimate       {args.mesh}",
        f"  ground truth   {args.mesh_gt}",
        f"  alignment      {how}",
        f"  culling        {cull}",
        f"  samples        {m['samples']} per mesh",
        "  ---------------------------------",
        f"  accuracy    [cm]  {m['accuracy_cm']:.4f}",
        f"  completion  [cm]  {m['completion_cm']:.4f}",
        f"  completion ratio  {m['completion_ratio_pct']:.2f} % (< {m['threshold_cm']:g} cm)",
    ]))
    for k in MESH_KEYS:
        print(f"MESH_{k} {m[k]:.4f}")
    if args.json:
        write_mesh_json(args.json, m, args.mesh, args.mesh_gt, merge=ate_result is not None)
        print(f"wrote {args.json}")
    return m
