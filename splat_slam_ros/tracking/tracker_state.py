"""Crash-safe checkpoints of a :class:`~splat_slam_ros.tracking.tracker.Tracker` (resume after
``kill -9``), kept in a :class:`~splat_slam_ros.io.keyframe_store.KeyframeStore`.

Written incrementally after each tracker step that changed the pose graph (a keyframe, a
local BA, an applied loop closure / global BA update); frames tracked in between are
re-tracked after a restart (the input rewinds to :attr:`TrackerCheckpoint.resume_stamp`).
Each checkpoint writes only what changed since the previous one:

  ``tstate``       poses of all keyframes (the BA variables ``omega`` of Eq. 1), motion state
                   (last pose, constant-velocity model, last flow) - small, rewritten
  ``tkfp<n>``      disparity + flow confidence of the keyframes whose disparity tensor was
                   replaced since the previous checkpoint (local BA, loop closure and global BA
                   write new tensors), all in one file; the manifest says which file holds
                   each keyframe's newest version, and a file no keyframe refers to is deleted
  ``timg<k>``      the image handed on with a window keyframe (mapping size; prepared as the
                   flow front-end input again on restore, resized to the BA grid x
                   ba_downsample), deleted once the keyframe leaves the window
  ``tedgep<n>``    the flow edges of the window's factor graph (target + weight, Eq. 1) added
                   since the previous checkpoint, in one file, deleted once all its edges were
                   pruned; ages and kinds live in the manifest
  ``trec<n>``      the frame records (trajectory filler) since the previous checkpoint

One file per checkpoint for each kind (not one per keyframe or edge): every file costs an
fsync, and a loop-closure update moves dozens of keyframes.

Metadata (window, published ids, next keyframe id, update numbers, ...) goes into the same
atomic manifest commit, so a checkpoint is either complete or absent. A restored tracker
continues with new keyframe ids and update numbers, never reusing published ones.
"""
from __future__ import annotations

import itertools
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
import torch

from splat_slam_ros.imaging import flow_input
from splat_slam_ros.io.keyframe_store import KeyframeStore
from splat_slam_ros.tracking.keyframe_set import KEYFRAME_CAUSES, KeyframeState
from splat_slam_ros.tracking.trajectory_filler import FrameRecord
from splat_slam_ros.types import Intrinsics, KeyframeData

_NAN44 = np.full((4, 4), np.nan)


class TrackerStateError(RuntimeError):
    """A tracker checkpoint does not fit the tracker it should restore."""


def intrinsics_to_list(k: Intrinsics) -> list:
    return [k.fx, k.fy, k.cx, k.cy, k.width, k.height, k.distortion_model,
            [float(x) for x in (k.distortion or [])]]


def intrinsics_from_list(v: Sequence) -> Intrinsics:
    return Intrinsics(float(v[0]), float(v[1]), float(v[2]), float(v[3]), int(v[4]), int(v[5]),
                      str(v[6]), [float(x) for x in v[7]])


def _records_arrays(recs: List[FrameRecord], h: int, w: int) -> Dict[str, np.ndarray]:
    n = len(recs)
    flow = np.zeros((n, h, w, 2), np.float16)
    weight = np.zeros((n, h, w, 2), np.float16)
    has_flow = np.zeros(n, bool)
    flow2, weight2 = np.zeros_like(flow), np.zeros_like(weight)   # next keyframe -> frame
    has_flow2 = np.zeros(n, bool)
    for i, r in enumerate(recs):
        if r.flow is not None and r.weight is not None:
            flow[i] = r.flow.cpu().numpy()
            weight[i] = r.weight.cpu().numpy()
            has_flow[i] = True
        if r.ref2_kf is not None and r.flow2 is not None and r.weight2 is not None:
            flow2[i] = r.flow2.cpu().numpy()
            weight2[i] = r.weight2.cpu().numpy()
            has_flow2[i] = True
    opt = lambda x: -1 if x is None else int(x)           # noqa: E731
    pose = lambda p: _NAN44 if p is None else np.asarray(p, np.float64)   # noqa: E731
    return {"index": np.array([r.index for r in recs], np.int64),
            "timestamp": np.array([r.timestamp for r in recs], np.float64),
            "kf_id": np.array([opt(r.kf_id) for r in recs], np.int64),
            "ref_kf": np.array([opt(r.ref_kf) for r in recs], np.int64),
            "rel_pose": np.stack([pose(r.rel_pose) for r in recs]) if n else np.zeros((0, 4, 4)),
            "online_pose": (np.stack([pose(r.online_pose) for r in recs]) if n
                            else np.zeros((0, 4, 4))),
            "ref_scale": np.array([r.ref_scale for r in recs], np.float64),
            "lost": np.array([r.lost for r in recs], bool),
            "skipped": np.array([r.skipped for r in recs], bool),
            "has_flow": has_flow, "flow": flow, "weight": weight,
            "ref2_kf": np.array([opt(r.ref2_kf) for r in recs], np.int64),
            "has_flow2": has_flow2, "flow2": flow2, "weight2": weight2}


