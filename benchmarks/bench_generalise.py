#!/usr/bin/env python
"""Generalisation benchmark: tracking on scenes and motions not tuned on, peers beside us.

The suite renders 640x480 sequences with ``splat-slam-synth`` along every real trajectory in
``../shared/data/trajectories`` (TUM hand-held fr1/xyz and fr2/desk, EuRoC V1_02 drone,
KITTI 00 car) at 15, 20 and 30 Hz, in every scene of the generator (room, low_texture, tiled,
repetitive, thin, deep), with procedural or photo textures (the real photos of
``../shared/data``) and the realistic or harsh camera effects, plus the real EuRoC clip of
``../shared/data``. Sequences are split into a **tuning** set (what defaults may be chosen
on) and a **check** set with other seeds, starts, scenes and motions that no parameter is
chosen on; the benchmark prints both and a summary of the check set against the targets
(100 % of frames posed, ATE and frames/s against a peer's where it ran, peak RSS).

Each tracking run is ``bench_tracking.py``'s child: its own process, default configuration,
tracking + loop closure + global BA (``--tracking-only`` of the product), frames/s = input
frames / wall time of the whole process. ``--full`` also runs the whole default pipeline
(``splat-slam-run``) on the cases marked ``full`` (fast drone motion) and prints its
frames/s, keyframes per second and PSNR.

A single run's ATE on a hard sequence moves a lot with any small change (a few cells of one
flow more or less can halve or double it), so a tuning decision on one run per sequence
reads noise. ``--starts N`` runs each sequence from N start frames (0, ``--start-step``,
2 x ``--start-step`` ...; ``splat-slam-run --start-frame``) and reports the run of median
ATE with the range over the starts; the check summary then counts a sequence as fully posed
only when every start posed every frame. Peers run once, from the first frame.

DSO (https://github.com/JakobEngel/dso, GPL-3.0) is never vendored: pass ``--dso BIN`` (a
built ``dso_dataset``) or ``--dso-source DIR`` (a checkout: built with CMake into a scratch
folder under ``--data-dir``). It runs monocular, without photometric calibration
(``mode=1``), headless, on the same PNGs; its ``result.txt`` is read as a TUM trajectory.
ORB-SLAM3 (``--orbslam3``; monocular, GPL-3.0) runs from the ``pyorbslam3`` wheel on PyPI in
a scratch environment under ``--data-dir``, on the same PNGs; ``orb_peer.py`` says how, and
why its vocabulary is trained here unless ``--orb-vocab ORBvoc.txt`` is given. A peer is
measured like our runs: its whole process (start-up included), peak RSS, Sim(3) ATE over
the frames it posed.

    .venv/bin/python benchmarks/bench_generalise.py [--split tuning|check|all]
        [--cases a,b] [--starts N [--start-step K]] [--full]
        [--dso BIN | --dso-source DIR] [--orbslam3
        [--orb-vocab FILE]] [--set KEY=JSON ...]
        [--data-dir DIR] [--out benchmarks/results/generalise.json]

Rendering a missing sequence takes about 1 s per frame (cached under ``--data-dir``).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_tracking as bt                       # noqa: E402  (the tracking child, _save)
import orb_peer                                   # noqa: E402  (ORB-SLAM3 beside us)

REPO = bt.REPO
SHARED = REPO.parent / "shared" / "data"
FR1, FR2 = "freiburg1_xyz-groundtruth.txt", "fr2_desk_groundtruth.txt"
V102, KITTI = "V102_groundtruth.csv", "KITTI_00_gt.txt"
PHOTO_SOURCES = ["tum_fr3_long_office_17/*.png", "icl_nuim_living_room_5/color/*.png",
                 "rgbd_5_frames_ch5/color/*.png", "euroc_v1_01_first95/mav0/cam0/data/*.png"]


def seq(split, traj, start, frames, fps, scene, realism, textures, seed, full=False):
    return dict(split=split, traj=traj, start=start, frames=frames, fps=fps, scene=scene,
                realism=realism, textures=textures, seed=seed, full=full)


# name -> sequence; "real:" sequences are folders of ../shared/data used as they are
SUITE = {
    # tuning set: defaults may be chosen on these
    "t_fr2desk_room_photo": seq("tuning", FR2, 47, 150, 30, "room", "realistic", "photo", 11),
    "t_v102_repetitive": seq("tuning", V102, 8, 150, 20, "repetitive", "realistic", "proc", 12),
    "t_fr1xyz_lowtex": seq("tuning", FR1, 0, 150, 30, "low_texture", "realistic", "proc", 13),
    "t_kitti_deep": seq("tuning", KITTI, 0, 100, 20, "deep", "realistic", "proc", 14),
    "t_v102_thin_harsh": seq("tuning", V102, 0, 150, 20, "thin", "harsh", "photo", 15),
    # fast drone motion, 5 s each along V1_02 (the keyframe rate bound was chosen on these)
    **{f"t_v102_fast{start}": seq("tuning", V102, start, 100, 20, "room", "realistic",
                                  "photo" if start % 20 else "proc", seed)
       for start, seed in ((20, 11), (30, 12), (40, 13), (50, 14), (60, 15), (70, 16))},
    # a 15-Hz camera on fast drone motion: two frames apart the view has moved too far for
    # the flow (the keyframe interval is 0.125 s)
    "t_v102_fast40_15hz": seq("tuning", V102, 40, 75, 15, "room", "realistic", "photo", 17),
    # low texture through a harsh camera (noise, JPEG): the loss threshold's floor
    "t_fr2desk_lowtex_harsh": seq("tuning", FR2, 50, 150, 30, "low_texture", "harsh", "proc",
                                  18),
    # check set: other seeds, starts, scenes, rates; no parameter is chosen on these
    "c_fr2desk_tiled_harsh": seq("check", FR2, 60, 150, 30, "tiled", "harsh", "proc", 101),
    "c_v102_room_photo": seq("check", V102, 8, 200, 20, "room", "realistic", "photo", 102,
                             full=True),
    "c_fr1xyz_thin_photo": seq("check", FR1, 5, 150, 20, "thin", "realistic", "photo", 103),
    "c_v102_lowtex_harsh": seq("check", V102, 2, 150, 30, "low_texture", "harsh", "proc", 104),
    "c_kitti_repetitive": seq("check", KITTI, 20, 100, 20, "repetitive", "realistic", "proc",
                              105),
    "c_v102_tiled_15hz": seq("check", V102, 60, 120, 15, "tiled", "realistic", "photo", 106),
    "c_euroc_v101_real": dict(split="check", real="euroc_v1_01_first95", full=False),
}
# peers beside us (never vendored): result key -> name, and how to run it
PEERS = {"dso": "DSO", "orbslam3": "ORB-SLAM3"}
PEER_FLAGS = {"dso": "--dso BIN or --dso-source DIR", "orbslam3": "--orbslam3"}
# the issue's targets on the check set
TARGETS = dict(posed_frac=1.0, peak_rss_mb=200.0, full_fps=1.24, full_kf_per_s=6.0)


# ------------------------------------------------------------------ sequences
def photo_textures(data_dir: Path) -> Path:
    """A folder of the real photos in ../shared/data (at most 32, spread over the sets)."""
    out = data_dir / "photo_textures"
    if out.is_dir() and any(out.iterdir()):
        return out
    out.mkdir(parents=True, exist_ok=True)
    for pattern in PHOTO_SOURCES:
        files = sorted(SHARED.glob(pattern))
        for f in files[::max(1, len(files) // 8)][:8]:
            shutil.copy(f, out / f"{f.parent.parent.name}_{f.parent.name}_{f.name}")
    if not any(out.iterdir()):
        sys.exit(f"error: no photos found under {SHARED} (needs ../shared/data)")
    return out


def ensure(data_dir: Path, name: str, c: dict) -> Path:
    if "real" in c:
        p = SHARED / c["real"]
        if not p.is_dir():
            sys.exit(f"error: {p} not found (needs ../shared/data)")
        return p
    extra = ["--scene", c["scene"], "--realism", c["realism"], "--seed", str(c["seed"]),
             "--quiet"]
    if c["textures"] == "photo":
        extra += ["--textures", str(photo_textures(data_dir))]
    return bt.ensure_sequence(data_dir, bt.case(c["traj"], c["frames"], extra, f"gen_{name}",
                                                fps=c["fps"], start=c["start"]))


# ------------------------------------------------------------------ DSO
def build_dso(source: Path, data_dir: Path) -> Path:
    """CMake build of a DSO checkout in a scratch folder; the dso_dataset binary."""
    build = data_dir / "dso_build"
    binary = build / "bin" / "dso_dataset"
    if binary.is_file():
        return binary
    if not (source / "CMakeLists.txt").is_file():
        sys.exit(f"error: {source} is not a DSO source checkout (no CMakeLists.txt)")
    build.mkdir(parents=True, exist_ok=True)
    subprocess.run(["cmake", "-S", str(source), "-B", str(build),
                    "-DCMAKE_BUILD_TYPE=Release"], check=True)
    subprocess.run(["cmake", "--build", str(build), "-j", str(os.cpu_count() or 2)], check=True)
    if not binary.is_file():
        sys.exit(f"error: the DSO build did not produce {binary}")
    return binary


def frame_inputs(seq_dir: Path, peer: str = "DSO"):
    """A sequence's image files and stamps in order, its intrinsics and ground truth (what
    a peer runs on: the same PNGs as ours)."""
    sys.path.insert(0, str(REPO))
    from splat_slam_ros.io.datasets import open_dataset
    ds = open_dataset(seq_dir)
    entries = getattr(ds, "_entries", None)
    if entries is None:
        sys.exit(f"error: {seq_dir}: {peer} needs a folder of image files")
    return ([e.image for e in entries], [e.timestamp for e in entries], ds.intrinsics,
            ds.gt_trajectory())


def dso_inputs(seq_dir: Path, work: Path):
    """DSO's input for a sequence: images/ (symlinks, in order), times.txt, camera.txt
    (pinhole, already undistorted: our renders have none; the real EuRoC clip is given
    DSO's RadTan line). Returns (images, camera, frame stamps, ground truth)."""
    paths, stamps, K, (gt_ts, gt) = frame_inputs(seq_dir)
    img = work / "images"
    img.mkdir(parents=True, exist_ok=True)
    with open(work / "times.txt", "w") as fh:
        for i, (p, t) in enumerate(zip(paths, stamps)):
            os.symlink(Path(p).resolve(), img / f"{i:06d}.png")
            fh.write(f"{i:06d} {t:.6f}\n")
    W, H = K.width, K.height
    if K.has_distortion and K.distortion_model == "plumb_bob":
        first = (f"RadTan {K.fx / W} {K.fy / H} {(K.cx + 0.5) / W} {(K.cy + 0.5) / H} "
                 + " ".join(str(float(x)) for x in list(K.distortion)[:4]))
    elif K.has_distortion:
        sys.exit(f"error: {seq_dir}: {K.distortion_model} distortion is not passed to DSO")
    else:
        first = f"Pinhole {K.fx / W} {K.fy / H} {(K.cx + 0.5) / W} {(K.cy + 0.5) / H} 0"
    (work / "camera.txt").write_text(f"{first}\n{W} {H}\ncrop\n{W} {H}\n")
    return img, work / "camera.txt", stamps, (gt_ts, gt)


def read_dso_result(path: Path):
    """DSO's result.txt: ``stamp tx ty tz qx qy qz qw`` (camera-to-world) per posed frame
    (the stamps of times.txt); none when DSO wrote nothing."""
    from splat_slam_ros.io.trajectory_io import read_trajectory
    if not path.is_file() or path.stat().st_size == 0:
        return [], []
    return read_trajectory(path, "tum")


def run_measured(cmd, work: Path, log=subprocess.DEVNULL):
    """A peer's process: exit status, wall seconds (start-up included) and peak RSS (MB,
    its VmHWM polled every 0.2 s)."""
    from splat_slam_ros.heap import proc_memory_mb
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=work, stdout=log, stderr=subprocess.STDOUT
                         if log is not subprocess.DEVNULL else subprocess.DEVNULL)
    hwm = 0.0
    while p.poll() is None:
        hwm = max(hwm, proc_memory_mb(p.pid).get("VmHWM", 0.0))
        time.sleep(0.2)
    return p.returncode, time.perf_counter() - t0, hwm


