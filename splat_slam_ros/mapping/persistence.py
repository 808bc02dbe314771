"""A mapper's state as arrays + JSON metadata, and the mapper rebuilt from them.

:func:`map_state` / :func:`load_map_state` turn the Gaussians with their bookkeeping, the
mapped keyframes (pose, exposure), the window with its visibility sets and the counters
into arrays + metadata and back; keyframe images and proxy depths are stored per keyframe
by the caller (:func:`keyframe_depth`), so a snapshot costs O(map). :func:`restore_mapper`
builds a :class:`~splat_slam_ros.mapping.mapper.Mapper` from them: the mapper node's
crash-safe store (io/keyframe_store.py: :func:`commit_map` / :func:`resume_map`) and the
saved session's ``map_state.npz`` (io/session.py: :func:`mapper_arrays` /
:func:`restore_map_state`) hold these arrays.
"""
from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import numpy as np
import torch

from splat_slam_ros.io.session import KEYFRAME_DEPTH
from splat_slam_ros.mapping.keyframe_inputs import MapError, MappedKeyframe
from splat_slam_ros.types import Intrinsics


def map_state(mp) -> Tuple[Dict[str, np.ndarray], Dict[str, Any]]:
    """(arrays, JSON metadata) that :func:`load_map_state` turns back into an equal map:
    Gaussians with kf_id/created/born/uid, mapped keyframes with pose and exposure, the
    window and its visibility sets, counters. Adam moments are not kept (they restart at
    zero, as for new Gaussians). Keyframe images and depths are not included: the caller
    stores them per keyframe, so a snapshot costs O(map), not O(keyframes x image)."""
    g = mp.map
    arrays = {k: v.detach().cpu().numpy() for k, v in g.tensors().items()}
    ids = sorted(mp.keyframes)
    kfs = [mp.keyframes[k] for k in ids]
    arrays["kf_ids"] = np.array(ids, np.int64)
    arrays["kf_index"] = np.array([k.index for k in kfs], np.int64)
    arrays["kf_timestamp"] = np.array([k.timestamp for k in kfs], np.float64)
    arrays["kf_pose"] = np.stack([k.pose for k in kfs]) if kfs else np.zeros((0, 4, 4))
    arrays["kf_exposure"] = (np.stack([k.exposure.detach().cpu().numpy() for k in kfs])
                             if kfs else np.zeros((0, 2), np.float32))
    win = mp.window
    vis = {str(k): v.detach().cpu().numpy().tolist() for k, v in win.visibility.items()}
    meta = {"window": list(win.window), "last": win.last, "visibility": vis,
            "next_uid": g.next_uid, "settled_uid": int(mp.settled_uid),
            "iteration": int(mp.iteration), "n_deformations": int(mp.n_deformations),
            "n_deformed_gaussians": int(mp.n_deformed_gaussians),
            "scene_depth": float(mp.scene_depth), "next_index": int(mp.next_index),
            "counts": dict(mp.counts),
            "vignette": [float(x) for x in mp.vignette.detach().cpu()]}
    return arrays, meta


def load_map_state(mp, arrays: Dict[str, np.ndarray], meta: Dict, image_of,
                   depth_of) -> None:
    """Restore :func:`map_state` output into the (fresh) mapper ``mp``. ``image_of(kf_id)``
    returns the keyframe's H x W x 3 uint8 image, ``depth_of(kf_id)`` a dict with the
    proxy ``depth`` (float32), its validity mask bit-packed along rows (``valid``,
    ``np.packbits(mask, axis=-1)``), the image ``width`` and, when the keyframe's depth
    loss is weighted, its ``weight`` (float16)."""
    if mp.keyframes or len(mp.map):
        raise MapError("load_map_state needs a fresh mapper (no keyframes, no Gaussians)")
    dev = mp.device
    mp.map.load_tensors({k: torch.from_numpy(np.asarray(arrays[k])) for k in
                         ("means", "colors", "log_scales", "quats", "opacity_logits",
                          "kf_id", "created", "born", "uid")},
                        meta.get("next_uid"))
    for i, k in enumerate(np.asarray(arrays["kf_ids"]).tolist()):
        img = np.ascontiguousarray(np.asarray(image_of(int(k)), np.uint8))
        d = depth_of(int(k))
        W = int(d["width"])
        valid = np.unpackbits(np.asarray(d["valid"]), axis=-1)[..., :W].astype(bool)
        weight = d.get("weight")
        mp.add_keyframe_record(MappedKeyframe(
            int(k), int(arrays["kf_index"][i]), float(arrays["kf_timestamp"][i]),
            np.asarray(arrays["kf_pose"][i], np.float64), torch.from_numpy(img).to(dev),
            torch.from_numpy(np.asarray(d["depth"], np.float32)).to(dev),
            torch.from_numpy(valid.copy()).to(dev),
            torch.from_numpy(np.asarray(arrays["kf_exposure"][i], np.float32)).to(dev),
            None if weight is None else torch.from_numpy(np.asarray(weight, np.float32)).to(dev)))
    win = mp.window
    win.window = [int(x) for x in meta.get("window", [])]
    win.last = meta.get("last")
    win.visibility = {int(k): torch.tensor(v, dtype=torch.long, device=dev)
                      for k, v in (meta.get("visibility") or {}).items()}
    mp.iteration, mp.settled_uid = (int(meta.get(k, 0)) for k in ("iteration", "settled_uid"))
    mp.n_deformations = int(meta.get("n_deformations", 0))
    mp.n_deformed_gaussians = int(meta.get("n_deformed_gaussians", 0))
    mp.scene_depth = float(meta.get("scene_depth", 0.0))
    mp.next_index = max(mp.next_index, int(meta.get("next_index", 0)))
    mp.counts.update({k: int(v) for k, v in (meta.get("counts") or {}).items()})
    with torch.no_grad():
        mp.vignette.copy_(torch.tensor(meta.get("vignette", [0.0, 0.0])))


