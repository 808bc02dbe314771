"""The mapper stage's endpoint of the update protocol (splat_slam_ros/roles.py), ROS-free.

:class:`MapperRole` takes keyframes and their proxy-depth revisions, keeps which keyframe
ids it consumed (mapped or not), which revision of each it took and what still waits, maps
a keyframe once both its image and a depth arrived (mapping policy: revisits, merges and
held keyframes, mapping/revisit.py), deforms the map with every newer revision, persists the
map with exactly the inputs it reflects (mapping/persistence.py) and becomes final (final
refinement) once it took every revision of the depth stage's final digest.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional

from splat_slam_ros.config import SlamConfig
from splat_slam_ros.evaluation.rendering import evaluate_keyframes
from splat_slam_ros.io.keyframe_store import KeyframeStore
from splat_slam_ros.io.trajectory_io import write_tum
from splat_slam_ros.mapping.persistence import commit_map, resume_map
from splat_slam_ros.mapping.revisit import (MIN_DEPTH_FRACTION, anchoring_fraction, merge_pair,
                                            revisit_reason, waits_for_loop_closure)
from splat_slam_ros.roles import Outbox, ack
from splat_slam_ros.types import LOOP_SEQ_START, Intrinsics, KeyframeData, ProxyDepth, UpdateEvent


def write_mesh(mapper, cfg: SlamConfig, directory: Path, metrics: dict, progress: bool = False,
               renders=None) -> None:
    """``map_mesh.ply`` when ``mapping.mesh`` (its info in ``metrics["mesh"]``); ``renders``:
    :meth:`Mapper.keyframe_renders` when already made."""
    if cfg.mapping.mesh:
        # Open3D takes 1.5 s to import: loaded when a mesh is written, not by every stage
        from splat_slam_ros.mapping.mesh import map_mesh_output
        metrics["mesh"] = map_mesh_output(mapper, Path(directory) / "map_mesh.ply", progress,
                                          renders)


def write_map_outputs(mapper, cfg: SlamConfig, directory: Path, progress: bool = False) -> dict:
    """map.ply, map_mesh.ply (``mapping.mesh``), renders/ and the map's metrics of a run (the
    in-process pipeline and the mapper node): each keyframe is rendered once for the mesh and
    the metrics."""
    d = Path(directory)
    mapper.save_ply(d / "map.ply")
    renders = mapper.keyframe_renders()
    metrics: dict = {}
    write_mesh(mapper, cfg, d, metrics, progress, renders)
    metrics.update(evaluate_keyframes(mapper, d / "renders", renders=renders))
    metrics["map"] = mapper.stats()
    return metrics


class MapperRole:
    """Keyframes + proxy depths -> Gaussian map (Eq. 11), deformed by every newer depth (§3.2)."""
    name = "mapper"
    update_sources = ("tracker", "loop")

    def __init__(self, cfg: SlamConfig, store: Optional[KeyframeStore] = None,
                 snapshot_every: int = 1):
        self.cfg = cfg
        self.mapper: Optional["Mapper"] = None   # noqa: F821 (mapping.mapper, imported in _map)
        self.intr: Optional[Intrinsics] = None
        self.pending_kf: Dict[int, KeyframeData] = {}
        self.pending_depth: Dict[int, ProxyDepth] = {}
        self.offered: Dict[int, bool] = {}          # kf_id -> mapped?
        self.taken: Dict[int, int] = {}             # kf_id -> last revision taken
        self.last_update_seq = 0
        self.digest: Optional[Dict[int, int]] = None
        self.t_input_end: Optional[float] = None    # epoch s the input ended (input_ended)
        self.finalized = False
        self.dirty: set = set()                     # keyframes whose depth changed
        self.held: set = set()                      # acked, waiting for a depth (see _try_map)
        self.gone: set = set()                      # merged since the last snapshot
        self.loop_seen = False                      # a loop closer's updates arrive
        self.settled: set = set()                   # keyframes loop closure has corrected
        self.newest_kf = -1
        self.background_mark = 0                    # Mapper.background_iters at the last keyframe
        self.input_waiting: Optional[Callable[[], bool]] = None  # the node's queue (live)
        self.snapshot_every = max(1, int(snapshot_every))
        self.n_since_snapshot = 0
        self.timings: Dict[str, float] = {"mapping": 0.0, "deformation": 0.0, "refine": 0.0}
        self.store = store
        if store is not None and store.exists:
            self._resume()

    # ------------------------------------------------------------ persistence
    def _resume(self) -> None:
        meta = self.store.meta
        self.offered = {int(k): bool(v) for k, v in meta.get("offered", {}).items()}
        self.taken = {int(k): int(v) for k, v in meta.get("taken", {}).items()}
        self.last_update_seq = int(meta.get("last_update_seq", 0))
        self.intr, self.mapper = resume_map(self.store, self.cfg)

    def snapshot(self) -> None:
        """Commit the map with exactly the inputs it reflects (offered, taken revisions)."""
        if self.store is None or self.mapper is None:
            return
        commit_map(self.store, self.mapper, self.intr, self.dirty, self.gone, self.offered,
                   self.taken, self.last_update_seq)
        self.n_since_snapshot = 0

    def restore(self, mapper: "Mapper", intr: Intrinsics) -> None:  # noqa: F821
        """Start from a loaded map (extend runs): its keyframes count as mapped."""
        self.mapper, self.intr = mapper, intr
        self.offered = {int(k): True for k in mapper.keyframes}
        self.dirty = set(self.offered)
        self.snapshot()

    def reset(self) -> None:
        """Drop the map and everything it consumed; the next keyframes start a new map."""
        self.mapper = None
        for d in (self.pending_kf, self.pending_depth, self.offered, self.taken, self.dirty,
                  self.gone, self.settled):
            d.clear()
        if self.store is not None:
            self.store.clear()

    def save(self, directory: Path, final: bool = False) -> dict:
        """map.ply (+ map_mesh.ply), renders/ and metrics of the map now (``final``: mapper_metrics.json, the
        tracker writes the run's trajectories; else also trajectory_keyframes + metrics.json)."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        if self.mapper is None:
            return {}
        metrics = write_map_outputs(self.mapper, self.cfg, d)
        if not final:
            write_tum(d / "trajectory_keyframes.txt", *self.mapper.keyframe_trajectory())
        (d / ("mapper_metrics.json" if final else "metrics.json")).write_text(
            json.dumps(metrics, indent=2, default=str))
        return metrics

    # ------------------------------------------------------------ inputs
    def on_keyframe(self, kf: KeyframeData) -> Outbox:
        if kf.kf_id in self.offered:        # consumed before a restart: ack again (LoopRole)
            return Outbox(acks=[ack(kf)])
        if kf.kf_id in self.pending_kf:
            return Outbox()
        self.newest_kf = max(self.newest_kf, int(kf.kf_id))
        self.pending_kf[kf.kf_id] = kf
        return self._try_map()

    def on_proxy_depth(self, pd: ProxyDepth) -> Outbox:
        k = int(pd.kf_id)
        if pd.revision <= self.taken.get(k, -1):        # a replay
            return Outbox()
        if int(pd.update_seq) >= LOOP_SEQ_START:        # made after a loop-closure update
            self.loop_seen = True
            self.settled.add(k)
        if self.mapper is not None and k in self.mapper.keyframes:
            # Map deformation (§3.2): the keyframe's Gaussians follow its new pose and depth
            t0 = time.perf_counter()
            self.mapper.apply_update(k, pd.pose, pd.depth,
                                     pd.depth_weight(self.cfg.mapping.ba_depth_weight))
            self.taken[k] = int(pd.revision)
            self.dirty.add(k)
            self._merge_revisit(k, pd)
            self.timings["deformation"] += time.perf_counter() - t0
            self.last_update_seq = max(self.last_update_seq, int(pd.update_seq))
            out = Outbox()
        elif k in self.offered:                         # consumed, not mapped (redundant view)
            self.taken[k] = int(pd.revision)
            out = Outbox()
        else:
            old = self.pending_depth.get(k)
            if old is None or pd.revision > old.revision:
                self.pending_depth[k] = pd
            out = self._try_map()
        return out.extend(self._check_final())

    def on_update(self, ev: UpdateEvent) -> Outbox:  # deformation: the ProxyDepth stream
        self.last_update_seq = max(self.last_update_seq, int(ev.seq))
        self.loop_seen |= int(ev.seq) >= LOOP_SEQ_START
        return Outbox()

    def input_ended(self, t: float) -> None:
        """The input ended at epoch second ``t``: the player's end_of_stream event or, at the
        latest, the depth stage's final digest. ``mapping.final_deadline_s`` counts from the
        earliest (the depth stage, behind on live input, sent its digest seconds later)."""
        self.t_input_end = t if self.t_input_end is None else min(self.t_input_end, t)

    def on_final(self, node: str, info: dict) -> Outbox:
        if node == "depth":
            self.digest = {int(k): int(v) for k, v in (info.get("digest") or {}).items()}
            # sent then (graph event "t"), maybe queued here since
            self.input_ended(float(info.get("t") or time.time()))
            return self._try_map()                  # held keyframes: mapped with what is there
        return Outbox()

    # ------------------------------------------------------------ work
    def _try_map(self) -> Outbox:
        """Map every keyframe that has its depth. A proxy depth with (almost) no valid pixel
        (revision 0 of a keyframe that had no views yet: the first of a small warm-up batch)
        would anchor no Gaussians and leave the map without a scene depth: such a keyframe
        is acked (lockstep goes on) and held until a revision with depth or the final digest.
        In revisit mode a keyframe is also held until loop closure has corrected its pose
        (mapping/revisit.py: ``waits_for_loop_closure``)."""
        out = Outbox()
        for k in sorted(self.pending_kf):
            if k not in self.pending_depth:
                continue
            pd = self.pending_depth[k]
            thin = anchoring_fraction(pd, self.cfg.mapping.ba_depth_weight) < MIN_DEPTH_FRACTION
            if self.digest is None and (thin or waits_for_loop_closure(
                    self.cfg.mapping, self.mapper, k, self.loop_seen, self.settled,
                    self.newest_kf)):
                if k not in self.held:
                    self.held.add(k)
                    out.acks.append(ack(self.pending_kf[k]))
                continue
            out.extend(self._map(self.pending_kf.pop(k), self.pending_depth.pop(k)))
        return out.extend(self._check_final())

    def _merge_revisit(self, k: int, pd: ProxyDepth) -> None:
        """Keyframe ``k`` (mapped) moved: when it now sees what another mapped keyframe sees,
        the newer of the two is merged into the older (mapping/revisit.py: ``merge_pair``)."""
        pair = merge_pair(self.cfg.mapping, self.mapper, k, pd)
        if pair is None:
            return
        drop, keep = pair
        self.mapper.merge_keyframe(drop, keep)
        self.offered[drop] = False                      # later revisions: taken, not applied
        self.dirty.discard(drop)
        self.gone.add(drop)

    def _map(self, kf: KeyframeData, pd: ProxyDepth) -> Outbox:
        t0 = time.perf_counter()
        if self.mapper is None:
            # imported here: the mapper (and scipy) is ~30 MB a tracking-only run never needs
            from splat_slam_ros.mapping.mapper import Mapper
            self.intr = kf.intrinsics
            self.mapper = Mapper(self.cfg, kf.intrinsics)
        revisit = revisit_reason(self.cfg.mapping, self.mapper, pd)
        if revisit is not None:             # consumed, not mapped (bounded map)
            st = dict(self.mapper.stats(), kf_id=int(kf.kf_id), mapped=False, reason=revisit)
        else:
            # after the input ended, keyframes still queued get no step of their own while
            # more wait: the final refinement (one view a step) has the time instead
            st = self.mapper.add_keyframe(kf.kf_id, kf.image, pd.pose, pd.depth,
                                          pd.depth_weight(self.cfg.mapping.ba_depth_weight),
                                          timestamp=kf.timestamp, yield_to=self.input_waiting,
                                          min_steps=0 if self.t_input_end is not None else None)
        self.timings["mapping"] += time.perf_counter() - t0
        mapped = bool(st.get("mapped"))
        self.background_mark = self.mapper.background_iters     # a new allowance
        self.offered[kf.kf_id] = mapped
        self.taken[kf.kf_id] = int(pd.revision)
        if mapped:
            self.dirty.add(kf.kf_id)
        self.n_since_snapshot += 1
        if self.n_since_snapshot >= self.snapshot_every:
            self.snapshot()
        info = dict(st, kf_id=int(kf.kf_id), pose=pd.pose, timestamp=float(kf.timestamp),
                    n_mapped=sum(self.offered.values()))
        held = kf.kf_id in self.held
        self.held.discard(kf.kf_id)
        return Outbox(acks=[] if held else [ack(kf)], mapped=[info])

    def wants_background(self) -> bool:
        """Live input (``mapping.time_budget``): steps left of ``mapping.background_steps``
        since the last mapped keyframe, until the final refinement. The node runs them
        (:meth:`background`) while no input waits, and sets ``input_waiting``: input that
        arrives cuts a keyframe's or the background's steps."""
        m = self.mapper
        return (self.cfg.mapping.time_budget and m is not None and not self.finalized and
                m.background_iters - self.background_mark < self.cfg.mapping.background_steps)

    def background(self, steps: int = 4) -> None:
        self.mapper.background(steps, self.input_waiting)

    def lacking(self) -> List[int]:
        """Keyframes whose revision in the depth stage's final digest this stage has not taken
        (empty before the digest and once final). A node asks the depth stage to send them
        again: a DDS history can drop a message that a burst of newer ones overtook."""
        if self.digest is None or self.finalized:
            return []
        return [k for k, rev in sorted(self.digest.items()) if self.taken.get(k, -1) < rev]

    def _check_final(self) -> Outbox:
        if self.digest is None or self.finalized or self.lacking():
            return Outbox()
        self.finalized = True
        info: dict = {"keyframes": sum(self.offered.values())}
        if self.mapper is not None:
            t0 = time.perf_counter()
            # mapping.final_deadline_s counts from the input's end, not from now
            info["refine"] = self.mapper.final_refine(
                since_input_s=0.0 if self.t_input_end is None else time.time() - self.t_input_end)
            self.timings["refine"] += time.perf_counter() - t0
            self.snapshot()
        return Outbox(final=info)
