"""splat-slam-run: the whole method in one process (the reference for the ROS graph)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from splat_slam_ros.cli.common import (add_topic_arguments, bag_topics, parse_overrides,
                                       run_main)

EPILOG = """\
modes:
  (default)                 tracking + proxy depth + Gaussian mapping, all stages in-process
  --tracking-only           tracker (flow + dense BA + loop closure + global BA) only
  --gt-poses --gt-depth     the Gaussian mapper alone, on ground-truth poses and depth
  --load-map RUN --localize localize-only in the session RUN saved: relocalise, then track in
                            RUN's map frame; the map is copied unchanged, nothing is added
  --load-map RUN            extend RUN's map (a full run's): relocalise, then track, add
                            keyframes and grow the same Gaussian map where it lacks the view

outputs in --out: trajectory_full.txt, trajectory_keyframes.txt (TUM format), map.ply,
metrics.json (ATE when the input has ground truth, PSNR/SSIM/depth L1 on keyframes, LPIPS
with --set evaluation.lpips_backbone=FILE),
renders/ (rendered keyframes), config.yaml (the configuration used), groundtruth.txt,
report.html + report.png (the run report; splat-slam-report rebuilds them), session/ (the
keyframes and a manifest, for a later --load-map; not in --gt-poses mode).
--localize writes trajectory_full.txt (posed frames only, in the loaded map's frame),
metrics.json (relocalised_frame, frames_posed, frames_lost, ATE) and map.ply (a copy).
--load-map without --localize writes a full run's outputs: trajectory_full.txt from the first
relocalised frame on, trajectory_keyframes.txt with the loaded and the new keyframes, the
extended map.ply, metrics.json "extend" (keyframes and Gaussians before / after), session/.

exit status: 0 done, 2 a user error (bad input, config), 3 no result: the tracker never
initialised (no keyframe: too little camera motion for the thresholds; the message says which
to lower), or the map stayed empty (too few keyframes with parallax for the proxy depth),
or (--load-map) no frame relocalised in the loaded map.

examples:
  splat-slam-run data/fr1_xyz --out runs/fr1 --config config/tum.yaml
  splat-slam-run data/replica --out runs/paper --preset paper     # the paper's GPU schedule
  splat-slam-run bags/synth --out runs/synth --tracking-only
  splat-slam-run data/seq --out runs/a --max-frames 400       # a map of the first part
  splat-slam-run data/seq --out runs/b --start-frame 300 --load-map runs/a --localize
  splat-slam-run data/seq --out runs/c --start-frame 300 --load-map runs/a   # grow the map
  splat-slam-run data/icl --out runs/icl --gt-poses --gt-depth --format posefolder \\
      --intrinsics icl.yaml
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="splat-slam-run", description=__doc__, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", help="dataset folder (TUM, Replica, ScanNet, EuRoC, image folder, "
                                 "video) or a bag written by splat-slam-convert")
    p.add_argument("--out", required=True, help="output directory (created)")
    p.add_argument("--config", help="YAML config (see config/*.yaml); defaults otherwise")
    p.add_argument("--preset", metavar="NAME", help="start from the shipped config/NAME.yaml "
                   "(e.g. paper: the paper's GPU mapping schedule); --config and --set apply on top")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config value, e.g. --set tracking.keyframe_thresh=3")
    p.add_argument("--tracking-only", action="store_true", help="run the tracker only")
    p.add_argument("--gt-poses", action="store_true",
                   help="use ground-truth poses (mapping in isolation; needs --gt-depth)")
    p.add_argument("--gt-depth", action="store_true",
                   help="use ground-truth depth as proxy depth (mapping in isolation; "
                        "needs --gt-poses)")
    p.add_argument("--max-frames", type=int, help="stop after N input frames")
    p.add_argument("--start-frame", type=int, default=0, metavar="N",
                   help="skip the first N input frames (0 <= N < frames): one sequence split "
                        "into sessions")
    p.add_argument("--load-map", metavar="RUN", help="the output folder of an earlier run whose "
                   "saved session (RUN/session/) to load: extend its map, or with --localize "
                   "only localise in it")
    p.add_argument("--localize", action="store_true",
                   help="localize-only in the --load-map session: no keyframe is added, the "
                        "map is not changed (copied to --out)")
    p.add_argument("--format", default="auto", help="input format (see splat-slam-convert)")
    p.add_argument("--intrinsics", help="intrinsics YAML when the input has none")
    add_topic_arguments(p)
    p.add_argument("--skip-frames", metavar="FILE",
                   help="replay a live run's tracker: the frames whose timestamps FILE lists "
                        "(the frames_skipped.txt a live splat-slam-launch run writes) are "
                        "skipped as the busy live tracker skipped them (posed between their "
                        "tracked neighbours, or tracked later to bridge a large motion); the "
                        "others are tracked. In process, so a live run's tracking is reproduced "
                        "exactly, whatever this machine's speed")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _session_usage(args) -> str:
    """The usage mistake of --start-frame / --load-map / --localize, or ''."""
    if args.start_frame < 0:
        return f"--start-frame must be >= 0, got {args.start_frame}"
    if args.localize and not args.load_map:
        return "--localize needs --load-map RUN (the run whose saved map to localize in)"
    if args.load_map and args.tracking_only and not args.localize:
        return ("--tracking-only cannot extend a map (--load-map without --localize grows the "
                "map); use --localize to track in it")
    if args.load_map and Path(args.load_map).resolve() == Path(args.out).resolve():
        return "--out must be another folder than --load-map (the loaded map is not changed)"
    if args.load_map and (args.gt_poses or args.gt_depth):
        return "--load-map cannot be combined with --gt-poses/--gt-depth"
    if args.skip_frames and (args.localize or args.gt_poses or args.gt_depth):
        return "--skip-frames replays the tracker: not with --localize or --gt-poses/--gt-depth"
    return ""


def _print_localize(res, out: Path) -> None:
    m = res.metrics
    print(f"relocalised at frame {m['relocalised_frame']} against keyframe "
          f"{m['relocalised_keyframe']}")
    print(f"frames {res.frames}  posed {m['frames_posed']}  lost {m['frames_lost']}  "
          f"wall {res.wall_s:.1f} s")
    if isinstance(m.get("ate_rmse_cm_full"), (int, float)):
        print(f"ate_rmse_cm_full {m['ate_rmse_cm_full']:.4f}")
    print(f"outputs in {out}")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)

    def body() -> int:
        from splat_slam_ros.heap import (RUN_MMAP_THRESHOLD, RUN_TRIM_THRESHOLD,
                                         TRACKING_TRIM_THRESHOLD, bound_heap)
        # one run, then exit: the step's temporaries stay in the heap (heap.RUN_*); a
        # tracking-only run, with no mapping step, gives its free heap top back
        bound_heap(RUN_MMAP_THRESHOLD, trim_threshold=TRACKING_TRIM_THRESHOLD
                   if args.tracking_only else RUN_TRIM_THRESHOLD)
        from splat_slam_ros.config import load_config
        from splat_slam_ros.io.datasets import open_dataset
        from splat_slam_ros.pipeline import (SUMMARY_METRICS, NotInitializedError, keyframe_line,
                                             run)

        if args.gt_poses != args.gt_depth:
            print("error: --gt-poses and --gt-depth go together (mapping in isolation on ground "
                  "truth); without both, the tracker estimates poses and proxy depth",
                  file=sys.stderr)
            return 2
        if args.tracking_only and args.gt_poses:
            print("error: --tracking-only cannot be combined with --gt-poses/--gt-depth",
                  file=sys.stderr)
            return 2
        if args.max_frames is not None and args.max_frames <= 0:
            print("error: --max-frames must be positive", file=sys.stderr)
            return 2
        bad = _session_usage(args)
        if bad:
            print(f"error: {bad}", file=sys.stderr)
            return 2
        overrides = parse_overrides(args.set)
        cfg = load_config(args.config, overrides, preset=args.preset)
        skip_stamps = None
        if args.skip_frames:
            from splat_slam_ros.io.trajectory_io import read_stamps
            skip_stamps = read_stamps(args.skip_frames)     # checked before any frame
        session = None
        if args.load_map:
            from splat_slam_ros.io.session import load_session
            session = load_session(Path(args.load_map))     # validated before any frame
        ds = open_dataset(args.input, fmt=args.format, intrinsics=args.intrinsics,
                          **bag_topics(args.image_topic, args.camera_info_topic))
        if args.start_frame:
            from splat_slam_ros.io.datasets import FromFrame
            ds = FromFrame(ds, args.start_frame)
        mode = "tracking" if args.tracking_only else "gt_mapping" if args.gt_poses else "full"
        if session is not None and not args.localize:
            from splat_slam_ros.extend import extend_config
            mode = "extend"
            for note in extend_config(cfg, overrides):
                print(f"extending a loaded map: {note}", file=sys.stderr)
        if mode == "gt_mapping" and not (ds.has_gt_pose and ds.has_gt_depth):
            print(f"error: {args.input} has no ground-truth "
                  f"{'poses' if not ds.has_gt_pose else 'depth'}; --gt-poses --gt-depth need both",
                  file=sys.stderr)
            return 2
        out = Path(args.out)
        try:
            if session is not None and args.localize:
                from splat_slam_ros.localize import run_localize
                res = run_localize(ds, cfg, out, session, progress=not args.no_progress,
                                   max_frames=args.max_frames)
            else:
                res = run(ds, cfg, out, mode=mode, progress=not args.no_progress,
                          max_frames=args.max_frames, session=session,
                          skip_stamps=skip_stamps)
        except NotInitializedError as e:       # no result: never initialised / relocalised
            print(f"error: {e} (metrics.json in {out})", file=sys.stderr)
            return 3
        if args.localize:
            _print_localize(res, out)
            return 0
        m = res.metrics
        if mode == "extend":
            x = m["extend"]
            print(f"relocalised at frame {x['relocalised_frame']} against keyframe "
                  f"{x['relocalised_keyframe']}; keyframes {x['loaded']['keyframes']} loaded + "
                  f"{x['new_keyframes']} new, Gaussians {x['loaded']['gaussians']} -> "
                  f"{x['gaussians']}")
        print(f"frames {res.frames}  keyframes {res.keyframes}  wall {res.wall_s:.1f} s  "
              f"{m['fps']:.2f} frames/s")
        kf_line = keyframe_line(m)
        if kf_line:
            print(kf_line)
        for k in SUMMARY_METRICS:
            if isinstance(m.get(k), (int, float)):
                print(f"{k} {m[k]:.4f}")
        if res.timings:
            print("time per stage (s): " + ", ".join(f"{k} {v:.1f}" for k, v in res.timings.items()))
        print(f"outputs in {out}")
        print(f"report: {out / 'report.html'}")
        return 0

    return run_main(body)


if __name__ == "__main__":
    sys.exit(main())
