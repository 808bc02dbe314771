"""The run report's data: a run directory's files read back into one :class:`RunRecord`.

Only files are read (metrics.json, trajectory_*.txt, groundtruth.txt, config.yaml, renders/),
never a live pipeline, so a report built at the end of a run and one rebuilt later by
``splat-slam-report`` are the same.
"""
from __future__ import annotations

import base64
import html
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np
import torch

from splat_slam_ros.evaluation.inputs import MetricError
from splat_slam_ros.evaluation.trajectory import align_poses, ate
from splat_slam_ros.io.trajectory_io import TrajectoryFormatError, read_trajectory
from splat_slam_ros.mapping.keyframe_views import KEYFRAMES_JSON
from splat_slam_ros.report import plots as rp

REPORT_HTML = "report.html"
REPORT_PNG = "report.png"
CONFIG_YAML = "config.yaml"
GROUNDTRUTH = "groundtruth.txt"
THUMB_WIDTH = 256


class ReportError(ValueError):
    """A user-facing report mistake (not a run directory, unreadable metrics)."""


# ====================================================================== loading
@dataclass
class RunRecord:
    """Everything the report shows, read from one run directory."""
    run_dir: Path
    metrics: dict = field(default_factory=dict)
    config_text: Optional[str] = None
    est: Optional[Tuple[np.ndarray, np.ndarray]] = None
    est_kf: Optional[Tuple[np.ndarray, np.ndarray]] = None
    gt: Optional[Tuple[np.ndarray, np.ndarray]] = None
    ate: Optional[dict] = None
    ate_kf: Optional[dict] = None
    kf_doc: Optional[dict] = None
    warnings: List[str] = field(default_factory=list)
    missing: List[str] = field(default_factory=list)

    @property
    def keyframes(self) -> List[dict]:
        return list((self.kf_doc or {}).get("keyframes", []))

    @property
    def history(self) -> List[dict]:
        return list((self.kf_doc or {}).get("history", []))

    @property
    def name(self) -> str:
        return str(self.metrics.get("dataset") or self.run_dir.resolve().name)


def _read_traj(path: Path, rec: RunRecord):
    if not path.is_file():
        return None
    try:
        ts, P = read_trajectory(path, "tum")
    except TrajectoryFormatError as e:
        rec.warnings.append(f"{path.name} could not be read: {e}")
        return None
    if len(ts) == 0:
        rec.warnings.append(f"{path.name} is empty (no pose was estimated)")
        return None
    return ts, P


def _align(rec: RunRecord, est, label: str) -> Optional[dict]:
    if rec.gt is None or est is None:
        return None
    try:
        return ate(rec.gt[0], rec.gt[1], est[0], est[1], align="sim3")
    except MetricError as e:
        rec.warnings.append(f"no ATE for the {label} trajectory: {e}")
        return None


