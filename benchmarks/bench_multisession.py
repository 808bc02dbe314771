#!/usr/bin/env python
"""Maps across sessions: one sequence split in two sessions, the second localised in the
first's saved map (``splat-slam-run --load-map RUN --localize``).

    .venv/bin/python benchmarks/bench_multisession.py [--sequence fr2desk] [--split 150]
        [--data-dir DIR] [--json benchmarks/results/multisession.json]

The first session: frames ``0 .. split-1`` with the full default pipeline (``--max-frames split``),
which saves ``session/``. The second: frames ``split ..`` with ``--start-frame split
--load-map S1 --localize``. Printed: frames until relocalised, frames posed / lost in the second
session, the ATE of both sessions' trajectories together under one Sim(3) against the single run's
ATE over the same frames (target: at most 1.5x), whether the second session left the map
byte-identical, and frames/s of each session (input frames / wall time of the whole
command). The sequence is ``bench_defaults.py``'s realistic 640x480 render (rendered into
``--data-dir`` when missing). Extending a loaded map is not supported yet, so there is no
extend-mode row.
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", default="fr2desk", choices=SEQUENCES)
    ap.add_argument("--split", type=int, default=150, help="first frame of the second session")
    ap.add_argument("--data-dir", default=str(REPO / "benchmarks" / "results" / "data"))
    ap.add_argument("--work", default=str(REPO / "benchmarks" / "results" / "multisession_work"))
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "multisession.json"))
    a = ap.parse_args(argv)
    import numpy as np
    from splat_slam_ros.evaluation import ate
    from splat_slam_ros.io.datasets import open_dataset
    seq = ensure_sequence(Path(a.data_dir), a.sequence, 300)
    n = len(open_dataset(seq))
    if not 0 < a.split < n:
        print(f"error: --split must be in 1..{n - 1}", file=sys.stderr)
        return 2
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    s1, s2, single = work / "first", work / "second", work / "single"
    run = tool("splat-slam-run")
    res = {"sequence": a.sequence, "split": a.split, "frames": n}
    res["single"] = timed([run, str(seq), "--out", str(single), "--no-progress"],
                          work / "single.log", None)
    res["first"] = timed([run, str(seq), "--out", str(s1), "--no-progress",
                             "--max-frames", str(a.split)], work / "first.log", None)
    res["second"] = timed([run, str(seq), "--out", str(s2), "--no-progress", "--start-frame",
                             str(a.split), "--load-map", str(s1), "--localize"],
                            work / "second.log", None)
    for k, frames in (("single", n), ("first", a.split), ("second", n - a.split)):
        if res[k]["rc"] != 0:
            print(f"error: {k} exited {res[k]['rc']} (log in {work / (k + '.log')})",
                  file=sys.stderr)
            return 1
        res[k]["fps"] = round(frames / res[k]["wall_command_s"], 3)
    m2 = json.loads((s2 / "metrics.json").read_text())
    gt_ts, gt = open_dataset(seq).gt_trajectory()
    t1, P1 = _trajectory(s1)
    t2, P2 = _trajectory(s2)
    both = ate(gt_ts, gt, np.concatenate([t1, t2]), np.concatenate([P1, P2]))
    ts, Ps = _trajectory(single)
    keep = np.isin(np.round(ts, 6), np.round(np.concatenate([t1, t2]), 6))
    one = ate(gt_ts, gt, ts[keep], Ps[keep])
    res.update(relocalised_frame=m2.get("relocalised_frame"),
               frames_until_relocalised=None if m2.get("relocalised_frame") is None else
               int(m2["relocalised_frame"]) - a.split,
               second_posed=m2.get("frames_posed"), second_lost=m2.get("frames_lost"),
               ate_two_sessions_cm=both["rmse_cm"], ate_single_run_cm=one["rmse_cm"],
               ratio=both["rmse_cm"] / max(one["rmse_cm"], 1e-9),
               map_unchanged=filecmp.cmp(s1 / "map.ply", s2 / "map.ply", shallow=False))
    print(f"\n| {a.sequence}, split at {a.split} | value |\n|---|---|")
    for k in ("frames_until_relocalised", "second_posed", "second_lost",
              "ate_two_sessions_cm", "ate_single_run_cm", "ratio", "map_unchanged"):
        v = res[k]
        print(f"| {k} | {round(v, 3) if isinstance(v, float) else v} |")
    for k in ("single", "first", "second"):
        r = res[k]
        print(f"| {k} frames/s (load {r['load_before'][0]}) | {r['fps']} |")
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(res, indent=1))
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
