"""splat-slam-synth: synthetic RGB-D sequences (TUM layout) along real camera trajectories."""
from __future__ import annotations

import argparse
import sys
from typing import List, Optional

from splat_slam_ros.cli.common import run_main
from splat_slam_synth.options import REALISM_PRESETS, SCENES, SynthError


def _scene_lines() -> str:
    import textwrap
    return "\n".join(textwrap.fill(desc, 92, initial_indent=f"  {name:<13}",
                                    subsequent_indent=" " * 15) for name, desc in SCENES.items())


EPILOG = """\
scenes (--scene NAME; for one seed and trajectory all but deep share the room's size):
""" + _scene_lines() + """

output (TUM RGB-D layout):
  OUT/rgb/<t>.png, OUT/depth/<t>.png (uint16, 5000 per metre, 0 = beyond 13.1 m),
  OUT/rgb.txt, OUT/depth.txt, OUT/groundtruth.txt (camera-to-world, the exact pose each
  frame was rendered with), OUT/intrinsics.yaml (fx fy cx cy width height + depth_scale,
  fps and a record of the generation options).

examples:
  splat-slam-synth --trajectory ../shared/data/trajectories/freiburg1_xyz-groundtruth.txt \\
      --frames 300 --size 640x480 --out synth/fr1_xyz
  splat-slam-synth --trajectory ../shared/data/trajectories/fr2_desk_groundtruth.txt \\
      --frames 1500 --start 47 --realism realistic --out synth/fr2_desk_real
  splat-slam-synth --trajectory builtin --frames 90 --size 320x240 --noise 3 --out synth/tiny
  splat-slam-synth --frames 300 --scene repetitive --realism harsh --seed 3 --out synth/rep_harsh
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="splat-slam-synth", epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Render a synthetic RGB-D sequence (textured room with furniture-like boxes, "
                    "exact depth and ground-truth poses) along a recorded camera trajectory.")
    g = p.add_argument_group("sequence")
    g.add_argument("--trajectory", default="builtin", metavar="FILE",
                   help="camera-to-world trajectory: TUM (t tx ty tz qx qy qz qw), KITTI (3x4 "
                        "rows, 10 Hz) or EuRoC CSV, detected automatically; 'builtin' = a smooth "
                        "hand-held-like path (default)")
    g.add_argument("--format", dest="fmt", default="auto", choices=["auto", "tum", "kitti", "euroc"],
                   help="trajectory format (default: auto)")
    g.add_argument("--frames", type=int, default=300, metavar="N",
                   help="number of camera frames to render (default 300)")
    g.add_argument("--fps", type=float, default=30.0,
                   help="camera frame rate; frames are sampled by timestamp at this rate, not "
                        "per trajectory row (default 30, like TUM's camera)")
    g.add_argument("--start", type=float, default=0.0, metavar="SECONDS",
                   help="first frame at the trajectory's first timestamp + SECONDS (default 0)")
    g.add_argument("--size", default=None, metavar="WxH",
                   help="image size (default 640x480, or the size in --intrinsics)")
    g.add_argument("--out", required=True, metavar="DIR", help="output folder")
    g.add_argument("--overwrite", action="store_true",
                   help="allow a non-empty --out: its rgb/, depth/ and index files are replaced")
    c = p.add_argument_group("camera and scene")
    c.add_argument("--fov", type=float, default=None, metavar="DEG",
                   help="horizontal field of view (default: TUM-like fx=fy=525 at 640 px wide, "
                        "scaled to the width; principal point at the image centre)")
    c.add_argument("--intrinsics", default=None, metavar="FILE",
                   help="intrinsics YAML (ours or ROS camera_info); plumb_bob/equidistant "
                        "distortion is rendered")
    c.add_argument("--textures", default=None, metavar="DIR",
                   help="folder of .png/.jpg images used as wall/box textures (e.g. real photos); "
                        "default: procedural textures (wood, tiles, bricks, posters, fabric...)")
    c.add_argument("--scene", default=None, metavar="NAME",
                   help="scene variant: " + ", ".join(SCENES) + " (default room; each is "
                        "described under 'scenes' below)")
    c.add_argument("--seed", type=int, default=0, help="scene, texture and noise seed (default 0)")
    c.add_argument("--up", default=None, choices=["+x", "-x", "+y", "-y", "+z", "-z"],
                   help="world up axis for the room (default: +z for TUM/EuRoC/builtin, -y for "
                        "KITTI)")
    c.add_argument("--device", default="cpu",
                   help="torch device for rendering: cpu (default), cuda[:N] or auto")
    c.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads for rendering (default 1: fastest on a busy 2-core "
                        "machine; 0 = torch default)")
    r = p.add_argument_group(
        "camera realism (RGB only; depth and poses stay exact)",
        "Each effect is off by default; --realism realistic turns on a sensible mix "
        "(motion blur 5 x 15 ms, auto-exposure 0.08, vignetting 0.25, noise 2, JPEG 90), "
        "--realism harsh a much stronger one (motion blur 7 x 20 ms, auto-exposure 0.25, "
        "vignetting 0.5, noise 4, JPEG 75, rolling shutter 20 ms). "
        "Explicit options override the preset.")
    r.add_argument("--realism", default=None, choices=list(REALISM_PRESETS),
                   help="preset (default clean)")
    r.add_argument("--motion-blur", type=int, default=None, metavar="K",
                   help="average K sub-exposure renders spread over --exposure before each frame "
                        "stamp, poses interpolated along the trajectory (1 = off; costs K renders)")
    r.add_argument("--exposure", dest="exposure_ms", type=float, default=None, metavar="MS",
                   help="exposure time for --motion-blur in milliseconds (default 15, at most "
                        "the frame period)")
    r.add_argument("--auto-exposure", type=float, default=None, metavar="A",
                   help="slow smooth gain drift of relative amplitude A (0.1 = +-10%%) plus an "
                        "offset drift of +-A/4 of full scale, periods 3-14 s, like an "
                        "auto-exposure camera")
    r.add_argument("--vignetting", type=float, default=None, metavar="V",
                   help="radial brightness falloff 1 - V r^2 (r = 1 in the image corners)")
    r.add_argument("--noise", type=float, default=None, metavar="SIGMA",
                   help="sensor noise std at mid-grey in 8-bit units: read noise SIGMA/2 plus "
                        "shot noise growing with sqrt(intensity)")
    r.add_argument("--jpeg", type=int, default=None, metavar="Q",
                   help="JPEG-compress and decompress each frame at quality Q (1-100) before "
                        "saving it as PNG")
    r.add_argument("--rolling-shutter", dest="rolling_shutter_ms", type=float, default=None,
                   metavar="MS",
                   help="rolling-shutter readout time from the top to the bottom row in "
                        "milliseconds (0 = global shutter, the default; at most the frame "
                        "period): row r is read out MS*(1 - r/(H-1)) before the frame stamp, so "
                        "the bottom row is at the stamp and its ground-truth pose; rendered in "
                        "row bands <= 0.5 ms apart, each with its --motion-blur sub-exposures")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)

    def body() -> int:
        from splat_slam_synth import generate_sequence
        stats: dict = {}
        out = generate_sequence(
            args.trajectory, args.frames, args.size, args.out, fps=args.fps, start=args.start,
            fmt=args.fmt, seed=args.seed, textures=args.textures, fov=args.fov,
            intrinsics=args.intrinsics, up=args.up, realism=args.realism,
            motion_blur=args.motion_blur, exposure_ms=args.exposure_ms,
            auto_exposure=args.auto_exposure, vignetting=args.vignetting, noise=args.noise,
            jpeg=args.jpeg, rolling_shutter_ms=args.rolling_shutter_ms, scene=args.scene,
            device=args.device, overwrite=args.overwrite, threads=args.threads or None,
            progress=not args.quiet, stats=stats)
        w, h = stats["size"]
        print(f"wrote {stats['frames']} frames {w}x{h} to {out} "
              f"({stats['s_per_frame']:.3f} s/frame rendering, {stats['boxes']} boxes, "
              f"scene setup {stats['setup_s']:.1f} s)")
        return 0

    return run_main(body, extra_errors=(SynthError,))


if __name__ == "__main__":
    sys.exit(main())