def _records_from(a: Dict[str, np.ndarray]) -> List[FrameRecord]:
    out = []
    for i in range(len(a["index"])):
        opt = lambda x: None if int(x) < 0 else int(x)     # noqa: E731
        pose = lambda p: None if np.isnan(p).any() else p.copy()   # noqa: E731
        flow = weight = None
        if a["has_flow"][i]:
            flow = torch.from_numpy(a["flow"][i].copy())
            weight = torch.from_numpy(a["weight"][i].copy())
        ref2 = flow2 = weight2 = None
        if "has_flow2" in a and a["has_flow2"][i]:
            ref2 = opt(a["ref2_kf"][i])
            flow2 = torch.from_numpy(a["flow2"][i].copy())
            weight2 = torch.from_numpy(a["weight2"][i].copy())
        out.append(FrameRecord(int(a["index"][i]), float(a["timestamp"][i]),
                               kf_id=opt(a["kf_id"][i]), ref_kf=opt(a["ref_kf"][i]),
                               rel_pose=pose(a["rel_pose"][i]), ref_scale=float(a["ref_scale"][i]),
                               flow=flow, weight=weight, lost=bool(a["lost"][i]),
                               online_pose=pose(a["online_pose"][i]),
                               ref2_kf=ref2, flow2=flow2, weight2=weight2,
                               skipped=bool(a["skipped"][i]) if "skipped" in a else False))
    return out


def _disp_arrays(ks: KeyframeState) -> Dict[str, np.ndarray]:
    return {"disp": ks.disp.cpu().numpy(),
            "conf": (ks.conf if ks.conf is not None else torch.ones_like(ks.disp)).cpu().numpy(),
            "info": np.array([ks.frame_index, ks.timestamp, KEYFRAME_CAUSES.index(ks.cause)])}


def _cause(info: np.ndarray) -> str:
    """A restored keyframe's cause (a checkpoint of an earlier version has none: counted in
    the rate bound, as most keyframes are)."""
    return KEYFRAME_CAUSES[int(info[2])] if len(info) > 2 else "threshold"


def _edge_arrays(val) -> Dict[str, np.ndarray]:
    return {"target": val[0].cpu().numpy(), "weight": val[1].cpu().numpy()}


class _Packs:
    """Items (keyframes, edges) written together, one store record per checkpoint: the
    manifest maps each item to the record holding its newest version, and a record no item
    refers to any more is deleted with the commit that stops referring to it. A record whose
    items are mostly newer elsewhere has its remaining items written again (disk stays
    O(items), not O(items x checkpoints))."""

    def __init__(self, prefix: str, state: Optional[dict]):
        state = state or {}
        self.prefix = prefix
        self.of: Dict[str, str] = dict(state.get("of", {}))       # item key -> record name
        self.size: Dict[str, int] = {k: int(v) for k, v in state.get("size", {}).items()}
        nums = [int(v[len(prefix):]) for v in self.size]
        self.n = max(nums) + 1 if nums else 0
        self._cache: Dict[str, Dict[str, np.ndarray]] = {}

    def state(self) -> dict:
        return {"of": dict(self.of), "size": dict(self.size)}

    def stale(self) -> List[str]:
        """Items of records that less than half of their items still refer to."""
        live: Dict[str, List[str]] = {}
        for key, name in self.of.items():
            live.setdefault(name, []).append(key)
        return [key for name, keys in live.items() if 2 * len(keys) < self.size.get(name, 0)
                for key in keys]

    def write(self, st: KeyframeStore, staged: dict, items: Dict[str, Dict[str, np.ndarray]],
              current: Callable[[str], Dict[str, np.ndarray]]) -> None:
        """Stage one record with the changed ``items`` (key -> arrays) and the unchanged
        items (``current(key)``) of records this leaves mostly stale; delete dead records."""
        name = f"{self.prefix}{self.n}"
        self.of.update({key: name for key in items})
        for key in self.stale():
            items[key] = current(key)
            self.of[key] = name
        if items:
            self.n += 1
            keys = list(items)                   # one stacked array per field (few zip members)
            staged[name] = st.stage(name, keys=np.array(keys), **{
                f: np.stack([items[k][f] for k in keys]) for f in items[keys[0]]})
            self.size[name] = len(items)
        live = set(self.of.values())
        for dead in [n for n in self.size if n not in live]:     # nothing refers to it
            staged[dead] = None
            del self.size[dead]

    def drop(self, key: str) -> None:
        self.of.pop(key, None)

    def read(self, st: KeyframeStore, key: str) -> Dict[str, np.ndarray]:
        name = self.of.get(key)
        if name is None or not st.has(name):
            raise TrackerStateError(f"tracker checkpoint in {st.dir} misses the record of {key}")
        if name not in self._cache:
            rec = st.get(name)
            rec["_row"] = {str(k): i for i, k in enumerate(rec.pop("keys").tolist())}
            self._cache[name] = rec
        rec = self._cache[name]
        if key not in rec["_row"]:
            raise TrackerStateError(f"tracker checkpoint in {st.dir}: {name} lacks {key}")
        i = rec["_row"][key]
        return {f: v[i] for f, v in rec.items() if f != "_row"}

    def done_reading(self) -> None:
        self._cache.clear()


