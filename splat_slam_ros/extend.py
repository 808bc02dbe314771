"""Extend runs (``splat-slam-run SEQ --out OUT2 --load-map OUT``): a loaded map grows.

The session that the full run in ``OUT`` saved (``OUT/session/``: keyframes, and
``map_state.npz``, the mapper's state) is loaded and checked before any frame. The run is
the in-process pipeline (:mod:`splat_slam_ros.pipeline`) with two stages started from the
session instead of empty:

- the tracker (:class:`~splat_slam_ros.tracking.relocalise.ExtendTracker`) holds the loaded
  keyframes, starts lost and relocalises; from there it tracks and makes keyframes in the
  loaded map's frame and scale (local BA keeps the loaded keyframes fixed);
- the mapper holds the loaded Gaussians and mapped keyframes (their images, proxy depths,
  exposures, the mapping window): new keyframes join its window, its optimisation keeps
  sampling the loaded keyframes' views, and the final refinement runs over all of them.

So that a revisited place is not mapped twice, unless the configuration sets them the run
uses ``mapping.revisit_cull_deg`` 10 (a new keyframe next to a mapped one with the same
viewing direction, or whose view the map covers to ``mapping.revisit_coverage``, is not
mapped) and ``mapping.seed_uncovered`` (new Gaussians only where the loaded map does not
explain the view). The loop closer holds the loaded keyframes too, fixed in every BA: a new
keyframe that sees a loaded one's view again closes a loop that pulls the new part of the
map onto the loaded one (never the reverse). Proxy depth works on the new keyframes.

Outputs in ``OUT2`` as for a full run: trajectory_full.txt (the frames posed from the first
relocalisation on, in the loaded map's frame), trajectory_keyframes.txt (every keyframe of
the extended map, loaded and new), map.ply, metrics.json (``extend``: the loaded session,
keyframes and Gaussians before and after, the relocalisation), and a session of the
extended map (it can be extended again).
"""
from __future__ import annotations

from typing import Dict, List

from splat_slam_ros.config import MappingConfig, SlamConfig
from splat_slam_ros.coordinator import Coordinator
from splat_slam_ros.io.session import Session, loop_graph, map_state
from splat_slam_ros.mapping.persistence import restore_map_state
from splat_slam_ros.tracking.relocalise import ExtendTracker
from splat_slam_ros.types import Intrinsics

# mapping settings of an extend run, unless the configuration sets them (module docstring)
EXTEND_MAPPING = {"revisit_cull_deg": 10.0, "seed_uncovered": True}


def extend_config(cfg: SlamConfig, overrides: Dict[str, object]) -> List[str]:
    """Apply :data:`EXTEND_MAPPING` where ``cfg`` has the default and ``overrides`` (the
    command line's ``--set``) does not name the key; returns 'key value' of each applied."""
    defaults, notes = MappingConfig(), []
    for key, value in EXTEND_MAPPING.items():
        if getattr(cfg.mapping, key) == getattr(defaults, key) and \
                f"mapping.{key}" not in overrides:
            setattr(cfg.mapping, key, value)
            notes.append(f"mapping.{key} {value}")
    return notes


def extend_coordinator(cfg: SlamConfig, intrinsics: Intrinsics, session: Session) -> Coordinator:
    """A :class:`Coordinator` whose tracker and mapper continue ``session`` (SessionError
    before any frame when it has no map state, or another camera or mapping size)."""
    arrays, meta, map_cam = map_state(session)
    co = Coordinator(cfg, intrinsics, mapping=True, make_tracker=lambda flow: ExtendTracker(
        cfg, intrinsics, session, flow_predictor=flow))
    trk = co.tracker.tracker                # (checks the camera and the mapping size)
    co.mapper.restore(restore_map_state(arrays, meta, cfg, map_cam), map_cam)
    if co.loop is not None:             # loops from new keyframes to loaded ones (fixed)
        co.loop.add_fixed(trk.loaded_keyframe_data())
        co.loop.loop.restore_graph_summary(loop_graph(session))
    co.loaded = {"keyframes": len(trk.loaded_ids),
                 "mapped_keyframes": len(co.mapper.mapper.keyframes),
                 "gaussians": len(co.mapper.mapper.map)}
    return co


def extend_metrics(co: Coordinator, session: Session) -> dict:
    """metrics.json ``extend``: the loaded session, what it held and what the run added."""
    trk = co.tracker.tracker
    mp = co.mapper.mapper
    lc = co.loop.loop if co.loop is not None else None
    loops = lc.loop_stats() if lc is not None else {"loop_edges": 0, "loop_edges_to_loaded": 0}
    return {"session": str(session.path.parent), "loaded": co.loaded,
            "loop_edges": loops["loop_edges"],
            "loop_edges_to_loaded": loops["loop_edges_to_loaded"],
            "new_keyframes": len(trk.new_keyframe_ids()),
            "mapped_keyframes": len(mp.keyframes), "gaussians": len(mp.map),
            "relocalised_frame": trk.relocalised_frame,
            "relocalised_keyframe": trk.relocalised_keyframe,
            "relocalisations": trk.n_relocalisations,
            "frames_before_relocalised": trk.n_unplaced}


def never_relocalised(frames: int, keyframes: int) -> str:
    return (f"never relocalised in the loaded map: none of the {frames} frames matched any of "
            f"the session's {keyframes} keyframes (another place, or too little overlap with "
            f"the run that made it)")
