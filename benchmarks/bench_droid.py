#!/usr/bin/env python
"""Per-frame cost of the learned (DROID-SLAM network) and the classical (DIS) flow front end.

What the tracker pays for every input frame: ``prepare(frame)`` (DROID: feature +
context encoders; DIS: grey image + texture) and one ``predict_pair`` against the
last keyframe (both directions; DROID: one correlation volume + ``iters`` GRU
steps on two edges). Each new keyframe adds a few more ``predict_pair`` calls
(its graph edges), so the per-frame figure is a lower bound for keyframes.

The network's weights do not change its cost, so without ``--checkpoint`` a
checkpoint with random weights in the public layout is written to a temporary
file and loaded through the same code path. Accuracy is NOT measured here (no
real checkpoint is available in this project).

    python benchmarks/bench_droid.py [--sizes 320x240,640x480] [--device cpu|cuda|auto]
        [--threads 1] [--iters 4] [--reps 3] [--checkpoint droid.pth]
        [--out benchmarks/results/droid.json]

Prints a table; writes the JSON (median wall and CPU seconds per frame, load average).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from splat_slam_ros.cli.common import run_main  # noqa: E402
from splat_slam_ros.tracking.droid_flow import DroidFlowPredictor  # noqa: E402
from splat_slam_ros.tracking.droid_net import DroidNet  # noqa: E402
from splat_slam_ros.tracking.flow_frontend import DISFlowPredictor  # noqa: E402


def random_checkpoint(path: Path) -> Path:
    torch.manual_seed(0)
    sd = {"module." + k: v for k, v in DroidNet().state_dict().items()}
    torch.save(sd, path)
    return path


def frames(w: int, h: int, shift: int = 6):
    rng = np.random.default_rng(0)
    small = rng.integers(0, 256, (h // 4 + 2, (w + 2 * shift) // 4 + 2, 3), dtype=np.uint8)
    big = np.repeat(np.repeat(small, 4, 0), 4, 1)
    return (np.ascontiguousarray(big[:h, :w]), np.ascontiguousarray(big[:h, shift:shift + w]))


def sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def time_frame(pred, kf_prep, img, dev, reps: int):
    """Median wall / CPU seconds of prepare(img) + predict_pair(kf, img)."""
    walls, cpus, parts = [], [], []
    for _ in range(reps + 1):                                  # first run: warm-up
        sync(dev)
        t0, c0 = time.perf_counter(), time.process_time()
        p = pred.prepare(img)
        sync(dev)
        t1 = time.perf_counter()
        pred.predict_pair(kf_prep, p)
        sync(dev)
        t2, c2 = time.perf_counter(), time.process_time()
        walls.append(t2 - t0)
        cpus.append(c2 - c0)
        parts.append((t1 - t0, t2 - t1))
    walls, cpus, parts = walls[1:], cpus[1:], parts[1:]
    return {"wall_s": statistics.median(walls), "cpu_s": statistics.median(cpus),
            "prepare_s": statistics.median(p[0] for p in parts),
            "pair_s": statistics.median(p[1] for p in parts), "reps": reps}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="320x240,640x480")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads (the tracker runs with tracking.threads=1)")
    ap.add_argument("--iters", type=int, default=4,
                    help="GRU iterations (tracking.flow_model_iters)")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--checkpoint", default="")
    ap.add_argument("--no-dis", action="store_true")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "droid.json"))
    a = ap.parse_args(argv)
    try:
        sizes = [tuple(int(v) for v in s.lower().split("x")) for s in a.sizes.split(",")]
    except ValueError:
        print(f"error: --sizes expects WxH[,WxH...], got {a.sizes!r}", file=sys.stderr)
        return 2
    torch.set_num_threads(max(a.threads, 1))
    tmp = tempfile.TemporaryDirectory()
    ck = Path(a.checkpoint) if a.checkpoint else random_checkpoint(Path(tmp.name) / "droid.pth")
    droid = DroidFlowPredictor.from_checkpoint(ck, a.device, iters=a.iters)
    dis = DISFlowPredictor(8, "dis_medium", 2)
    dev = droid.device
    rows = []
    load0 = os.getloadavg()
    jobs = [(s, name) for s in sizes for name in (["droid"] if a.no_dis else ["droid", "dis"])]
    for (w, h), name in tqdm(jobs, desc="bench_droid"):
        pred = droid if name == "droid" else dis
        kf, img = frames(w, h)
        r = time_frame(pred, pred.prepare(kf), img, dev if name == "droid" else
                       torch.device("cpu"), a.reps)
        r.update(predictor=name, size=f"{w}x{h}", device=str(dev) if name == "droid" else "cpu",
                 loadavg=os.getloadavg()[0])
        rows.append(r)
    gpu = torch.cuda.get_device_name(0) if dev.type == "cuda" else None
    out = {"threads": a.threads, "iters": a.iters, "checkpoint": "random (public layout)"
           if not a.checkpoint else str(ck), "cpu": platform.processor() or platform.machine(),
           "cpu_count": os.cpu_count(), "gpu": gpu, "loadavg_start": load0,
           "loadavg_end": os.getloadavg(), "torch": torch.__version__, "rows": rows}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=2))
    print(f"{'predictor':9s} {'size':8s} {'device':7s} {'wall s/frame':>12s} {'cpu s':>7s} "
          f"{'prepare':>8s} {'pair':>7s} {'load1':>6s}")
    for r in rows:
        print(f"{r['predictor']:9s} {r['size']:8s} {r['device']:7s} {r['wall_s']:12.3f} "
              f"{r['cpu_s']:7.3f} {r['prepare_s']:8.3f} {r['pair_s']:7.3f} {r['loadavg']:6.2f}")
    print(f"threads={a.threads} iters={a.iters} load average start {load0[0]:.2f} end "
          f"{os.getloadavg()[0]:.2f}; wrote {a.out}")
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
