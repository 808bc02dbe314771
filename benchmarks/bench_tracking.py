#!/usr/bin/env python
"""Tracking benchmark: ATE and throughput of the tracker on synthetic renders of real motion.

Sequences are rendered with ``splat-slam-synth`` (TUM layout, exact ground truth)
along the TUM fr1/xyz (300 frames) and fr2/desk (600 frames) ground-truth
trajectories at 640x480, clean and with camera realism (motion blur,
auto-exposure, vignetting, noise, JPEG), plus a closed loop (a path that
returns to its start) tracked with and without loop closure + global BA.

Each case runs in its own process, so frames/s = input frames / wall time of
the whole run including Python start-up, imports and image decoding. CPU time
(user + sys of that process) is reported too: it is what the run costs when the
machine is not shared. The 1-minute load average before/after each case is
recorded (other work on the same cores slows the wall-clock numbers).

    .venv/bin/python benchmarks/bench_tracking.py [--cases fr1_clean,fr1_real,...]
        [--data-dir DIR] [--out benchmarks/results/tracking.json]

Writes ``benchmarks/results/tracking.json`` and prints a table.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data" / "trajectories"
REALISTIC = ["--realism", "realistic"]       # blur 5, AE 0.08, vignetting 0.25, noise 2, JPEG 90

CASES = {
    # name: (trajectory, frames, realism args, config overrides, targets)
    "fr1_clean": ("freiburg1_xyz-groundtruth.txt", 300, [], {}, 1.0),
    "fr1_real": ("freiburg1_xyz-groundtruth.txt", 300, REALISTIC, {}, 1.0),
    "fr2_clean": ("fr2_desk_groundtruth.txt", 600, [], {}, 2.0),
    "fr2_real": ("fr2_desk_groundtruth.txt", 600, REALISTIC, {}, 2.0),
    "loop_real": ("@loop", 400, REALISTIC, {}, None),
    "loop_real_nolc": ("@loop", 400, REALISTIC,
                       {"tracking.loop_closure": False, "tracking.global_ba": False}, None),
}
TARGET_FPS = 5.0


def closed_loop_trajectory(path: Path, duration: float = 13.5, period: float = 12.0,
                           radius: float = 0.8) -> None:
    """A hand-held-like closed path: once around an ellipse looking outwards at the
    walls (a full turn), then 1.5 s more so the start is revisited; TUM file."""
    import numpy as np
    from splat_slam_ros.io.trajectory_io import write_tum
    t = np.arange(0, duration, 0.01)
    ang = 2 * np.pi * t / period
    pos = np.stack([radius * np.cos(ang), 0.7 * radius * np.sin(ang),
                    1.3 + 0.05 * np.sin(3 * ang)], 1)
    look = np.stack([np.cos(ang + 0.3), np.sin(ang + 0.3), -0.25 + 0.05 * np.sin(2 * ang)], 1)
    z = look / np.linalg.norm(look, axis=1, keepdims=True)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    P = np.tile(np.eye(4), (len(t), 1, 1))
    P[:, :3, 0], P[:, :3, 1], P[:, :3, 2], P[:, :3, 3] = x, y, z, pos
    write_tum(path, t, P)


def sequence_dir(data_dir: Path, traj: str, frames: int, realism) -> Path:
    tag = "real" if realism else "clean"
    stem = "loop" if traj == "@loop" else traj.split("-")[0].split("_groundtruth")[0]
    return data_dir / f"{stem}_{frames}_{tag}"


def ensure_sequence(data_dir: Path, traj: str, frames: int, realism) -> Path:
    out = sequence_dir(data_dir, traj, frames, realism)
    if (out / "groundtruth.txt").is_file() and (out / "intrinsics.yaml").is_file() and \
            len(list((out / "rgb").glob("*.png"))) == frames:
        return out
    if traj == "@loop":
        tfile = data_dir / "closed_loop_trajectory.txt"
        closed_loop_trajectory(tfile)
    else:
        tfile = SHARED / traj
        if not tfile.is_file():
            sys.exit(f"error: trajectory {tfile} not found (needs ../shared/data)")
    synth = Path(sys.executable).with_name("splat-slam-synth")
    cmd = [str(synth) if synth.exists() else "splat-slam-synth", "--trajectory", str(tfile),
           "--frames", str(frames), "--size", "640x480", "--out", str(out), "--overwrite",
           *realism]
    print("rendering:", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    return out


# ------------------------------------------------------------------ child run
def run_child(args) -> None:
    """One tracking run (in its own process): writes metrics JSON to --json."""
    t0 = time.perf_counter()
    import numpy as np
    from splat_slam_ros.config import load_config
    from splat_slam_ros.io.datasets import open_dataset
    from splat_slam_ros.evaluation import ate
    from splat_slam_ros.coordinator import track_sequence
    overrides = {}
    for kv in args.set or []:
        k, v = kv.split("=", 1)
        overrides[k] = json.loads(v)
    cfg = load_config(args.config, overrides)
    ds = open_dataset(args.child)
    res = track_sequence(iter(ds), cfg, ds.intrinsics, progress=False, total=len(ds))
    gt_ts, gt = ds.gt_trajectory()
    full = ate(gt_ts, gt, res.timestamps, res.poses)
    kf = ate(gt_ts, gt, res.kf_timestamps, res.kf_poses)
    out = dict(frames=res.n_frames, keyframes=res.n_keyframes, lost=res.n_lost,
               ate_full_cm=full["rmse_cm"], ate_kf_cm=kf["rmse_cm"], scale=full["scale"],
               tracking_wall_s=res.wall_s, in_process_s=time.perf_counter() - t0,
               timings={k: round(float(v), 3) for k, v in res.timings.items()},
               loop_events=sum(e.reason == "loop_closure" for e in res.events))
    Path(args.json).write_text(json.dumps(out, indent=1))


def run_case(name, seq: Path, overrides: dict, config: Path, tmp: Path) -> dict:
    js = tmp / f"{name}.json"
    cmd = [sys.executable, __file__, "--child", str(seq), "--config", str(config),
           "--json", str(js)]
    for k, v in overrides.items():
        cmd += ["--set", f"{k}={json.dumps(v)}"]
    load0 = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    r = json.loads(js.read_text())
    r.update(wall_s=wall, cpu_s=cpu, fps=r["frames"] / wall, fps_cpu=r["frames"] / cpu,
             load_before=load0, load_after=os.getloadavg()[0], sequence=str(seq),
             overrides=overrides)
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--data-dir", default=str(REPO / "benchmarks" / "results" / "data"))
    ap.add_argument("--config", default=str(REPO / "config" / "synthetic.yaml"))
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "tracking.json"))
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--json", help=argparse.SUPPRESS)
    ap.add_argument("--set", action="append", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        run_child(args)
        return
    names = [c for c in args.cases.split(",") if c]
    for c in names:
        if c not in CASES:
            sys.exit(f"error: unknown case {c!r} (use {', '.join(CASES)})")
    data_dir = Path(args.data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    results = {}
    for c in names:
        traj, frames, realism, overrides, target = CASES[c]
        seq = ensure_sequence(data_dir, traj, frames, realism)
        print(f"== {c}: {seq}", flush=True)
        r = run_case(c, seq, overrides, Path(args.config), data_dir)
        r["target_ate_cm"] = target
        results[c] = r
        print(f"   ATE full {r['ate_full_cm']:.3f} cm (keyframes {r['ate_kf_cm']:.3f}), "
              f"{r['keyframes']} kf, {r['lost']} lost, {r['fps']:.2f} frames/s wall "
              f"({r['fps_cpu']:.2f} per CPU-second), load {r['load_before']:.1f}", flush=True)
    meta = dict(machine=platform.processor() or platform.machine(), cpus=os.cpu_count(),
                python=platform.python_version(), date=time.strftime("%Y-%m-%d %H:%M"),
                note="fps = input frames / wall time of the whole process (start-up, "
                     "imports and PNG decoding included); fps_cpu = frames / CPU seconds "
                     "of that process; load = 1-min load average of the shared machine")
    meta["torch"] = torch.__version__
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    old = json.loads(Path(args.out).read_text()) if Path(args.out).is_file() else {}
    old.setdefault("cases", {}).update(results)
    old["meta"] = meta
    Path(args.out).write_text(json.dumps(old, indent=1))
    print("\n| case | frames | kf | ATE full (cm) | ATE kf (cm) | target | fps wall | "
          "fps/CPU-s | load |")
    print("|---|---|---|---|---|---|---|---|---|")
    for c, r in old["cases"].items():
        t = r.get("target_ate_cm")
        print(f"| {c} | {r['frames']} | {r['keyframes']} | {r['ate_full_cm']:.3f} | "
              f"{r['ate_kf_cm']:.3f} | {'-' if t is None else f'<= {t}'} | {r['fps']:.2f} | "
              f"{r['fps_cpu']:.2f} | {r['load_before']:.1f} |")
    if "loop_real" in old["cases"] and "loop_real_nolc" in old["cases"]:
        a, b = old["cases"]["loop_real"], old["cases"]["loop_real_nolc"]
        print(f"\nloop: ATE with loop closure + global BA {a['ate_full_cm']:.3f} cm, "
              f"without {b['ate_full_cm']:.3f} cm")
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
