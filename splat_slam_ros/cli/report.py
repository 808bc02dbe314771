"""splat-slam-report: rebuild report.html + report.png from an earlier run's directory."""
from __future__ import annotations

import argparse
import sys

EPILOG = """\
The report shows the estimated trajectory over the ground truth (when the input had it) and
the per-frame error, every keyframe's input beside the map's rendered colour and depth, its
proxy depth and colour error with PSNR/SSIM/depth L1, the map size over the run, time per
stage and frames/s, the configuration and the warnings of the run. It is built from the run
directory's files only, so rebuilding it gives the same bytes.

examples:
  splat-slam-report out/demo/run
  splat-slam-report runs/fr1 --out runs/fr1_report --max-keyframes 12
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="splat-slam-report", description=__doc__, epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir", metavar="RUN_DIR",
                   help="output directory of splat-slam-run, splat-slam-launch or the demo")
    p.add_argument("--out", help="write report.html and report.png here (default: RUN_DIR)")
    p.add_argument("--max-keyframes", type=int, default=40,
                   help="keyframes shown in the grid, evenly spread (default 40)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from splat_slam_ros.cli.common import run_main
    from splat_slam_ros.report.build import write_report
    from splat_slam_ros.report.run_record import ReportError

    def body() -> int:
        try:
            page, png = write_report(args.run_dir, out_dir=args.out,
                                     max_keyframes=args.max_keyframes)
        except ReportError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"wrote {page}")
        print(f"wrote {png}")
        return 0

    return run_main(body)


if __name__ == "__main__":
    sys.exit(main())
