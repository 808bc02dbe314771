"""splat-slam-convert: any supported dataset -> rosbag2 (MCAP) with the project's topic layout.

    splat-slam-convert INPUT --info       (describe a dataset or bag, reports damaged MCAP files)
    splat-slam-convert BAG --recover --out NEW   (repair a bag whose recorder was killed)
    splat-slam-convert INPUT --out BAG_DIR [--format auto|tum|replica|scannet|euroc|folder|
        video|posefolder] [--intrinsics FILE] [--max-frames N] [--stride K] [--fps F]
        [--depth-scale S] [--image-topic T] [--camera-info-topic T] [--overwrite]
        [--compress] [--jpeg Q] [--quiet]
"""
from __future__ import annotations

import argparse
import sys

from splat_slam_ros.cli.common import add_topic_arguments, bag_topics
from splat_slam_ros.io.datasets import FORMATS, DatasetError, open_dataset


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="splat-slam-convert",
        description="Convert a dataset (TUM, Replica, ScanNet, EuRoC, ICL/slambook pose folder, "
                    "image folder, video) or another rosbag2 bag (a robot's recording: raw, "
                    "compressed, Bayer or YUV images) into a rosbag2 MCAP bag for the "
                    "splat_slam nodes.")
    ap.add_argument("input", help="dataset folder, video file, or bag")
    ap.add_argument("--out", help="output bag folder (must not exist)")
    ap.add_argument("--info", action="store_true",
                    help="only describe INPUT (dataset or bag): frames, intrinsics, topics")
    ap.add_argument("--format", default="auto",
                    choices=["auto"] + list(FORMATS),
                    help="input layout (default: detect)")
    ap.add_argument("--intrinsics", help="camera intrinsics YAML (fx fy cx cy width height "
                    "[distortion_model distortion depth_scale]) or ROS camera_info YAML; "
                    "overrides the dataset's own")
    ap.add_argument("--max-frames", type=int, help="convert at most N frames")
    ap.add_argument("--stride", type=int, default=1, help="keep every K-th frame (default 1)")
    ap.add_argument("--fps", type=float, help="frame rate for layouts without timestamps "
                    "(folder, replica, scannet, posefolder; default 30) or to override a "
                    "video's timestamps")
    add_topic_arguments(ap)
    ap.add_argument("--depth-scale", type=float,
                    help="raw depth units per metre (default per format: TUM/ICL 5000, "
                    "Replica 6553.5, ScanNet 1000)")
    ap.add_argument("--recover", action="store_true",
                    help="INPUT is a damaged bag (recorder killed: no index/footer): write every "
                         "complete message to a new indexed bag --out")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing bag folder")
    ap.add_argument("--compress", action="store_true",
                    help="zstd-compress the MCAP chunks (smaller, slower to write)")
    ap.add_argument("--jpeg", type=int, metavar="Q",
                    help="store the images as JPEG CompressedImage at quality Q (1-100) on "
                         "/camera/image_raw/compressed: about 15x smaller, lossy")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    return ap


def _human(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} GiB"


def describe(ds) -> None:
    """Print what a dataset or bag holds (``--info``)."""
    K = ds.intrinsics
    print(f"{ds.source}: {ds.format} '{ds.name}', {len(ds)} frames {K.width}x{K.height}")
    print(f"  intrinsics fx={K.fx:g} fy={K.fy:g} cx={K.cx:g} cy={K.cy:g} "
          f"{K.distortion_model} {list(K.distortion)}")
    print(f"  gt_pose={ds.has_gt_pose} gt_depth={ds.has_gt_depth}")
    if ds.format == "bag":
        print(f"  converted from: {ds.source_format}" if ds.source_format else
              "  recorded elsewhere (not by splat-slam-convert)")
        print(f"  camera: {ds.topics['image']}, calibration from "
              f"{ds.topics['camera_info'] or '--intrinsics'}")
        for h in ds.health():
            print(f"  {'DAMAGED ' if h.damaged else ''}{h.describe()}"
                  + ("; repair: splat-slam-convert --recover BAG --out NEW" if h.damaged else ""))
        for topic, (msgtype, n) in sorted(ds.topic_counts().items()):
            print(f"  {topic}: {msgtype}, {n} messages")
    tr = ds.gt_trajectory()
    if tr is not None and len(tr[0]) > 1:
        print(f"  ground truth: {len(tr[0])} poses over {tr[0][-1] - tr[0][0]:.3f} s")
    for note in ds.notes:
        print(f"  note: {note}")


def recover(src: str, out: str) -> int:
    """``--recover``: copy every complete message of a (damaged) bag into a new indexed bag."""
    from pathlib import Path

    from splat_slam_ros.io.mcap_recover import recover_bag
    p = Path(src)
    if not p.exists():
        print(f"error: bag not found: {p}", file=sys.stderr)
        return 2
    if not (p.is_dir() and (p / "metadata.yaml").is_file()) and p.suffix.lower() != ".mcap":
        print(f"error: {p}: a bag is a rosbag2 folder or a .mcap file", file=sys.stderr)
        return 2
    try:
        healths = recover_bag(p, out)
    except (OSError, ValueError, KeyError) as e:
        print(f"error: cannot recover {p}: {e}", file=sys.stderr)
        return 2
    for h in healths:
        print(f"  {h.describe()}")
    n = sum(h.messages for h in healths)
    print(f"wrote {out}: {n} messages recovered, indexed"
          + ("" if any(h.damaged for h in healths) else " (the input was intact)"))
    return 0


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if not args.info and not args.out:
        ap.error("--out is required (or use --info to only describe INPUT)")
    if args.recover:
        return recover(args.input, args.out)
    from splat_slam_ros.io.bagio import write_bag
    topics = bag_topics(args.image_topic, args.camera_info_topic)
    try:
        if args.info:
            with open_dataset(args.input, fmt=args.format, intrinsics=args.intrinsics,
                              fps=args.fps, depth_scale=args.depth_scale, **topics) as ds:
                describe(ds)
            return 0
        ds = open_dataset(args.input, fmt=args.format, intrinsics=args.intrinsics,
                          max_frames=args.max_frames, stride=args.stride, fps=args.fps,
                          depth_scale=args.depth_scale, **topics)
        K = ds.intrinsics
        print(f"{ds.format} dataset '{ds.name}': {len(ds)} frames {K.width}x{K.height}, "
              f"fx={K.fx:g} fy={K.fy:g} cx={K.cx:g} cy={K.cy:g}"
              + (f", distortion {K.distortion_model}" if K.has_distortion else "")
              + f", gt_pose={ds.has_gt_pose}, gt_depth={ds.has_gt_depth}")
        for note in ds.notes:
            print(f"  note: {note}")
        s = write_bag(ds, args.out, progress=not args.quiet, overwrite=args.overwrite,
                      compress=args.compress, jpeg_quality=args.jpeg)
    except DatasetError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted; partial bag removed", file=sys.stderr)
        return 130
    print(f"wrote {s['path']}: {s['frames']} frames, {s['duration_s']:.3f} s, "
          f"{_human(s['size_bytes'])}")
    for topic, n in s["topics"].items():
        print(f"  {topic}: {n} messages")
    return 0


if __name__ == "__main__":
    sys.exit(main())
