"""The main job on the embedded default: synthetic sequence -> bag -> SLAM -> evaluation.

``./run.sh demo`` runs this. It generates a synthetic hand-held sequence through a textured
room with the project's own generator (no data set needed), converts it to a rosbag2/mcap
bag, runs Splat-SLAM on the bag with the default configuration (the ROS 2 node graph by
default, ``--mode inprocess`` for all stages in one process) and prints ATE, PSNR and
frames/s. Everything lands in ``--out``.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="./run.sh demo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    p.add_argument("--frames", type=int, default=240, help="synthetic frames (default 240)")
    p.add_argument("--size", default="320x240", help="image size WxH (default 320x240)")
    p.add_argument("--trajectory", default="builtin",
                   help="trajectory file (TUM/KITTI/EuRoC) or 'builtin' (default)")
    p.add_argument("--realism", default="realistic", choices=["clean", "realistic"],
                   help="camera realism preset of the generator (default realistic)")
    p.add_argument("--mode", default="graph", choices=["graph", "inprocess"],
                   help="run the ROS 2 node graph (default), or all stages in one process")
    p.add_argument("--config", default=None,
                   help="SLAM config YAML (default: the built-in defaults, as for splat-slam-run; "
                        "config/demo.yaml is a faster preset with a poorer map)")
    p.add_argument("--fresh", action="store_true", help="regenerate the sequence and the bag")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from splat_slam_ros.cli.common import run_main

    def body() -> int:
        from splat_slam_ros.config import load_config
        from splat_slam_ros.io.datasets import open_dataset
        from splat_slam_ros.io.bagio import write_bag
        from splat_slam_synth import generate_sequence

        cfg = load_config(args.config)       # first: a bad file stops before any work
        out = Path(args.out)
        seq, bag, run_dir = out / "sequence", out / "bag", out / "run"
        if args.fresh:
            for d in (seq, bag):
                shutil.rmtree(d, ignore_errors=True)
        t0 = time.perf_counter()
        w, h = (int(x) for x in args.size.lower().split("x"))
        if not (seq / "groundtruth.txt").is_file():
            print(f"[demo] 1/4 generating {args.frames} synthetic frames ({args.size}, "
                  f"{args.realism}) -> {seq}", flush=True)
            seq.parent.mkdir(parents=True, exist_ok=True)
            generate_sequence(args.trajectory, args.frames, (w, h), seq,
                              realism=args.realism, overwrite=True)
        else:
            print(f"[demo] 1/4 reusing the synthetic sequence in {seq} (--fresh regenerates)")
        if not (bag / "metadata.yaml").is_file():
            print(f"[demo] 2/4 converting to a rosbag2/mcap bag -> {bag}", flush=True)
            write_bag(open_dataset(seq), bag, progress=True)
        else:
            print(f"[demo] 2/4 reusing the bag in {bag}")

        t_run = time.perf_counter()
        if args.mode == "graph":
            import os

            from splat_slam_nodes.tools import launch as graph
            from splat_slam_ros.ros_env import random_domain_id
            # an isolated DDS domain, so another ROS graph on this machine or LAN cannot
            # cross-talk with the demo (set ROS_DOMAIN_ID yourself to choose one)
            os.environ.setdefault("ROS_DOMAIN_ID", str(random_domain_id()))
            print(f"[demo] 3/4 running the ROS 2 node graph on the bag -> {run_dir}", flush=True)
            rc = graph.main(["--bag", str(bag), "--out", str(run_dir), "--fresh"]
                            + (["--config", args.config] if args.config else []))
            if rc:
                return rc
        else:
            from splat_slam_ros.pipeline import run
            print(f"[demo] 3/4 running all stages in one process on the bag -> {run_dir}",
                  flush=True)
            run(open_dataset(bag), cfg, run_dir, mode="full", progress=True)
        wall = time.perf_counter() - t_run
        print("[demo] 4/4 evaluation", flush=True)
        m = json.loads((run_dir / "metrics.json").read_text())
        print(f"ATE_RMSE_cm {m.get('ate_rmse_cm_full', float('nan')):.4f}")
        if "psnr" in m:
            print(f"PSNR_dB {m['psnr']:.2f}")
        print(f"frames/s {m['frames'] / wall:.2f}  ({m['frames']} frames, {wall:.1f} s, "
              f"{m['keyframes']} keyframes)")
        print(f"[demo] done in {time.perf_counter() - t0:.1f} s; outputs in {run_dir}")
        print(f"[demo] report: {run_dir / 'report.html'} (summary figure: "
              f"{run_dir / 'report.png'})")
        return 0

    from splat_slam_synth import SynthError
    return run_main(body, extra_errors=(SynthError,))


if __name__ == "__main__":
    sys.exit(main())
