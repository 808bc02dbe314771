"""Mapping benchmark: the Gaussian mapper alone on ground-truth poses + ground-truth depth.

Datasets:
- ``icl``: ../shared/data/icl_nuim_living_room_5 (5 real frames 640x480, wide baselines,
  fy = -480 converted by the dataset reader); every frame is mapped;
- ``synth``: a synthetic TUM-layout sequence rendered by ``splat_slam_synth`` along a
  real hand-held trajectory (TUM fr1/xyz ground truth); keyframes by the covisibility rules
  (or every k-th frame with --keyframe-every).

Prints keyframe PSNR / SSIM / depth L1, seconds per mapped keyframe and peak RSS, and writes
benchmarks/results/mapping.json. CPU timings are noisy when other processes share the
cores: the load average at start and end is recorded beside them.

    python benchmarks/bench_mapping.py                      # both, paper settings (--preset paper)
    python benchmarks/bench_mapping.py --preset ""          # both, the CPU defaults
    python benchmarks/bench_mapping.py --only icl --scale 0.5 --set mapping.iters_first=300
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import torch

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "benchmarks" / "results" / "mapping.json"

from splat_slam_ros.config import load_config  # noqa: E402
from splat_slam_ros.evaluation.map_sequence import map_sequence  # noqa: E402
from splat_slam_ros.evaluation.rendering import evaluate_map  # noqa: E402
from splat_slam_ros.heap import peak_rss_mb  # noqa: E402
from splat_slam_ros.io.datasets import open_dataset  # noqa: E402
from splat_slam_ros.types import Frame, Intrinsics  # noqa: E402

ICL_K = Intrinsics(481.2, -480.0, 319.5, 239.5, 640, 480)


def resized(frames, K: Intrinsics, scale: float):
    """Frames (and intrinsics) resized by ``scale`` (area for colour, nearest for depth)."""
    if scale == 1.0:
        return list(frames), K
    K2 = K.scaled(scale)
    out = []
    for f in frames:
        img = cv2.resize(f.image, (K2.width, K2.height), interpolation=cv2.INTER_AREA)
        d = cv2.resize(f.gt_depth, (K2.width, K2.height), interpolation=cv2.INTER_NEAREST)
        out.append(Frame(f.index, f.timestamp, img, K2, f.gt_pose, d))
    return out, K2


def run_one(name: str, ds, cfg, scale: float, keyframe_every: int, refine):
    frames, K = resized(list(ds), ds.intrinsics, scale)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    mapper, m = map_sequence(frames, cfg, K, use_gt_depth=True, progress=True,
                             keyframe_every=keyframe_every, refine_iters=refine)
    wall = time.perf_counter() - t0
    novel = None
    if len(frames) > m["keyframes"]:        # frames that were not mapped: novel views
        kfs = set(mapper.keyframes)
        others = [f for f in frames if f.index not in kfs]
        novel = evaluate_map(mapper, others)
    res = {
        "dataset": name, "frames": len(frames), "size": f"{K.width}x{K.height}",
        "keyframes": m["keyframes"], "psnr": round(m["psnr"], 3), "ssim": round(m["ssim"], 4),
        "depth_l1_cm": round(m["depth_l1_cm"], 3), "gaussians": m["gaussians"],
        "map_mb": m["map_mb"], "s_per_keyframe": m["s_per_keyframe"],
        "first_keyframe_s": m["first_keyframe_s"],
        "s_per_later_keyframe": m["s_per_later_keyframe"],
        "refine_iters": m["refine_iters"], "refine_s": m["refine_s"], "wall_s": round(wall, 1),
        "peak_rss_mb": round(peak_rss_mb(), 1), "torch_threads": torch.get_num_threads(),
        "loadavg_start": round(load0, 2), "loadavg_end": round(os.getloadavg()[0], 2),
        "map_stats": {k: v for k, v in mapper.stats().items() if k != "window"},
    }
    if novel is not None:
        res["novel_view_psnr"] = round(novel["psnr"], 3)
        res["novel_view_depth_l1_cm"] = round(novel.get("depth_l1_cm", float("nan")), 3)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", choices=("icl", "synth"), help="run one dataset")
    ap.add_argument("--preset", default="paper", help="config preset (config/NAME.yaml; default "
                    "paper: the paper's schedule, the numbers in docs/benchmarks.md; '' = defaults)")
    ap.add_argument("--scale", type=float, default=1.0, help="resize factor (speed)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override, e.g. mapping.iters_first=300")
    ap.add_argument("--synth-frames", type=int, default=60)
    ap.add_argument("--synth-size", default="320x240")
    ap.add_argument("--keyframe-every", type=int, default=None,
                    help="synthetic: map every k-th frame (default: covisibility rules)")
    ap.add_argument("--refine", type=int, default=None,
                    help="final refinement iterations (default mapping.final_refine_iters)")
    ap.add_argument("--tag", default="", help="label stored with the results")
    ap.add_argument("--threads", type=int, default=0,
                    help="torch threads (0 = torch default); 1 is much faster when other "
                         "processes oversubscribe the cores")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)

    overrides = {}
    for kv in args.set:
        k, _, v = kv.partition("=")
        overrides[k] = json.loads(v) if v[:1] in "0123456789-[{tf" else v
    cfg = load_config(None, overrides, preset=args.preset or None)
    results = []
    if args.only in (None, "icl"):
        path = DATA / "icl_nuim_living_room_5"
        if not path.is_dir():
            print(f"skip icl: {path} not found")
        else:
            ds = open_dataset(path, fmt="posefolder", intrinsics=ICL_K, depth_scale=5000.0)
            results.append(run_one("icl_nuim_living_room_5", ds, cfg, args.scale, 1, args.refine))
    if args.only in (None, "synth"):
        from splat_slam_synth import generate_sequence
        traj = DATA / "trajectories" / "freiburg1_xyz-groundtruth.txt"
        with tempfile.TemporaryDirectory() as tmp:
            out = generate_sequence(str(traj) if traj.is_file() else "builtin",
                                    args.synth_frames, args.synth_size, Path(tmp) / "seq",
                                    fps=10.0, progress=False)
            ds = open_dataset(out)
            every = 0 if args.keyframe_every is None else args.keyframe_every
            results.append(run_one(f"synth_fr1xyz_{args.synth_frames}f", ds, cfg, args.scale,
                                   every, args.refine))
    for r in results:
        r["tag"] = args.tag
        r["overrides"] = overrides
        print(f"{r['dataset']:28s} {r['size']:>8s} kf {r['keyframes']:3d}  "
              f"PSNR {r['psnr']:6.2f} dB  SSIM {r['ssim']:.3f}  "
              f"depth L1 {r['depth_l1_cm']:.2f} cm  {r['s_per_keyframe']:.1f} s/kf "
              f"(first {r['first_keyframe_s']:.0f} s)  refine {r['refine_s']:.0f} s  "
              f"G {r['gaussians']}  {r['map_mb']:.1f} MB  RSS {r['peak_rss_mb']:.0f} MB  "
              f"load {r['loadavg_start']:.1f}->{r['loadavg_end']:.1f}"
              + (f"  novel PSNR {r['novel_view_psnr']:.2f}" if "novel_view_psnr" in r else ""))
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    old = json.loads(RESULTS.read_text()) if RESULTS.is_file() else []
    RESULTS.write_text(json.dumps(old + results, indent=2))
    print(f"results appended to {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