def keyframe_depth(mp, kf_id: int) -> Dict[str, np.ndarray]:
    """The proxy depth (float32), packed validity mask and (when the keyframe's depth loss is
    weighted) float16 weights a mapped keyframe holds now."""
    kf = mp.keyframes[int(kf_id)]
    out = {"depth": kf.depth.detach().cpu().numpy().astype(np.float32),
           "valid": np.packbits(kf.valid.cpu().numpy(), axis=-1),
           "width": np.array(kf.valid.shape[-1], np.int64)}
    if kf.weight is not None:
        out["weight"] = kf.weight.detach().cpu().numpy().astype(np.float16)
    return out


def restore_mapper(arrays: Dict[str, np.ndarray], meta: Dict[str, Any], cfg, intrinsics,
                   image_of, depth_of) -> "Mapper":  # noqa: F821
    """Rebuild a Mapper from :func:`map_state` output; ``image_of(kf_id)`` returns the
    keyframe's H x W x 3 uint8 image, ``depth_of(kf_id)`` what :func:`keyframe_depth` gave."""
    from splat_slam_ros.mapping.mapper import Mapper   # not on the tracking-only path (~30 MB)
    mp = Mapper(cfg, intrinsics)
    load_map_state(mp, arrays, meta, image_of, depth_of)
    return mp


def mapper_arrays(mp) -> Tuple[Dict[str, np.ndarray], dict]:
    """(arrays, metadata) of a mapper for the session's ``map_state.npz``: :func:`map_state`
    plus, per mapped keyframe ``k``, ``kf<k>_image`` and the ``kf<k>_<name>`` arrays of
    :func:`keyframe_depth` (depth, packed validity, width, weight)."""
    arrays, meta = map_state(mp)
    for k, kf in mp.keyframes.items():
        arrays[f"kf{k}_image"] = kf.image.cpu().numpy().astype(np.uint8)
        for name, a in keyframe_depth(mp, k).items():
            arrays[f"kf{k}_{name}"] = a
    return arrays, meta


def restore_map_state(arrays: Dict[str, np.ndarray], meta: dict, cfg, intrinsics):
    """The Mapper that the session's map state (``io.session.map_state``: arrays, metadata)
    describes (:func:`restore_mapper`), settled (``Mapper.settled_uid``): a later run maps
    new places, and the loaded Gaussians, whose own views it rarely revisits, are not
    pruned for the opacity that optimising those new views leaves them."""
    mp = restore_mapper(arrays, meta, cfg, intrinsics, lambda k: arrays[f"kf{k}_image"],
                        lambda k: {n: arrays[f"kf{k}_{n}"] for n in KEYFRAME_DEPTH
                                   if f"kf{k}_{n}" in arrays})
    mp.settled_uid = mp.map.next_uid
    return mp


def commit_map(store, mapper, intr: Intrinsics, dirty: set, gone: set, offered: Dict,
               taken: Dict, last_update_seq: int) -> None:
    """Commit the map to a node's store (io/keyframe_store.py) with exactly the inputs it
    reflects (``offered``, ``taken`` revisions, ``last_update_seq``): the map's arrays,
    the depth (and, once, the image) of the ``dirty`` keyframes; the records of the
    ``gone`` (merged) keyframes are deleted (both sets are emptied)."""
    arrays, meta = map_state(mapper)
    staged = {f"kf{k}_mdepth": store.stage(f"kf{k}_mdepth", **keyframe_depth(mapper, k))
              for k in sorted(dirty) if k in mapper.keyframes}
    staged.update({f"kf{k}_image": store.stage(f"kf{k}_image", image=np.asarray(
        mapper.keyframes[k].image.cpu(), np.uint8)) for k in sorted(dirty) if
        k in mapper.keyframes and not store.has(f"kf{k}_image")})
    for k in sorted(gone):                         # merged keyframes: records deleted
        staged[f"kf{k}_mdepth"] = staged[f"kf{k}_image"] = None
    dirty.clear()
    gone.clear()
    i = intr
    staged["map"] = store.stage("map", **arrays)
    store.commit(staged, {"map": meta,
                          "offered": {str(k): v for k, v in offered.items()},
                          "taken": {str(k): v for k, v in taken.items()},
                          "intrinsics": [i.fx, i.fy, i.cx, i.cy, i.width, i.height],
                          "last_update_seq": last_update_seq})


def resume_map(store, cfg) -> Tuple[Optional[Intrinsics], Optional["Mapper"]]:  # noqa: F821
    """(mapping camera, Mapper) a node's store holds (:func:`commit_map`), or (None, None)
    when it holds no map."""
    meta = store.meta
    if store.has("map") and meta.get("intrinsics"):
        intr = Intrinsics(*meta["intrinsics"][:4], *map(int, meta["intrinsics"][4:6]))
        return intr, restore_mapper(store.get("map"), meta["map"], cfg, intr,
                                    lambda k: store.get(f"kf{k}_image")["image"],
                                    lambda k: store.get(f"kf{k}_mdepth"))
    return None, None
