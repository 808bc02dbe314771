"""Mesh benchmark: ICL-NUIM living room (5 frames), mapper on ground-truth poses + depth,
``map_mesh.ply`` by TSDF fusion of the rendered depth, evaluated against a mesh fused from the
full-resolution ground-truth depth (accuracy / completion / completion ratio after culling to
the ground-truth cameras, as ``splat-slam-eval --mesh`` does).

    python benchmarks/bench_mesh.py                       # 320x240, MappingConfig.fast()
    python benchmarks/bench_mesh.py --scale 1.0 --preset paper

Writes benchmarks/results/mesh.json. CPU timings are noisy on a shared machine: the load
average is recorded beside them.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "icl_nuim_living_room_5"
RESULTS = REPO / "benchmarks" / "results" / "mesh.json"

sys.path.insert(0, str(REPO / "benchmarks"))
from bench_mapping import ICL_K, resized  # noqa: E402

from splat_slam_ros.config import MappingConfig, SlamConfig  # noqa: E402
from splat_slam_ros.evaluation.map_sequence import map_sequence  # noqa: E402
from splat_slam_ros.io.datasets import open_dataset  # noqa: E402
from splat_slam_ros.mapping.mesh import fuse_frames, map_mesh  # noqa: E402
from splat_slam_ros.evaluation.mesh import evaluate_meshes  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scale", type=float, default=0.5, help="image scale for mapping")
    ap.add_argument("--preset", choices=("fast", "paper"), default="fast")
    ap.add_argument("--samples", type=int, default=200_000)
    args = ap.parse_args()
    if not DATA.is_dir():
        print(f"error: {DATA} not found", file=sys.stderr)
        return 2
    k = REPO / "benchmarks" / "results" / "icl_intrinsics.yaml"
    k.parent.mkdir(parents=True, exist_ok=True)
    k.write_text(f"fx: {ICL_K.fx}\nfy: {ICL_K.fy}\ncx: {ICL_K.cx}\ncy: {ICL_K.cy}\n"
                 f"width: {ICL_K.width}\nheight: {ICL_K.height}\ndepth_scale: 5000\n")
    ds = open_dataset(DATA, intrinsics=k)
    full = list(ds)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    gt_mesh = fuse_frames(full, ds.intrinsics)
    t_gt = time.perf_counter() - t0
    frames, K = resized(full, ds.intrinsics, args.scale)
    cfg = SlamConfig()
    cfg.mapping = MappingConfig.fast() if args.preset == "fast" else MappingConfig()
    cfg.mapping.keyframe_every = 1
    t0 = time.perf_counter()
    mapper, m = map_sequence(frames, cfg, K, progress=True)
    t_map = time.perf_counter() - t0
    est, info = map_mesh(mapper, progress=True)
    t0 = time.perf_counter()
    poses = np.stack([f.gt_pose for f in full])
    ev = evaluate_meshes(est, gt_mesh, poses=poses, K=ds.intrinsics, n_samples=args.samples,
                         progress=True)
    t_eval = time.perf_counter() - t0
    res = {"data": "icl_nuim_living_room_5", "size": f"{K.width}x{K.height}",
           "preset": args.preset, "keyframes": m["keyframes"], "psnr": round(m["psnr"], 2),
           "depth_l1_cm": round(m["depth_l1_cm"], 3),
           **{k2: (round(v, 3) if isinstance(v, float) else v) for k2, v in ev.items()},
           "mesh": info, "gt_mesh_faces": len(gt_mesh.triangles), "gt_fusion_s": round(t_gt, 2),
           "mapping_s": round(t_map, 1), "eval_s": round(t_eval, 1),
           "loadavg_start": [round(x, 2) for x in load0],
           "loadavg_end": [round(x, 2) for x in os.getloadavg()]}
    print(json.dumps(res, indent=2))
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(res, indent=2) + "\n")
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