def load_run(run_dir) -> RunRecord:
    """Read a run directory; ReportError if it is not one."""
    d = Path(run_dir)
    if not d.is_dir():
        raise ReportError(f"run directory not found: {d}")
    files = ("metrics.json", "trajectory_full.txt", f"renders/{KEYFRAMES_JSON}")
    if not any((d / f).is_file() for f in files):
        raise ReportError(f"{d} is not a run directory (it has none of {', '.join(files)}); "
                          "give the --out folder of splat-slam-run or splat-slam-launch")
    rec = RunRecord(d)
    if (d / "metrics.json").is_file():
        try:
            rec.metrics = json.loads((d / "metrics.json").read_text())
        except json.JSONDecodeError as e:
            raise ReportError(f"{d / 'metrics.json'} is not valid JSON: {e}") from None
    else:
        rec.missing.append("metrics.json: frame counts, timings and frames/s were not recorded")
    if (d / CONFIG_YAML).is_file():
        rec.config_text = (d / CONFIG_YAML).read_text()
    else:
        rec.missing.append(f"{CONFIG_YAML}: the configuration of this run was not recorded")
    rec.est = _read_traj(d / "trajectory_full.txt", rec)
    rec.est_kf = _read_traj(d / "trajectory_keyframes.txt", rec)
    rec.gt = _read_traj(d / GROUNDTRUTH, rec)
    if rec.metrics.get("mode") == "gt_mapping":
        rec.missing.append("trajectory error: this run mapped on ground-truth poses "
                           "(--gt-poses), so its trajectory is the ground truth")
    elif rec.gt is None:
        rec.missing.append("ground truth: the input had no ground-truth poses, so there is "
                           "no ATE and the trajectory is shown unaligned, in map units")
    else:
        rec.ate = _align(rec, rec.est, "full")
        rec.ate_kf = _align(rec, rec.est_kf, "keyframe")
    kj = d / "renders" / KEYFRAMES_JSON
    if kj.is_file():
        try:
            rec.kf_doc = json.loads(kj.read_text())
        except json.JSONDecodeError as e:
            rec.warnings.append(f"renders/{KEYFRAMES_JSON} is not valid JSON: {e}")
    if not rec.keyframes and (d / "map.ply").is_file():
        rec.missing.append(f"keyframe views: the run wrote map.ply but no renders/"
                           f"{KEYFRAMES_JSON} (made before the report existed?), so there are "
                           "no per-keyframe images, image metrics or map history")
    elif not rec.keyframes:
        rec.missing.append("map: this run built no Gaussian map (tracking only, or no keyframe "
                           "reached the mapper), so there are no rendered keyframes, image "
                           "metrics or map size")
    rec.warnings = derive_warnings(rec) + rec.warnings
    return rec


def derive_warnings(rec: RunRecord) -> List[str]:
    """What went wrong, from the recorded numbers (plus the warnings the run logged)."""
    m, out = rec.metrics, []
    frames = m.get("frames")
    if m.get("error"):
        out.append(str(m["error"]))
    elif m and m.get("mode") != "gt_mapping" and int(m.get("keyframes") or 0) == 0:
        out.append("the tracker never initialised: no keyframe was made (too little camera "
                   "motion or texture for the motion filter / warm-up)")
    if m.get("frames_dropped"):
        out.append(f"{m['frames_dropped']} input frames were dropped before tracking")
    received = m.get("frames_received")
    if isinstance(received, int) and isinstance(frames, int) and received < frames:
        out.append(f"only {received} of {frames} played frames reached the tracker")
    if rec.est is not None and isinstance(frames, int) and m.get("mode") != "gt_mapping" \
            and len(rec.est[0]) < frames:
        out.append(f"{frames - len(rec.est[0])} of {frames} frames have no estimated pose")
    for k in sorted(m):
        if k.startswith("ate_error_") or k == "evaluation_error":
            out.append(f"{k}: {m[k]}")
    for n, v in sorted((m.get("nodes") or {}).items()):
        if isinstance(v, dict) and v.get("restarts"):
            out.append(f"node {n} crashed and was restarted {v['restarts']} time(s)")
    out += [str(w) for w in m.get("warnings") or []]
    return out


# ====================================================================== images
def _read_rgb(path: Path) -> Optional[np.ndarray]:
    im = cv2.imread(str(path), cv2.IMREAD_COLOR) if path.is_file() else None
    return None if im is None else np.ascontiguousarray(im[..., ::-1])


def _read_depth(path: Path, scale: float) -> Optional[torch.Tensor]:
    im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    if im is None or im.ndim != 2:
        return None
    return torch.from_numpy(im.astype(np.float32)) / float(scale)


TILE_NAMES = ("input", "rendered RGB", "rendered depth", "proxy depth", "colour error")