def peer_result(rc, wall, hwm, load0, stamps, ts, P, gt_ts, gt) -> dict:
    """A peer's row: posed frames, frames/s, peak RSS and its ATE (Sim(3), every frame it
    posed; None under 3)."""
    from splat_slam_ros.evaluation.inputs import MetricError
    from splat_slam_ros.evaluation.trajectory import ate
    r = dict(rc=rc, wall_s=wall, fps=len(stamps) / wall, posed=len(ts), frames=len(stamps),
             peak_rss_mb=hwm, load_before=load0)
    try:
        r["ate_full_cm"] = ate(gt_ts, gt, ts, P)["rmse_cm"] if len(ts) >= 3 else None
    except MetricError as e:
        r["ate_full_cm"], r["error"] = None, str(e)
    return r


def run_dso(binary: Path, seq_dir: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        img, cam, stamps, (gt_ts, gt) = dso_inputs(seq_dir, work)
        cmd = [str(binary), f"files={img}", f"calib={cam}", "mode=1", "preset=0", "nogui=1",
               "nolog=1", "quiet=1", "nomt=0"]
        load0 = os.getloadavg()[0]
        rc, wall, hwm = run_measured(cmd, work)
        ts, P = read_dso_result(work / "result.txt")
    return peer_result(rc, wall, hwm, load0, stamps, ts, P, gt_ts, gt)


# ------------------------------------------------------------------ ORB-SLAM3
def orbslam3_vocabulary(data_dir: Path, given) -> Path:
    """ORB-SLAM3's vocabulary: ``--orb-vocab FILE`` (its own ORBvoc.txt), else one trained
    once from the real photos of ../shared/data (orb_peer.train_vocabulary), cached."""
    if given:
        if not Path(given).is_file():
            sys.exit(f"error: ORB vocabulary not found: {given}")
        return Path(given)
    out = data_dir / f"orbslam3_vocab_k{orb_peer.VOCAB_K}_L{orb_peer.VOCAB_L}.txt"
    if not out.is_file():
        imgs = [p for pat in PHOTO_SOURCES for p in sorted(SHARED.glob(pat))]
        if not imgs:
            sys.exit(f"error: no photos under {SHARED} to train an ORB vocabulary from "
                     "(pass --orb-vocab ORBvoc.txt)")
        words = orb_peer.train_vocabulary(orb_peer.orb_descriptors(imgs), out)
        print(f"trained an ORB vocabulary of {words} words on {len(imgs)} photos: {out}")
    return out


def run_orbslam3(py: Path, vocab: Path, seq_dir: Path) -> dict:
    """ORB-SLAM3 monocular on the sequence's frames (``py``: the scratch environment's
    python, orb_peer.peer_env), measured as DSO is: the whole child process."""
    paths, stamps, K, (gt_ts, gt) = frame_inputs(seq_dir, "ORB-SLAM3")
    fps = 1.0 / float(np.median(np.diff(stamps))) if len(stamps) > 1 else 30.0
    dist = list(K.distortion)[:4] if K.has_distortion else [0.0] * 4
    if K.has_distortion and K.distortion_model != "plumb_bob":
        sys.exit(f"error: {seq_dir}: {K.distortion_model} distortion is not passed to "
                 "ORB-SLAM3")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        job = orb_peer.write_job(work, vocab, orb_peer.settings_yaml(
            K.fx, K.fy, K.cx, K.cy, K.width, K.height, round(fps, 3), dist), paths, stamps)
        load0 = os.getloadavg()[0]
        with open(work / "peer.log", "w") as log:
            rc, wall, hwm = run_measured([str(py), orb_peer.__file__, str(job)], work, log)
        ts, P = orb_peer.read_trajectory(work / "trajectory.txt")
    return peer_result(rc, wall, hwm, load0, stamps, ts, P, gt_ts, gt)


# ------------------------------------------------------------------ full run
def run_full(seq_dir: Path, out: Path, extra) -> dict:
    cmd = [bt.tool("splat-slam-run"), str(seq_dir), "--out", str(out), "--no-progress"]
    cmd += [x for kv in extra for x in ("--set", kv)]
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    with open(out.parent / f"{out.name}.log", "w") as fh:
        rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT).returncode
    wall = time.perf_counter() - t0
    m = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() \
        else {}
    frames = int(m.get("frames") or 0)
    dur = None
    if (out / "trajectory_full.txt").is_file():            # seconds of input
        from splat_slam_ros.io.trajectory_io import read_trajectory
        ts, _ = read_trajectory(out / "trajectory_full.txt", "tum")
        dur = float(ts[-1] - ts[0]) if len(ts) > 1 else None
    return dict(rc=rc, wall_s=round(wall, 1), fps=frames / wall if frames else 0.0,
                keyframes=m.get("keyframes"), psnr=m.get("psnr"), ate_full_cm=m.get(
                    "ate_rmse_cm_full"), kf_per_s=(m.get("keyframes") or 0) / dur if dur else
                None, load_before=load0)


