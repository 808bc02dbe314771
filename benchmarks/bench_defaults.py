#!/usr/bin/env python
"""The default configuration end to end, in-process and through the ROS 2 graph (lockstep).

    .venv/bin/python benchmarks/bench_defaults.py [--data-dir DIR] [--sequences fr2desk,fr1xyz]
        [--modes inprocess,graph] [--max-frames N] [--preset NAME] [--set KEY=VALUE ...]
        [--json benchmarks/results/defaults.json]

Sequences (640x480, 30 Hz, ``--realism realistic``, exact depth and poses) are rendered with
``splat-slam-synth`` into ``--data-dir`` when missing: ``fr2desk_300_real`` along the real TUM
fr2/desk trajectory from t0 + 47 s (20 ms exposure) and ``fr1xyz_300_real`` along fr1/xyz.
Each is converted once to a rosbag2/MCAP bag (``<name>_bag``); both modes read that bag:

  inprocess  ``splat-slam-run BAG --out OUT``                       (one process)
  graph      ``splat-slam-launch --bag BAG --out OUT --mode lockstep``  (launcher + nodes)

Reported per run, from the run's own metrics.json (the same fields for both modes) and the
process accounting of this script: frames/s = input frames / wall time of the whole command
(Python start-up and output writing included), ATE RMSE (cm, Sim(3), full trajectory and
keyframes), keyframe PSNR / SSIM, depth L1 (cm, map depth at the keyframes vs the dataset's
depth, Sim(3) scale), peak RSS summed over processes (in-process: the process; graph: the
sum of the nodes' peaks (their metrics) + the launcher's own), CPU seconds, per-stage time and the load average
before and after. Runs go one after another (never two at once); timings on a shared machine
are noisy, so read them with the load average.

``--clean-twin`` also renders each sequence without camera effects (``<name>_<frames>_clean``:
same trajectory, frames and scene; no blur, exposure drift, vignetting, noise or JPEG) and
reports ``psnr_clean_twin``: the PSNR of those clean frames against the realistic input at the
run's keyframes, in the keyframes' camera (crop, processing size), after the best per-channel gain and offset per
keyframe (the exposure model of Eq. 11): the true scene, without vignetting or blur, seen
through the exposure model. A reference for the map's keyframe PSNR, not a bound: a map fitted
to the frames also learns their vignetting (``mapping.vignetting``) and, where the motion
repeats, much of their blur (docs/benchmarks.md "Defaults end to end").
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from splat_slam_ros.heap import proc_memory_mb

REPO = Path(__file__).resolve().parents[1]
TRAJ = REPO.parent / "shared" / "data" / "trajectories"
SEQUENCES = {   # name: (trajectory file, extra splat-slam-synth options)
    "fr2desk": ("fr2_desk_groundtruth.txt", ["--start", "47", "--exposure", "20"]),
    "fr1xyz": ("freiburg1_xyz-groundtruth.txt", []),
}
TARGETS = {"fps": 1.24, "psnr": 30.0, "depth_l1_cm": 3.0, "ate_rmse_cm_full": 1.0,
           "peak_rss_gb": 3.0}
KEYS = ("frames", "keyframes", "ate_rmse_cm_full", "ate_rmse_cm_keyframes", "psnr", "ssim",
        "depth_l1_cm", "depth_l1_edges_cm", "depth_l1_surfaces_cm", "depth_edge_band_fraction",
        "timings_s", "wall_s", "error")


def tool(name: str) -> str:
    exe = Path(sys.executable).with_name(name)
    return str(exe) if exe.exists() else name


def ensure_sequence(data_dir: Path, name: str, frames: int, clean: bool = False) -> Path:
    out = data_dir / f"{name}_{frames}_{'clean' if clean else 'real'}"
    if (out / "groundtruth.txt").is_file() and len(list((out / "rgb").glob("*.png"))) == frames:
        return out
    traj, extra = SEQUENCES[name]
    if not (TRAJ / traj).is_file():
        sys.exit(f"error: trajectory {TRAJ / traj} not found (needs ../shared/data)")
    cmd = [tool("splat-slam-synth"), "--trajectory", str(TRAJ / traj), "--frames", str(frames),
           "--size", "640x480", "--fps", "30", "--out", str(out), "--overwrite",
           "--realism", "clean" if clean else "realistic", *extra]
    print("rendering:", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    return out


def ensure_bag(seq: Path, jpeg: int = 0) -> Path:
    """The sequence's bag (converted once): raw images, or JPEG CompressedImage at quality
    ``jpeg`` (``splat-slam-convert --jpeg``)."""
    bag = seq.with_name(seq.name + "_bag" + (f"_jpeg{jpeg}" if jpeg else ""))
    if not (bag / "metadata.yaml").is_file():
        from splat_slam_ros.io.bagio import write_bag
        from splat_slam_ros.io.datasets import open_dataset
        write_bag(open_dataset(seq), bag, progress=True, overwrite=True,
                  jpeg_quality=jpeg or None)
    return bag


def timed(cmd, log: Path, env) -> dict:
    """Run ``cmd``; wall time of the whole command, CPU seconds (it and its children, wait4)
    and the peak RSS of the command's own process (VmHWM, polled: wait4's ru_maxrss would be
    the largest of its children for the launcher)."""
    import threading
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    hwm = [0.0]
    with open(log, "w") as fh:
        p = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env)
        done = threading.Event()

        def poll():
            while not done.wait(0.5):
                hwm[0] = max(hwm[0], proc_memory_mb(p.pid).get("VmHWM", 0.0))
        th = threading.Thread(target=poll, daemon=True)
        th.start()
        _, status, ru = os.wait4(p.pid, 0)
        done.set()
        th.join()
    wall = time.perf_counter() - t0
    return {"rc": os.waitstatus_to_exitcode(status), "wall_command_s": round(wall, 2),
            "cpu_s": round(ru.ru_utime + ru.ru_stime, 1), "own_peak_rss_mb": round(hwm[0], 1),
            "load_before": [round(x, 2) for x in load0],
            "load_after": [round(x, 2) for x in os.getloadavg()]}


def run_one(mode: str, bag: Path, out: Path, a, env) -> dict:
    extra = (["--preset", a.preset] if a.preset else []) + \
        [x for kv in a.set for x in ("--set", kv)]
    if mode == "inprocess":
        cmd = [tool("splat-slam-run"), str(bag), "--out", str(out), "--no-progress", *extra]
        if a.max_frames:
            cmd += ["--max-frames", str(a.max_frames)]
    else:
        cmd = [tool("splat-slam-launch"), "--bag", str(bag), "--out", str(out), "--fresh", "--mode",
               "lockstep", *extra]
        if a.max_frames:
            cmd += ["--max-frames", str(a.max_frames)]
    out.mkdir(parents=True, exist_ok=True)
    r = timed(cmd, out.parent / f"{out.name}.log", env)
    mf = out / "metrics.json"
    m = json.loads(mf.read_text()) if mf.is_file() else {}
    r.update({k: m[k] for k in KEYS if k in m})
    if mode == "graph":
        r["peak_rss_mb"] = round(float(m.get("peak_rss_mb_sum") or 0) + r["own_peak_rss_mb"], 1)
        r["cpu_s_nodes"] = round(sum(v.get("cpu_s", 0) for v in (m.get("nodes") or {}).values()), 1)
    else:
        r["peak_rss_mb"] = round(r["own_peak_rss_mb"], 1)
    frames = int(m.get("frames") or 0)
    r["fps"] = round(frames / r["wall_command_s"], 3) if frames else 0.0
    r["targets_met"] = {
        "fps": r["fps"] >= TARGETS["fps"],
        "psnr": (r.get("psnr") or 0) >= TARGETS["psnr"],
        "depth_l1_cm": (r.get("depth_l1_cm") or 1e9) <= TARGETS["depth_l1_cm"],
        "ate_rmse_cm_full": (r.get("ate_rmse_cm_full") or 1e9) <= TARGETS["ate_rmse_cm_full"],
        "peak_rss_gb": r["peak_rss_mb"] / 1024 <= TARGETS["peak_rss_gb"]}
    return r


def clean_twin_psnr(run_out: Path, seq: Path, clean: Path) -> float:
    """Mean PSNR of the clean twin's frames against ``seq``'s at the keyframes of the run in
    ``run_out``, in the run's keyframe camera (crop, processing size), with a per-keyframe
    gain/offset per channel."""
    from splat_slam_ros.config import load_config
    from splat_slam_ros.evaluation.image import psnr
    from splat_slam_ros.io.datasets import open_dataset
    from splat_slam_ros.io.trajectory_io import read_trajectory
    from splat_slam_ros.tracking.flow_frontend import mapping_preprocessor
    ts, _ = read_trajectory(run_out / "trajectory_keyframes.txt")
    real, twin = open_dataset(seq), open_dataset(clean)
    pre = mapping_preprocessor(load_config(run_out / "config.yaml"), real.intrinsics)

    def at_keyframes(ds) -> dict:       # the keyframes' colour files only
        return {round(float(f.timestamp), 4): pre(f.image)
                for f in ds.frames_at_stamps(ts, depth=False)}
    a, b = at_keyframes(real), at_keyframes(twin)
    vals = [psnr(b[t].astype(np.float32) / 255.0, a[t].astype(np.float32) / 255.0,
                 exposure_compensation=True) for t in sorted(a) if t in b]
    if not vals:
        raise ValueError(f"no keyframe of {run_out} is a frame of both {seq} and {clean}")
    return float(np.mean(vals))


def fmt(v, nd=2):
    return f"{v:.{nd}f}" if isinstance(v, (int, float)) else "-"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-dir", default=str(REPO / "benchmarks" / "results" / "data"))
    ap.add_argument("--sequences", default="fr2desk,fr1xyz")
    ap.add_argument("--frames", type=int, default=300, help="frames rendered per sequence")
    ap.add_argument("--modes", default="inprocess,graph")
    ap.add_argument("--max-frames", type=int, default=0, help="run only the first N frames")
    ap.add_argument("--preset", default="", help="config preset (default: none = defaults)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--clean-twin", action="store_true",
                    help="also render each sequence without camera effects and report the "
                         "PSNR of the true scene through the exposure model (psnr_clean_twin)")
    ap.add_argument("--work", default=str(REPO / "benchmarks" / "results" / "defaults_work"))
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "defaults.json"))
    a = ap.parse_args(argv)
    names = [s.strip() for s in a.sequences.split(",") if s.strip()]
    modes = [s.strip() for s in a.modes.split(",") if s.strip()]
    bad = [n for n in names if n not in SEQUENCES] + \
        [m for m in modes if m not in ("inprocess", "graph")]
    if bad:
        print(f"error: unknown sequence/mode {bad}; sequences {list(SEQUENCES)}, modes "
              "inprocess, graph", file=sys.stderr)
        return 2
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if "ROS_DOMAIN_ID" not in env:            # a shared machine: never the default domain
        from splat_slam_ros.ros_env import random_domain_id
        env["ROS_DOMAIN_ID"] = str(random_domain_id())
    data_dir, work = Path(a.data_dir), Path(a.work)
    data_dir.mkdir(parents=True, exist_ok=True)
    res = {"preset": a.preset or "defaults", "set": a.set, "max_frames": a.max_frames,
           "cpu_count": os.cpu_count(), "targets": TARGETS, "runs": {}}
    for name in names:
        seq = ensure_sequence(data_dir, name, a.frames)
        twin = ensure_sequence(data_dir, name, a.frames, clean=True) if a.clean_twin else None
        bag = ensure_bag(seq)
        for mode in modes:
            r = run_one(mode, bag, work / f"{name}_{mode}", a, env)
            if twin is not None and r["rc"] == 0:
                r["psnr_clean_twin"] = round(clean_twin_psnr(work / f"{name}_{mode}", seq,
                                                             twin), 2)
            res["runs"][f"{name}/{mode}"] = r
            print(f"{name}/{mode}: " + json.dumps(r), flush=True)
            Path(a.json).parent.mkdir(parents=True, exist_ok=True)
            Path(a.json).write_text(json.dumps(res, indent=2))
    print("\n| sequence / mode | frames/s | ATE full (cm) | PSNR (dB) | depth L1 (cm) | "
          "at edges / on surfaces (cm) | peak RSS (GB) | keyframes | load before -> after | "
          "clean-twin PSNR (dB) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for k, r in res["runs"].items():
        print(f"| {k} | {fmt(r['fps'])} | {fmt(r.get('ate_rmse_cm_full'))} | "
              f"{fmt(r.get('psnr'), 1)} | {fmt(r.get('depth_l1_cm'))} | "
              f"{fmt(r.get('depth_l1_edges_cm'), 1)} / {fmt(r.get('depth_l1_surfaces_cm'))} | "
              f"{fmt(r['peak_rss_mb'] / 1024)} | {r.get('keyframes', '-')} | "
              f"{r['load_before'][0]:.1f} -> {r['load_after'][0]:.1f} | "
              f"{fmt(r.get('psnr_clean_twin'), 2)} |")
    print(f"written {a.json}")
    return 0 if all(r["rc"] == 0 for r in res["runs"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