class TrackerCheckpoint:
    """Incremental save / restore of a Tracker's state in ``store`` (see module doc)."""

    def __init__(self, store: KeyframeStore):
        self.store = store
        self._disp_saved: Dict[int, torch.Tensor] = {}    # kf -> disparity tensor last written
        self._edges_saved: Dict[tuple, tuple] = {}        # (i, j) -> (target, weight) written
        self._n_records = int(store.meta.get("trk_records", 0))
        self._chunks = int(store.meta.get("trk_chunks", 0))
        self._disps = _Packs("tkfp", store.meta.get("trk_disp_records"))
        self._edges = _Packs("tedgep", store.meta.get("trk_edge_records"))

    @property
    def exists(self) -> bool:
        return "trk_next_kf" in self.store.meta

    @property
    def meta(self) -> dict:
        return self.store.meta

    @property
    def resume_stamp(self) -> Optional[float]:
        """Timestamp of the newest frame the checkpoint holds (the input resumes after it)."""
        return self.store.meta.get("trk_last_stamp")

    # ------------------------------------------------------------ save
    def save(self, trk, published: Sequence[KeyframeData] = (), meta: Optional[dict] = None
             ) -> None:
        """Checkpoint ``trk``: ``published`` are the keyframes handed on since the last one
        (their images are what a restored window prepares its flow inputs from)."""
        st, staged = self.store, {}
        ids = trk.kfs.ids
        for kd in published:                                  # window images, written once
            k = int(kd.kf_id)
            if k in trk.kfs and trk.kfs[k].prep is not None and not st.has(f"timg{k}"):
                staged[f"timg{k}"] = st.stage(f"timg{k}", image=np.asarray(kd.image, np.uint8))
        for k in list(self._disp_saved):
            if k not in trk.kfs:                              # dropped candidate / reset
                self._disps.drop(str(k))
                del self._disp_saved[k]
        disps = {}
        for k in ids:
            ks = trk.kfs[k]
            if ks.prep is None and st.has(f"timg{k}"):
                staged[f"timg{k}"] = None
            if self._disp_saved.get(k) is not ks.disp:
                disps[str(k)] = _disp_arrays(ks)
                self._disp_saved[k] = ks.disp
        self._disps.write(st, staged, disps, lambda key: _disp_arrays(trk.kfs[int(key)]))
        edges = trk.graph.edges
        for e in [e for e in self._edges_saved if e not in edges]:
            self._edges.drop(f"{e[0]}_{e[1]}")
            del self._edges_saved[e]
        added = {}
        for e, val in edges.items():
            if self._edges_saved.get(e) is not val:
                added[f"{e[0]}_{e[1]}"] = _edge_arrays(val)
                self._edges_saved[e] = val
        self._edges.write(st, staged, added, lambda key: _edge_arrays(
            edges[tuple(int(x) for x in key.split("_"))]))
        new = trk.records[self._n_records:]
        if new:
            staged[f"trec{self._chunks}"] = st.stage(f"trec{self._chunks}",
                                                     **_records_arrays(new, trk.h, trk.w))
            self._chunks += 1
            self._n_records = len(trk.records)
        lf = trk._last_flow
        staged["tstate"] = st.stage(
            "tstate", ids=np.array(ids, np.int64),
            poses=(torch.stack([trk.kfs[k].pose for k in ids]).cpu().numpy() if ids
                   else np.zeros((0, 4, 4))),
            last_pose=trk.last_pose.cpu().numpy(), velocity=trk.velocity.cpu().numpy(),
            last_flow=(lf[1].cpu().numpy() if lf is not None else np.zeros((0,), np.float32)))
        st.commit(staged, dict(meta or {}, **self._meta(trk, lf)))

    def _meta(self, trk, lf) -> dict:
        return {"trk_next_kf": int(trk.next_kf), "trk_window": [int(k) for k in trk.window],
                "trk_published": sorted(int(k) for k in trk.published),
                "trk_initialized": bool(trk.initialized), "trk_lost_count": int(trk.lost_count),
                "trk_n_lost": int(trk.n_lost), "trk_records": self._n_records,
                # frames skipped (live, busy) and how many of them bridges tracked after all:
                # frames_skipped.txt lists every skip of the run, also after a restart
                "trk_n_skipped": int(trk.n_skipped), "trk_n_bridged": int(trk.n_bridged),
                "trk_skipped_at": [[int(i), float(t)] for i, t in trk.skipped_at],
                "trk_segments": int(trk.n_segments),       # a new segment's start (warm-up)
                "trk_anchor": None if trk._anchor is None else
                [trk._anchor[0].cpu().numpy().tolist(), float(trk._anchor[1])],
                "trk_chunks": self._chunks,
                "trk_last_stamp": (float(trk.records[-1].timestamp) if trk.records else None),
                "trk_motion_typical": trk.motion._typical,
                "trk_last_flow_ref": None if lf is None else int(lf[0]),
                "trk_disp_records": self._disps.state(),
                "trk_edge_records": self._edges.state(),
                "trk_edges": {f"{i}_{j}": [int(trk.graph.age[(i, j)]), trk.graph.kind[(i, j)]]
                              for (i, j) in trk.graph.edges}}

    # ------------------------------------------------------------ restore
    def restore(self, trk, next_seq: int) -> None:
        """Put the checkpointed state into a freshly built ``trk``; its next update gets
        number ``next_seq``."""
        st, m = self.store, self.store.meta
        s = st.get("tstate")
        dev = trk.device
        trk.kfs.clear()
        for n, k in enumerate(int(x) for x in s["ids"]):
            r = self._disps.read(st, str(k))
            if r["disp"].shape != (trk.h, trk.w):
                raise TrackerStateError(f"tracker checkpoint in {st.dir} has {r['disp'].shape} "
                                        f"disparities, the tracker runs at {(trk.h, trk.w)}")
            prep = None
            if st.has(f"timg{k}"):
                prep = trk.flow.prepare(flow_input(st.get(f"timg{k}")["image"], (trk.h, trk.w),
                                                   trk.tc.ba_downsample))
            ks = trk.kfs.add(k, KeyframeState(
                torch.as_tensor(s["poses"][n], dtype=torch.float64, device=dev),
                torch.as_tensor(r["disp"], dtype=torch.float32, device=dev),
                int(r["info"][0]), float(r["info"][1]), prep=prep,
                conf=torch.as_tensor(r["conf"], dtype=torch.float32, device=dev),
                cause=_cause(r["info"])))
            self._disp_saved[k] = ks.disp
        for key, (age, kind) in m.get("trk_edges", {}).items():
            i, j = (int(x) for x in key.split("_"))
            e = self._edges.read(st, key)
            val = (torch.as_tensor(e["target"], device=dev), torch.as_tensor(e["weight"], device=dev))
            trk.graph.edges[(i, j)] = val
            trk.graph.age[(i, j)] = int(age)
            trk.graph.kind[(i, j)] = str(kind)
            self._edges_saved[(i, j)] = val
        recs: List[FrameRecord] = []
        for c in range(int(m.get("trk_chunks", 0))):
            if st.has(f"trec{c}"):
                recs += _records_from(st.get(f"trec{c}"))
        for r in recs[:max(len(recs) - 1 - trk.tc.max_stored_flows, 0)]:
            r.flow = r.weight = r.flow2 = r.weight2 = None   # the tracker's memory bound
        trk.records = recs
        trk.window = [int(k) for k in m["trk_window"]]
        trk.published = {int(k) for k in m["trk_published"]}
        trk.next_kf = int(m["trk_next_kf"])
        trk.initialized = bool(m["trk_initialized"])
        trk.lost_count, trk.n_lost = int(m["trk_lost_count"]), int(m["trk_n_lost"])
        trk.n_skipped, trk.n_bridged = (int(m.get(k, 0)) for k in ("trk_n_skipped",
                                                                     "trk_n_bridged"))
        trk.skipped_at = [(int(i), float(t)) for i, t in m.get("trk_skipped_at", [])]
        trk.n_segments, a = int(m.get("trk_segments", 1)), m.get("trk_anchor")
        trk._anchor = None if a is None else (
            torch.as_tensor(a[0], dtype=torch.float64, device=dev), float(a[1]))
        trk.motion._typical = m.get("trk_motion_typical")
        trk.last_pose = torch.as_tensor(s["last_pose"], dtype=torch.float64, device=dev)
        trk.velocity = torch.as_tensor(s["velocity"], dtype=torch.float64, device=dev)
        ref = m.get("trk_last_flow_ref")
        trk._last_flow = None if ref is None or s["last_flow"].size == 0 else (
            int(ref), torch.as_tensor(s["last_flow"], device=dev))
        trk._seq = itertools.count(int(next_seq))
        self._n_records = len(recs)
        self._disps.done_reading()
        self._edges.done_reading()
