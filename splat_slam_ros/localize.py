"""Localize-only runs (``splat-slam-run SEQ --out OUT2 --load-map OUT --localize``).

The session that the run in ``OUT`` saved (``OUT/session/``, :mod:`splat_slam_ros.io.session`)
is loaded and validated before any frame; every frame of the input is then tracked in it
by :class:`~splat_slam_ros.tracking.relocalise.Localizer` (relocalisation by descriptor +
DIS flow + pose-only fit, then tracking against the stored keyframes; nothing is added to
the session or optimised). Outputs in ``OUT2``: trajectory_full.txt (the posed frames, in
the session's frame; lost frames are not written), metrics.json (``localize``,
``relocalised_frame``, frame counts, ATE with Sim(3) alignment when the input has ground
truth), config.yaml, and map.ply: a byte-identical copy of the loaded map.
"""
from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Dict, Optional

from splat_slam_ros.config import SlamConfig, dump_config
from splat_slam_ros.io.prefetch import read_frames
from splat_slam_ros.io.session import Session, remove_session
from splat_slam_ros.io.trajectory_io import write_tum
from splat_slam_ros.pipeline import (NotInitializedError, RunResult, _write_json,
                                     evaluate_trajectories, frame_counts)
from splat_slam_ros.roles import Outbox
from splat_slam_ros.tracking.relocalise import Localizer
from splat_slam_ros.types import TrackStep


class NeverRelocalisedError(NotInitializedError):
    """No input frame matched the loaded session (exit status 3, like a run that never
    initialised: no result)."""


def run_localize(dataset, cfg: SlamConfig, out: Path, session: Session, progress: bool = True,
                 max_frames: Optional[int] = None) -> RunResult:
    """Track ``dataset`` in ``session`` without changing it; writes the outputs to ``out``.
    Raises :class:`NeverRelocalisedError` (after writing metrics.json) when no frame was
    posed; SessionError (before any frame) when the camera differs from the session's."""
    loc = Localizer(cfg, dataset.intrinsics, session)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    n = 0
    for frame in read_frames(dataset, progress, len(dataset), max_frames,
                             lambda k: dict(posed=len(loc.stamps), lost=loc.n_lost)):
        loc.track(frame)
        n += 1
    result = RunResult(frames=n, keyframes=0)
    result.wall_s = time.perf_counter() - t_start
    metrics: Dict[str, object] = {"mode": "localize", "localize": True,
                                  "dataset": getattr(dataset, "name", "?"),
                                  "session": str(session.path.parent),
                                  "session_keyframes": len(loc.ids),
                                  "relocalised_frame": loc.relocalised_frame,
                                  "relocalised_keyframe": loc.relocalised_keyframe,
                                  "relocalisations": loc.n_relocalisations,
                                  "frames": n, "keyframes": 0}
    metrics.update(frame_counts(n, 0, len(loc.stamps), lost=loc.n_lost))
    # outputs of an earlier run in ``out`` that this one does not write would mislead
    for stale in ("trajectory_full.txt", "trajectory_keyframes.txt", "map.ply"):
        (out / stale).unlink(missing_ok=True)
    remove_session(out)
    if loc.stamps:
        write_tum(out / "trajectory_full.txt", *loc.trajectory())
        evaluate_trajectories(dataset, out, metrics)
    if session.map_path is not None:
        shutil.copyfile(session.map_path, out / "map.ply")     # the map, never re-optimised
    metrics["map"] = "copied from the session" if session.map_path is not None else None
    metrics["wall_s"] = round(result.wall_s, 3)
    metrics["fps"] = round(n / max(result.wall_s, 1e-9), 3)
    if loc.relocalised_frame is None:
        metrics["error"] = (f"never relocalised in the loaded map: none of the {n} frames "
                            f"matched any of the session's {len(loc.ids)} keyframes "
                            f"(another place, or too little overlap with the first run)")
    _write_json(out / "metrics.json", metrics)
    dump_config(cfg, out / "config.yaml")
    if "error" in metrics:
        raise NeverRelocalisedError(metrics["error"])
    result.metrics = metrics
    return result


class LocalizeRole:
    """The tracker node's role in a localize-only graph (``splat-slam-launch --load-map RUN
    --localize``): the :class:`Localizer` behind the interface of
    :class:`~splat_slam_ros.roles.TrackerRole`. It publishes no keyframe and no update; the
    node publishes each located frame's pose (in the loaded map's frame) and writes the
    posed frames at the end. Frames the busy node skips (live input) are not posed."""
    name = "tracker"
    update_sources = ()                 # no loop closer runs: the map is read-only

    def __init__(self, cfg: SlamConfig, intrinsics, session: Session):
        self.loc = Localizer(cfg, intrinsics, session)
        self.tracker = self.loc         # what the node reads: see Localizer's tracker surface
        self.intrinsics = intrinsics
        self.finalized = False

    def on_frame(self, frame):
        T = self.loc.track(frame)
        pose = T if T is not None else self.loc.predict()
        return TrackStep(int(frame.index), float(frame.timestamp), False, None, pose,
                         lost=T is None, initialized=self.loc.initialized), Outbox()

    def on_update(self, ev):
        return Outbox()

    def on_final(self, node, info):
        return self.on_update(None)

    def finalize(self):
        self.finalized = True
        return Outbox(final={"last_seq": 0, "keyframes": 0})

    @property
    def complete(self) -> bool:
        return self.finalized
