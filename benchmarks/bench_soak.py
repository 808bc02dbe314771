"""Soak: the ROS 2 node graph in realtime mode on a long sequence in one revisited room.

    .venv/bin/python benchmarks/bench_soak.py [--frames 10000] [--size 160x120]
        [--data-dir DIR] [--config FILE] [--rate 1.0] [--out DIR]

The sequence: ``DATA_DIR/fr1xyz_300_real`` (TUM fr1/xyz motion, 300 realistic frames; rendered
with ``splat-slam-synth`` when the folder is missing) is resized to ``--size`` and played there
and back (598 frames, the camera returns to where it started), written as a rosbag2 once
(``DATA_DIR/soak_pingpong_<W>x<H>``), and the launcher plays that bag ``--frames / 598`` times
in a row (``splat-slam-launch --loop-bag N``, each pass shifted in time): the camera keeps
revisiting the same room.

While the graph runs, the benchmark samples every ``--sample-every`` seconds: the RSS of every
node process (/proc/<pid>/status VmRSS, and its private part RssAnon and shared-memory part
RssShmem), the tracker's keyframes (its checkpoint manifest), and the mapper's Gaussians and
mapped keyframes (/splat/map/status). Levels are medians over the samples within 5 % of the
frames played around the start (5 %) and the middle (50 %), and over the last 10 % (the end):
one sample can land on a transient burst. At the end it checks:
- RSS plateau: every node's RSS level at the end within 10 % of its level at the middle;
- bounded map: the Gaussians' level at the end within 10 % of the middle, mapped keyframes
  within 10 % (or 3 keyframes) of the middle (the benchmark's config sets
  mapping.revisit_cull_deg: a keyframe that revisits a mapped view, or whose view the map
  already covers, is consumed but not mapped, new keyframes wait for a loop-corrected pose,
  and a mapped keyframe an update shows to be a revisit is merged; and
  mapping.densify_max_per_view: densification stops at 1.5 x a view's first Gaussians);
- nothing lost: no node restarted or died, every keyframe the tracker published reached the
  mapper, every frame the tracker took is in the full trajectory (realtime mode drops frames
  by design when the tracker is busy, and DDS may not deliver some: both are counted).
Printed and written to ``benchmarks/results/soak.json`` (+ the samples). One run on a shared
2-core machine takes about frames / 30 s plus finalisation; timings are noisy.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional

import cv2
import numpy as np

from splat_slam_ros.heap import proc_memory_mb

REPO = Path(__file__).resolve().parents[1]
TRAJ = REPO.parent / "shared" / "data" / "trajectories" / "freiburg1_xyz-groundtruth.txt"
SOURCE = "fr1xyz_300_real"

CPU_CONFIG = """\
tracking:
  ba_downsample: 4
  warmup: 6
  global_ba_every: 40
  final_ba_iters: [3, 4]
mapping:
  iters_first: 40
  iters_per_keyframe: 5
  final_refine_iters: 20
  window_views_per_iter: 2
  random_views_per_iter: 1
  prune_every: 50
  densify_every: 50
  prune_min_age: 25
  revisit_cull_deg: 10.0
  densify_max_per_view: 1.5