# ------------------------------------------------------------------ starts
def ate_key(r: dict) -> float:
    """A run's ATE for ordering; a run without one (never initialised) is the worst."""
    return float("inf") if r["ate_full_cm"] is None else float(r["ate_full_cm"])


def over_starts(runs: list) -> dict:
    """The case's row from its runs (one per start frame): the run of median ATE (the
    lower one of an even count), with every run's start, ATE, posed and lost frames and
    keyframes under ``starts``."""
    r = dict(sorted(runs, key=ate_key)[(len(runs) - 1) // 2])
    r["starts"] = [{k: x[k] for k in ("start_frame", "ate_full_cm", "posed", "frames", "lost",
                                      "keyframes")} for x in runs]
    return r


def all_posed(r: dict) -> bool:
    """Every frame posed and none lost, in every start's run."""
    return all(x["posed"] == x["frames"] and x["lost"] == 0 for x in r.get("starts") or [r])


def ate_cell(r: dict) -> str:
    """The ATE (cm) and, over several starts, its range: ``0.95 (0.87-1.13)``; a start
    that never initialised: ``no ATE``; none did: ``-``."""
    runs = r.get("starts") or []
    if len(runs) < 2:
        return fmt(r["ate_full_cm"])
    vals = sorted(runs, key=ate_key)
    if vals[0]["ate_full_cm"] is None:
        return "-"
    worst = vals[-1]["ate_full_cm"]
    return f"{fmt(r['ate_full_cm'])} ({fmt(vals[0]['ate_full_cm'])}-" \
           f"{'no ATE' if worst is None else fmt(worst)})"


# ------------------------------------------------------------------ output
def fmt(v, spec=".3f"):
    return "-" if v is None else format(v, spec)


def table(results: dict) -> None:
    peers = [p for p in PEERS if any(r.get(p) for r in results.values())] or ["dso"]
    print("\n| case | split | posed | kf | kf/s | ATE full (cm) | ATE kf | scale drift | "
          "frames/s | RSS (MB) | load | " + " | ".join(
              f"{PEERS[p]} ATE | {PEERS[p]} posed | {PEERS[p]} frames/s | {PEERS[p]} RSS"
              for p in peers) + " |")
    print("|---" * (11 + 4 * len(peers)) + "|")
    for name, r in results.items():
        lost = f" ({r['lost']} lost)" if r["lost"] else ""
        cols = []
        for p in peers:
            d = r.get(p) or {}
            cols.append(f"{fmt(d.get('ate_full_cm'))} | "
                        f"{d.get('posed', '-')}{'/' + str(d['frames']) if d else ''} | "
                        f"{fmt(d.get('fps'), '.1f')} | {fmt(d.get('peak_rss_mb'), '.0f')}")
        print(f"| {name} | {r['split']} | {r['posed']}/{r['frames']}{lost} | {r['keyframes']} | "
              f"{r['kf_per_s']:.1f} | {ate_cell(r)} | {fmt(r['ate_kf_cm'])} | "
              f"{fmt(r['scale_drift'])} | {r['fps']:.1f} | {r['peak_rss_mb']:.0f} | "
              f"{r['load_before']:.1f} | " + " | ".join(cols) + " |")
    full = {n: r["full"] for n, r in results.items() if r.get("full")}
    for n, f in full.items():
        print(f"\nfull default run, {n}: {f['fps']:.2f} frames/s (target >= "
              f"{TARGETS['full_fps']}), {f['keyframes']} keyframes = {fmt(f['kf_per_s'], '.1f')}"
              f" per second of input (target <= {TARGETS['full_kf_per_s']}), PSNR "
              f"{fmt(f['psnr'], '.2f')} dB, ATE {fmt(f['ate_full_cm'])} cm, rc {f['rc']}")


def check_summary(results: dict) -> dict:
    chk = {n: r for n, r in results.items() if r["split"] == "check"}
    if not chk:
        return {}
    scored = [r for r in chk.values() if r["ate_full_cm"] is not None]
    s = {"sequences": len(chk), "with_ate": len(scored),
         "all_frames_posed": sum(all_posed(r) for r in chk.values()),
         "rss_le_200mb": sum(r["peak_rss_mb"] <= TARGETS["peak_rss_mb"] for r in chk.values()),
         "median_ate_full_cm": float(np.median([r["ate_full_cm"] for r in scored]))
         if scored else None,
         "max_scale_drift": max((r["scale_drift"] for r in scored), default=None)}
    for p in PEERS:     # a peer "tracks" a sequence when it posed enough frames for an ATE
        ran = {n: r for n, r in chk.items() if (r.get(p) or {}).get("ate_full_cm") is not None
               and r["ate_full_cm"] is not None}
        if ran:
            s[f"{p}_tracked"] = len(ran)
            s[f"ate_le_{p}"] = sum(r["ate_full_cm"] <= r[p]["ate_full_cm"]
                                   for r in ran.values())
            s[f"fps_ge_{p}"] = sum(r["fps"] >= r[p]["fps"] for r in ran.values())
            s[f"posed_ge_{p}"] = sum(r["posed"] >= r[p]["posed"] for r in ran.values())
            s[f"ate_ratio_to_{p}"] = {n: r["ate_full_cm"] / max(r[p]["ate_full_cm"], 1e-9)
                                      for n, r in ran.items()}
    print("\ncheck set: " + ", ".join(f"{k} {v if not isinstance(v, float) else round(v, 3)}"
                                      for k, v in s.items() if not k.startswith("ate_ratio")))
    for p, label in PEERS.items():
        if f"ate_ratio_to_{p}" in s:
            print(f"ATE / {label}'s: " + ", ".join(f"{n} {v:.2f}" for n, v in
                                                  s[f"ate_ratio_to_{p}"].items()))
        else:
            print(f"{label}: not run (pass {PEER_FLAGS[p]})")
    return s


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", choices=["tuning", "check", "all"], default="all")
    ap.add_argument("--cases", default="", help=f"comma-separated, from: {', '.join(SUITE)}")
    ap.add_argument("--starts", type=int, default=1, metavar="N",
                    help="runs of ours per sequence, from start frames 0, K, 2K ... (the row: "
                         "the run of median ATE, with the range; default 1)")
    ap.add_argument("--start-step", type=int, default=2, metavar="K",
                    help="frames between the start frames of --starts (default 2)")
    ap.add_argument("--full", action="store_true",
                    help="also the whole default pipeline on the cases marked full")
    ap.add_argument("--dso", help="a built DSO dso_dataset binary")
    ap.add_argument("--dso-source", help="a DSO source checkout, built into --data-dir")
    ap.add_argument("--orbslam3", action="store_true",
                    help="ORB-SLAM3 monocular beside us (pip wheel pyorbslam3 in a scratch "
                         "environment under --data-dir)")
    ap.add_argument("--orb-vocab", help="ORB-SLAM3's ORBvoc.txt (default: a vocabulary "
                                        "trained on ../shared/data's photos)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                    help="config override for every run of ours")
    ap.add_argument("--data-dir", default=str(REPO / "benchmarks" / "results" / "data"))
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "generalise.json"))
    a = ap.parse_args(argv)
    names = [c for c in a.cases.split(",") if c] or \
        [n for n, c in SUITE.items() if a.split in ("all", c["split"])]
    unknown = [c for c in names if c not in SUITE]
    if unknown:
        print(f"error: unknown case(s) {', '.join(unknown)} (use {', '.join(SUITE)})",
              file=sys.stderr)
        return 2
    if a.starts < 1 or a.start_step < 1 or (a.starts - 1) * a.start_step >= 30:
        print(f"error: --starts {a.starts} and --start-step {a.start_step}: both >= 1, the "
              "last start frame ((N - 1) x K) below 30", file=sys.stderr)
        return 2
    from splat_slam_ros.cli.common import parse_overrides
    from splat_slam_ros.config import ConfigError, load_config
    try:
        overrides = parse_overrides(a.set)
        load_config(None, overrides)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    data_dir = Path(a.data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    dso = Path(a.dso) if a.dso else build_dso(Path(a.dso_source), data_dir) \
        if a.dso_source else None
    if dso is not None and not dso.is_file():
        print(f"error: DSO binary not found: {dso}", file=sys.stderr)
        return 2
    orb = None
    if a.orbslam3 or a.orb_vocab:
        orb = (orb_peer.peer_env(data_dir), orbslam3_vocabulary(data_dir, a.orb_vocab))
    results = {}
    for name in names:
        c = SUITE[name]
        sdir = ensure(data_dir, name, c)
        print(f"== {name} ({c['split']}): {sdir}", flush=True)
        runs = []
        for k in range(a.starts):
            start = k * a.start_step
            runs.append(bt.run_case(name if k == 0 else f"{name}_from{start}", sdir, overrides,
                                    "", data_dir, start_frame=start))
            runs[-1]["start_frame"] = start
            if a.starts > 1:
                x = runs[-1]
                print(f"   from frame {start}: ATE {fmt(x['ate_full_cm'])} cm, "
                      f"{x['posed']}/{x['frames']} posed ({x['lost']} lost), "
                      f"{x['keyframes']} kf, {x['fps']:.1f} frames/s", flush=True)
        r = over_starts(runs) if a.starts > 1 else runs[0]
        r["split"] = c["split"]
        if dso is not None:
            r["dso"] = run_dso(dso, sdir)
        if orb is not None:
            r["orbslam3"] = run_orbslam3(*orb, sdir)
        if a.full and c.get("full"):
            r["full"] = run_full(sdir, data_dir / f"full_{name}", a.set)
        results[name] = r
        print(f"   ATE {ate_cell(r)} cm, {r['posed']}/{r['frames']} posed "
              f"({r['lost']} lost), "
              f"{r['keyframes']} kf ({r['kf_per_s']:.1f}/s), scale drift "
              f"{fmt(r['scale_drift'])}, {r['fps']:.1f} frames/s, {r['peak_rss_mb']:.0f} MB, "
              f"load {r['load_before']:.1f}", flush=True)
        for p, label in PEERS.items():
            if r.get(p):
                d = r[p]
                print(f"   {label}: ATE {fmt(d['ate_full_cm'])} cm, {d['posed']}/{d['frames']} "
                      f"posed, {d['fps']:.1f} frames/s, {d['peak_rss_mb']:.0f} MB", flush=True)
        bt._save(Path(a.out), {name: r})
    table(results)
    summary = check_summary(results)
    if summary:
        old = json.loads(Path(a.out).read_text())
        old["check_summary"] = summary
        Path(a.out).write_text(json.dumps(old, indent=1))
    print(f"\nwrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