def keyframe_tiles(rec: RunRecord, kf_id: int) -> List[Optional[np.ndarray]]:
    """The five tiles of one keyframe: input, render, rendered depth, proxy depth, error."""
    r = rec.run_dir / "renders"
    name = f"kf_{kf_id:05d}"
    scale = float((rec.kf_doc or {}).get("depth_scale", 1000.0))
    inp, ren = _read_rgb(r / f"{name}_input.png"), _read_rgb(r / f"{name}.png")
    dep, prx = _read_depth(r / f"{name}_depth.png", scale), _read_depth(r / f"{name}_proxy.png",
                                                                          scale)
    lo, hi = rp.depth_range(*[x for x in (prx, dep) if x is not None])
    err = None
    if inp is not None and ren is not None and inp.shape == ren.shape:
        err = rp.colour_error(ren, inp)
    return [inp, ren, None if dep is None else rp.colour_depth(dep, lo, hi),
            None if prx is None else rp.colour_depth(prx, lo, hi), err]


def depth_unit(rec: RunRecord) -> Tuple[float, str]:
    """Factor from the map's depth units to the shown unit, and its label."""
    if rec.metrics.get("mode") == "gt_mapping":
        return 100.0, "cm"
    if rec.ate is not None:
        return 100.0 * float(rec.ate["scale"]), "cm (Sim(3) scale)"
    return 1.0, "map units"


def worst_keyframe(rec: RunRecord) -> Optional[dict]:
    kfs = [k for k in rec.keyframes if isinstance(k.get("psnr"), (int, float))]
    return min(kfs, key=lambda k: (k["psnr"], k["kf_id"])) if kfs else None


def stage_times(rec: RunRecord) -> Tuple[Dict[str, float], str]:
    """In-process: seconds per stage; graph: CPU seconds per node."""
    t = rec.metrics.get("timings_s") or {}
    if t:
        out = {k: float(v) for k, v in t.items()}
        wall = rec.metrics.get("wall_s")
        if isinstance(wall, (int, float)) and wall > sum(out.values()):
            out["other (input, output, evaluation)"] = float(wall) - sum(out.values())
        return out, "wall time [s]"
    nodes = rec.metrics.get("nodes") or {}
    if nodes:
        return {k: float(v.get("cpu_s", 0.0)) for k, v in nodes.items()}, "CPU time per node [s]"
    return {}, ""


def headline(rec: RunRecord) -> str:
    m = rec.metrics
    parts = [f"{rec.name} ({m.get('mode', '?')})"]
    if "frames" in m:
        parts.append(f"{m['frames']} frames, {m.get('keyframes', 0)} keyframes")
    if isinstance(m.get("fps"), (int, float)):
        parts.append(f"{m['fps']:.2f} frames/s")
    if rec.ate is not None:
        parts.append(f"ATE {rec.ate['rmse_cm']:.2f} cm")
    if isinstance(m.get("psnr"), (int, float)):
        parts.append(f"PSNR {m['psnr']:.2f} dB")
    return "  |  ".join(parts)


def fmt(v, nd: int = 2, unit: str = "") -> str:
    """A number for the page ('n/a' for missing or non-finite values)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        return "n/a" if v is None or isinstance(v, (int, float)) else html.escape(str(v))
    s = f"{v:.{nd}f}" if isinstance(v, float) else str(v)
    return s + (f" {unit}" if unit else "")


def data_uri(data: bytes) -> str:
    kind = "jpeg" if data[:2] == b"\xff\xd8" else "png"
    return f"data:image/{kind};base64," + base64.b64encode(data).decode("ascii")


def keyframe_positions(rec: RunRecord) -> Optional[np.ndarray]:
    """Keyframe positions in the plotted frame: aligned with the full trajectory's Sim(3)
    when there is ground truth (so they lie on the plotted estimate), else as estimated."""
    if rec.est_kf is None:
        return None
    P = rec.est_kf[1]
    if rec.ate is not None:
        P = align_poses(P, rec.ate["scale"], rec.ate["rotation"], rec.ate["translation"])
    return P[:, :3, 3]
