#!/usr/bin/env python
"""Maps across sessions: one sequence split in two sessions, the second localised in the
first's saved map (``splat-slam-run --load-map RUN --localize``) and extending it
(``--load-map RUN``).

    .venv/bin/python benchmarks/bench_multisession.py [--sequence fr2desk] [--split 150]
        [--data-dir DIR] [--json benchmarks/results/multisession.json] [--graph]

The first session: frames ``0 .. split-1`` with the full default pipeline (``--max-frames split``),
which saves ``session/``. The second, in both modes: frames ``split ..`` with ``--start-frame
split --load-map S1 --localize`` and with ``--start-frame split --load-map S1`` (extend).
Printed per mode: frames until relocalised, frames posed / lost in the second session, the ATE
of both sessions' trajectories together under one Sim(3) against the single run's ATE over the
same frames (target: at most 1.5x), frames/s of each session (input frames / wall time of the
whole command); localize: whether the map stayed byte-identical; extend: keyframes and
Gaussians before and after, and the PSNR of the first session's keyframes in the extended map
against the first session's own (target: no loss above 0.5 dB). The sequence is
``bench_defaults.py``'s realistic 640x480 render (rendered into ``--data-dir`` when missing).
With ``--graph`` both second sessions run through the node graph instead:
``splat-slam-launch --bag B --load-map S1 [--localize]`` on a bag of frames ``split ..``
(lockstep; its frame indices start at 0, so "frames until relocalised" is its own count).
"""
from __future__ import annotations

import argparse
import filecmp
import json
import sys
from pathlib import Path

from bench_defaults import REPO, ensure_sequence, timed, tool

SEQUENCES = ("fr2desk", "fr1xyz")


def _trajectory(run: Path):
    from splat_slam_ros.io.trajectory_io import read_trajectory
    return read_trajectory(run / "trajectory_full.txt", "tum")