"""


class SoakError(Exception):
    """User-facing error: ``error: ...``, exit 2."""


# --------------------------------------------------------------------------- data
def source_sequence(data_dir: Path) -> Path:
    """The 300-frame realistic fr1/xyz sequence (rendered with splat-slam-synth if missing)."""
    d = data_dir / SOURCE
    if (d / "rgb.txt").is_file() and (d / "groundtruth.txt").is_file():
        return d
    if not TRAJ.is_file():
        raise SoakError(f"{d} is missing and so is {TRAJ} to render it from")
    print(f"rendering {d} with splat-slam-synth (about 1.3 s/frame) ...", flush=True)
    subprocess.run([sys.executable, "-m", "splat_slam_synth.cli", "--trajectory", str(TRAJ),
                    "--frames", "300", "--realism", "realistic", "--out", str(d), "--overwrite"],
                   check=True)
    return d


def pingpong_bag(data_dir: Path, size) -> Path:
    """The source sequence at ``size``, there and back (a closed path), as a rosbag2."""
    from splat_slam_ros.io.bagio import write_bag
    from splat_slam_ros.io.datasets import open_dataset
    from splat_slam_ros.io.trajectory_io import write_tum
    w, h = size
    bag = data_dir / f"soak_pingpong_{w}x{h}"
    if (bag / "metadata.yaml").is_file():
        return bag
    ds = open_dataset(source_sequence(data_dir))
    frames = list(ds)
    order = list(range(len(frames))) + list(range(len(frames) - 2, 0, -1))
    dt = float(np.median(np.diff([f.timestamp for f in frames])))
    seq = data_dir / f"soak_pingpong_{w}x{h}_seq"
    for sub in ("rgb", "depth"):
        (seq / sub).mkdir(parents=True, exist_ok=True)
    t0 = frames[0].timestamp
    stamps, poses, lines = [], [], []
    for n, i in enumerate(order):
        f = frames[i]
        t = t0 + n * dt
        name = f"{t:.6f}.png"
        cv2.imwrite(str(seq / "rgb" / name), cv2.cvtColor(
            cv2.resize(f.image, (w, h), interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2BGR))
        depth = cv2.resize(f.gt_depth, (w, h), interpolation=cv2.INTER_NEAREST)
        cv2.imwrite(str(seq / "depth" / name), np.clip(depth * 5000, 0, 65535).astype(np.uint16))
        stamps.append(t)
        poses.append(f.gt_pose)
        lines.append(f"{t:.6f} NAME/{name}\n")
    for kind in ("rgb", "depth"):
        (seq / f"{kind}.txt").write_text("# timestamp filename\n" +
                                         "".join(x.replace("NAME", kind) for x in lines))
    write_tum(seq / "groundtruth.txt", np.array(stamps), np.stack(poses))
    k = frames[0].intrinsics
    k.scaled(w / k.width).to_yaml(seq / "intrinsics.yaml", depth_scale=5000.0, fps=1.0 / dt)
    write_bag(open_dataset(seq), bag, progress=False)
    return bag


# --------------------------------------------------------------------------- sampling
def _rss_mb(pid: int, field: str = "VmRSS") -> Optional[float]:
    """A /proc/<pid>/status memory field in MB: VmRSS (all resident memory), RssAnon (the
    process's private heap and stacks), RssShmem (resident pages of shared memory: the DDS
    shared-memory segments it maps); None when the process is gone."""
    return proc_memory_mb(pid).get(field)


def _node_pids(launch_pid: int) -> Dict[str, int]:
    names = {"tracker_node": "tracker", "loop_closure_node": "loop_closure",
             "depth_node": "depth", "mapper_node": "mapper", "bag_player": "player"}
    out = {}
    try:
        kids = Path(f"/proc/{launch_pid}/task/{launch_pid}/children").read_text().split()
    except OSError:
        return out
    for k in kids:
        try:
            cmd = Path(f"/proc/{k}/cmdline").read_bytes()
        except OSError:
            continue
        for key, name in names.items():
            if key.encode() in cmd:
                out[name] = int(k)
    return out


class MapStatus:
    """The newest /splat/map/status (Gaussians, mapped keyframes), from a background spin."""

    def __init__(self, env: Dict[str, str]):
        os.environ.update({k: v for k, v in env.items() if k.startswith(("ROS_", "FASTRTPS",
                                                                         "RMW_", "SPLAT_"))})
        from splat_slam_ros.ros_env import apply_ros_environment
        apply_ros_environment()
        import rclpy
        from splat_slam_msgs.msg import MapperStatus

        from splat_slam_nodes import qos as Q
        from splat_slam_nodes.node_common import TOPICS
        rclpy.init(args=["bench_soak"])
        self.rclpy = rclpy
        self.node = rclpy.create_node("bench_soak_sampler")
        self.last = {"gaussians": 0, "keyframes_mapped": 0}
        self.node.create_subscription(MapperStatus, TOPICS["status"], self._on, Q.status_qos())
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _on(self, m) -> None:
        self.last = {"gaussians": int(m.gaussian_count), "keyframes_mapped": int(m.keyframes_mapped)}

    def _spin(self) -> None:
        while not self.stop.is_set() and self.rclpy.ok():
            self.rclpy.spin_once(self.node, timeout_sec=0.2)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def tracker_keyframes(out: Path) -> int:
    try:
        m = json.loads((out / "state" / "tracker" / "manifest.json").read_text())["meta"]
        return int(m.get("trk_next_kf", 0))
    except (OSError, ValueError, KeyError):
        return 0


# --------------------------------------------------------------------------- run
def run_soak(bag: Path, cfg_path: Path, out: Path, passes: int, rate: float,
             sample_every: float, timeout: float) -> dict:
    from tqdm import tqdm
    from splat_slam_ros import ros_env
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(ros_env.random_domain_id())
    env["PYTHONUNBUFFERED"] = "1"
    os.environ["ROS_DOMAIN_ID"] = env["ROS_DOMAIN_ID"]
    status = MapStatus(env)
    args = [sys.executable, "-m", "splat_slam_nodes.tools.launch", "--bag", str(bag), "--out",
            str(out), "--fresh", "--config", str(cfg_path), "--mode", "realtime", "--rate", str(rate),
            "--loop-bag", str(passes), "--final-timeout", str(timeout)]
    log = open(out.parent / f"{out.name}.log", "wb")
    t0 = time.monotonic()
    launch = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=str(REPO))
    samples: List[dict] = []
    pids: Dict[str, int] = {}
    try:
        with tqdm(desc="soak", unit="s", total=None, mininterval=30) as bar:
            while launch.poll() is None:
                if time.monotonic() - t0 > timeout:
                    raise SoakError(f"the run did not finish within {timeout:g} s")
                time.sleep(sample_every)
                pids.update(_node_pids(launch.pid))
                prog = {}
                try:
                    prog = json.loads((out / "state" / "player" / "progress.json").read_text())
                except (OSError, ValueError):
                    pass
                s = {"t": round(time.monotonic() - t0, 2), "frames": int(prog.get("frames", 0)),
                     "rss_mb": {n: _rss_mb(p) for n, p in pids.items()},
                     "anon_mb": {n: _rss_mb(p, "RssAnon") for n, p in pids.items()},
                     "shmem_mb": {n: _rss_mb(p, "RssShmem") for n, p in pids.items()},
                     "tracker_keyframes": tracker_keyframes(out), **status.last,
                     "load": os.getloadavg()[0]}
                samples.append(s)
                bar.update(sample_every)
                bar.set_postfix(frames=s["frames"], kf=s["tracker_keyframes"],
                                gauss=s["gaussians"], refresh=False)
    finally:
        if launch.poll() is None:
            launch.terminate()
            launch.wait(timeout=60)
        status.close()
    return {"rc": launch.returncode, "wall_s": round(time.monotonic() - t0, 1),
            "samples": samples}


WINDOW = 0.05       # levels are medians over +-5 % of the frames played (the end: the last 10 %)


def _playing(samples: List[dict]) -> List[dict]:
    """The samples taken while frames were played (up to the first one after the last frame:
    finalisation comes after)."""
    playing = [s for s in samples if s["frames"] > 0]
    last = max(s["frames"] for s in playing)
    n = next(i for i, s in enumerate(playing) if s["frames"] >= last)
    return playing[:n + 1]


def _level(samples: List[dict], frac: float, key) -> Optional[float]:
    """Median of ``key(sample)`` over the samples within WINDOW of ``frac`` of the frames
    played (``frac`` 1.0: the last 2 x WINDOW). A single sample can land on a transient burst
    (a global BA's recomputations move a node's RSS by ~150 MB for a few seconds), so the
    checks compare levels, not samples."""
    last = samples[-1]["frames"]
    lo, hi = (1.0 - 2 * WINDOW, 1.0) if frac >= 1.0 else (frac - WINDOW, frac + WINDOW)
    vals = [key(s) for s in samples if lo * last <= s["frames"] <= hi * last]
    vals = [v for v in vals if v is not None]
    return float(np.median(vals)) if vals else None


def summarise(res: dict, out: Path) -> dict:
    m = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else {}
    if not any(s["frames"] > 0 for s in res["samples"]):
        raise SoakError("no sample taken while frames were played")
    smp = _playing(res["samples"])
    fracs = (0.05, 0.5, 1.0)
    nodes = sorted({n for s in smp for n in s["rss_mb"]})

    def levels(key):
        return [_level(smp, f, key) for f in fracs]

    rss = {n: levels(lambda s, n=n: s["rss_mb"].get(n)) for n in nodes}
    anon = {n: levels(lambda s, n=n: (s.get("anon_mb") or {}).get(n)) for n in nodes}
    half = 0.5 * smp[-1]["frames"]
    peak = {n: [max((s["rss_mb"].get(n) or 0) for s in smp if s["frames"] <= half),
                max((s["rss_mb"].get(n) or 0) for s in smp if s["frames"] > half)]
            for n in nodes}
    growth = {n: (v[2] / v[1] - 1.0) if v[1] and v[2] else None for n, v in rss.items()}
    start, mid, end = ({k: round(_level(smp, f, lambda s, k=k: s[k]))
                        for k in ("gaussians", "keyframes_mapped", "tracker_keyframes")}
                       for f in fracs)
    checks = {"rss_plateau": all(g is not None and g <= 0.10 for g in growth.values()),
              "gaussians_bounded": bool(mid["gaussians"]) and
              end["gaussians"] <= 1.10 * mid["gaussians"],
              "mapped_keyframes_bounded": end["keyframes_mapped"] <= max(
                  1.10 * mid["keyframes_mapped"], mid["keyframes_mapped"] + 3)}
    restarts = {n: v.get("restarts", 0) for n, v in m.get("nodes", {}).items()}
    offered = {}
    mf = out / "state" / "mapper" / "manifest.json"
    if mf.is_file():
        offered = json.loads(mf.read_text())["meta"].get("offered", {})
    played = int(m.get("frames") or 0)
    taken = int(m.get("frames_tracked") or 0) - int(m.get("frames_dropped") or 0)
    posed = 0
    if (out / "trajectory_full.txt").is_file():
        from splat_slam_ros.io.trajectory_io import read_trajectory
        posed = len(read_trajectory(out / "trajectory_full.txt")[0])
    # no crash or restart, every keyframe reached the mapper, every frame the tracker took
    # is in the full trajectory (realtime mode drops frames by design: counted, not lost)
    checks["nothing_lost"] = (res["rc"] == 0 and not any(restarts.values()) and taken > 0 and
                              posed == taken and sorted(int(k) for k in offered) ==
                              list(range(m.get("keyframes", 0))))
    return {"frames": played, "frames_dropped_realtime": m.get("frames_dropped"),
            "frames_not_delivered": played - int(m.get("frames_tracked") or 0),
            "frames_posed": posed,
            "wall_s": res["wall_s"], "rc": res["rc"],
            "rss_mb_start_mid_end": {n: [None if x is None else round(x, 1) for x in v]
                                     for n, v in rss.items()},
            "rss_growth_last_half": {n: None if g is None else round(g, 4)
                                     for n, g in growth.items()},
            "anon_mb_start_mid_end": {n: [None if x is None else round(x, 1) for x in v]
                                      for n, v in anon.items()},
            "rss_peak_mb_first_last_half": {n: [round(x, 1) for x in v] for n, v in peak.items()},
            "tracker_keyframes": [start["tracker_keyframes"], mid["tracker_keyframes"],
                                  end["tracker_keyframes"], m.get("keyframes")],
            "mapped_keyframes": [start["keyframes_mapped"], mid["keyframes_mapped"],
                                 end["keyframes_mapped"]],
            "gaussians": [start["gaussians"], mid["gaussians"], end["gaussians"]],
            "restarts": restarts, "checks": checks, "ate_rmse_cm_full": m.get("ate_rmse_cm_full"),
            "load_mean": round(float(np.mean([s["load"] for s in smp])), 2)}


def table(r: dict) -> str:
    lines = [f"frames {r['frames']} (dropped by the realtime queue {r['frames_dropped_realtime']}, "
             f"not delivered {r['frames_not_delivered']}, posed {r['frames_posed']}), "
             f"wall {r['wall_s']:.0f} s, load {r['load_mean']}",
             "| node | RSS start MB | RSS middle MB | RSS end MB | growth, last half | "
             "private (RssAnon) start / middle / end MB | peak first / last half MB |",
             "|---|---|---|---|---|---|---|"]
    for n, v in r["rss_mb_start_mid_end"].items():
        g = r["rss_growth_last_half"][n]
        a = r["anon_mb_start_mid_end"].get(n) or [None] * 3
        p = r["rss_peak_mb_first_last_half"].get(n) or [None] * 2
        lines.append(f"| {n} | {v[0]} | {v[1]} | {v[2]} | "
                     f"{'-' if g is None else f'{100 * g:+.1f} %'} | "
                     f"{' / '.join('-' if x is None else f'{x:.0f}' for x in a)} | "
                     f"{' / '.join('-' if x is None else f'{x:.0f}' for x in p)} |")
    lines += ["| count | start | middle | end |", "|---|---|---|---|",
              "| tracker keyframes | " + " | ".join(str(x) for x in r["tracker_keyframes"][:3]) + " |",
              "| mapped keyframes | " + " | ".join(str(x) for x in r["mapped_keyframes"]) + " |",
              "| Gaussians | " + " | ".join(str(x) for x in r["gaussians"]) + " |",
              "checks: " + ", ".join(f"{k} {'ok' if v else 'FAILED'}" for k, v in r["checks"].items())]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=10000, help="frames to play (default 10000)")
    ap.add_argument("--size", default="160x120", help="image size (default 160x120)")
    ap.add_argument("--data-dir", default=str(REPO / "benchmarks" / "data"),
                    help=f"folder with {SOURCE} (rendered there when missing) and the soak bag")
    ap.add_argument("--config", help="SLAM config (default: a fast CPU schedule, see the file)")
    ap.add_argument("--rate", type=float, default=1.0, help="realtime playback speed factor")
    ap.add_argument("--sample-every", type=float, default=2.0, help="seconds between samples")
    ap.add_argument("--timeout", type=float, default=4 * 3600.0, help="seconds for the whole run")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "soak_run"))
    a = ap.parse_args(argv)
    try:
        w, h = (int(x) for x in a.size.lower().split("x"))
        if a.frames < 1 or a.rate <= 0 or w < 32 or h < 32:
            raise ValueError
    except ValueError:
        print("error: --frames >= 1, --rate > 0 and --size WxH (at least 32x32) expected",
              file=sys.stderr)
        return 2
    try:
        data = Path(a.data_dir)
        data.mkdir(parents=True, exist_ok=True)
        bag = pingpong_bag(data, (w, h))
        from splat_slam_ros.io.bagio import BagDataset
        per_pass = len(BagDataset(bag))
        passes = max(1, int(np.ceil(a.frames / per_pass)))
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        cfg = Path(a.config) if a.config else out.parent / "soak_config.yaml"
        if not a.config:
            cfg.write_text(CPU_CONFIG + f"camera:\n  width: {w}\n  height: {h}\n")
        print(f"soak: {passes} passes of {per_pass} frames ({passes * per_pass} frames, "
              f"{w}x{h}, realtime x{a.rate:g}), load {os.getloadavg()}", flush=True)
        res = run_soak(bag, cfg, out, passes, a.rate, a.sample_every, a.timeout)
        r = summarise(res, out)
    except SoakError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    r["config"] = cfg.read_text()
    print(table(r))
    res_dir = REPO / "benchmarks" / "results"
    res_dir.mkdir(parents=True, exist_ok=True)
    (res_dir / "soak.json").write_text(json.dumps(r, indent=2, default=str))
    (res_dir / "soak_samples.json").write_text(json.dumps(res["samples"], default=str))
    return 0 if r["rc"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