def _keyframe_psnr(run: Path) -> dict:
    views = json.loads((run / "renders" / "keyframes.json").read_text())["keyframes"]
    return {int(v["kf_id"]): float(v["psnr"]) for v in views}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", default="fr2desk", choices=SEQUENCES)
    ap.add_argument("--split", type=int, default=150, help="first frame of the second session")
    ap.add_argument("--data-dir", default=str(REPO / "benchmarks" / "results" / "data"))
    ap.add_argument("--work", default=str(REPO / "benchmarks" / "results" / "multisession_work"))
    ap.add_argument("--json", default=None, help="results file (default "
                    "benchmarks/results/multisession[_graph].json)")
    ap.add_argument("--graph", action="store_true", help="second sessions through "
                    "splat-slam-launch (a bag of the second part)")
    a = ap.parse_args(argv)
    a.json = a.json or str(REPO / "benchmarks" / "results" /
                           f"multisession{'_graph' if a.graph else ''}.json")
    import numpy as np
    from splat_slam_ros.evaluation.trajectory import ate
    from splat_slam_ros.io.datasets import open_dataset
    seq = ensure_sequence(Path(a.data_dir), a.sequence, 300)
    n = len(open_dataset(seq))
    if not 0 < a.split < n:
        print(f"error: --split must be in 1..{n - 1}", file=sys.stderr)
        return 2
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    s1, s2, s3, single = (work / n for n in ("first", "second", "extend", "single"))
    run = tool("splat-slam-run")
    res = {"sequence": a.sequence, "split": a.split, "frames": n}
    res["single"] = timed([run, str(seq), "--out", str(single), "--no-progress"],
                          work / "single.log", None)
    res["first"] = timed([run, str(seq), "--out", str(s1), "--no-progress",
                             "--max-frames", str(a.split)], work / "first.log", None)
    if a.graph:                         # the second part as a bag, through the graph
        from splat_slam_ros.io.bagio import write_bag
        from splat_slam_ros.io.datasets import FromFrame
        bag = work / "second_bag"
        write_bag(FromFrame(open_dataset(seq), a.split), bag, progress=False, overwrite=True)
        second = [tool("splat-slam-launch"), "--bag", str(bag), "--fresh", "--load-map", str(s1)]
    else:
        second = [run, str(seq), "--no-progress", "--start-frame", str(a.split), "--load-map",
                  str(s1)]
    res["second"] = timed(second + ["--out", str(s2), "--localize"], work / "second.log", None)
    res["extend"] = timed(second + ["--out", str(s3)], work / "extend.log", None)
    offset = 0 if a.graph else a.split  # the second session's first frame index
    for k, frames in (("single", n), ("first", a.split), ("second", n - a.split),
                      ("extend", n - a.split)):
        if res[k]["rc"] != 0:
            print(f"error: {k} exited {res[k]['rc']} (log in {work / (k + '.log')})",
                  file=sys.stderr)
            return 1
        res[k]["fps"] = round(frames / res[k]["wall_command_s"], 3)
    m2 = json.loads((s2 / "metrics.json").read_text())
    if isinstance(m2.get("localize"), dict):     # the graph's metrics keep these apart
        m2.update(m2["localize"])
    gt_ts, gt = open_dataset(seq).gt_trajectory()
    t1, P1 = _trajectory(s1)
    t2, P2 = _trajectory(s2)
    both = ate(gt_ts, gt, np.concatenate([t1, t2]), np.concatenate([P1, P2]))
    ts, Ps = _trajectory(single)
    keep = np.isin(np.round(ts, 6), np.round(np.concatenate([t1, t2]), 6))
    one = ate(gt_ts, gt, ts[keep], Ps[keep])
    res.update(relocalised_frame=m2.get("relocalised_frame"),
               frames_until_relocalised=None if m2.get("relocalised_frame") is None else
               int(m2["relocalised_frame"]) - offset,
               second_posed=m2.get("frames_posed"), second_lost=m2.get("frames_lost"),
               ate_two_sessions_cm=both["rmse_cm"], ate_single_run_cm=one["rmse_cm"],
               ratio=both["rmse_cm"] / max(one["rmse_cm"], 1e-9),
               map_unchanged=filecmp.cmp(s1 / "map.ply", s2 / "map.ply", shallow=False))
    m3 = json.loads((s3 / "metrics.json").read_text())
    x = m3["extend"]
    t3, P3 = _trajectory(s3)
    both3 = ate(gt_ts, gt, np.concatenate([t1, t3]), np.concatenate([P1, P3]))
    p1, p3 = _keyframe_psnr(s1), _keyframe_psnr(s3)
    drop = [p1[k] - p3[k] for k in p1 if k in p3]
    res.update(extend_frames_until_relocalised=None if x["relocalised_frame"] is None else
               int(x["relocalised_frame"]) - offset,
               extend_posed=m3.get("frames_posed"), extend_lost=m3.get("frames_lost"),
               extend_ate_two_sessions_cm=both3["rmse_cm"],
               extend_ratio=both3["rmse_cm"] / max(one["rmse_cm"], 1e-9),
               extend_keyframes=f"{x['loaded']['keyframes']} + {x['new_keyframes']}",
               extend_mapped_keyframes=f"{x['loaded']['mapped_keyframes']} -> "
                                       f"{x['mapped_keyframes']}",
               extend_gaussians=f"{x['loaded']['gaussians']} -> {x['gaussians']}",
               extend_first_keyframes_psnr=f"{np.mean(list(p1.values())):.2f} -> "
                                           f"{np.mean([p3[k] for k in p1 if k in p3]):.2f}",
               extend_first_keyframes_max_loss_db=max(drop) if drop else None,
               extend_psnr_all=m3.get("psnr"))
    print(f"\n| {a.sequence}, split at {a.split}{', graph' if a.graph else ''} | value |\n"
          f"|---|---|")
    for k in ("frames_until_relocalised", "second_posed", "second_lost",
              "ate_two_sessions_cm", "ate_single_run_cm", "ratio", "map_unchanged",
              "extend_frames_until_relocalised", "extend_posed", "extend_lost",
              "extend_ate_two_sessions_cm", "extend_ratio", "extend_keyframes",
              "extend_mapped_keyframes", "extend_gaussians", "extend_first_keyframes_psnr",
              "extend_first_keyframes_max_loss_db", "extend_psnr_all"):
        v = res[k]
        print(f"| {k} | {round(v, 3) if isinstance(v, float) else v} |")
    for k in ("single", "first", "second", "extend"):
        r = res[k]
        print(f"| {k} frames/s (load {r['load_before'][0]}) | {r['fps']} |")
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(res, indent=1))
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
