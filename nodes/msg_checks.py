"""Plausibility checks of the protocol messages a node receives, before conversion.

Deserialisable but malformed messages (fuzzing: NaN poses, "negative" ids that arrive as huge
unsigned values, zero / non-finite intrinsics, non-finite arrays, absurd sizes or batch
sizes) are refused with :class:`~splat_slam_nodes.convert.ConversionError`, which the node's
worker logs and drops; a refused message never reaches a stage role. Size mismatches
between the declared shape and the arrays are checked by the converters themselves.
"""
from __future__ import annotations

import math

import numpy as np

from .convert import ConversionError

MAX_ID = 2**31 - 1          # keyframe ids count up from 0; larger ones are "-1"-style garbage
MAX_SEQ = 2**63 - 1         # update sequence numbers (tracker from 1, loop closer from 10^9)
MAX_SIDE = 16384            # image / depth sides in pixels
MAX_BATCH = 1024            # keyframes in one batch (warm-up batches are a few keyframes)


def _pose(p, what: str) -> None:
    v = [p.position.x, p.position.y, p.position.z,
         p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]
    if not all(math.isfinite(x) for x in v):
        raise ConversionError(f"{what}: pose contains NaN or infinite values")
    if sum(x * x for x in v[3:]) < 1e-12:
        raise ConversionError(f"{what}: pose orientation is a zero quaternion")


def _finite(arr, what: str) -> None:
    a = np.frombuffer(memoryview(arr).cast("B"), np.float32) if len(arr) else np.zeros(0)
    if not np.isfinite(a).all():
        raise ConversionError(f"{what} contains NaN or infinite values")


def _id(v: int, what: str, limit: int = MAX_ID) -> None:
    if int(v) > limit:
        raise ConversionError(f"{what} {int(v)} is out of range (a negative id sent as unsigned?)")


def _side(w: int, h: int, what: str) -> None:
    if not (1 <= int(w) <= MAX_SIDE and 1 <= int(h) <= MAX_SIDE):
        raise ConversionError(f"{what}: size {int(w)}x{int(h)} outside 1..{MAX_SIDE}")


def check_keyframe(msg):
    """A splat_slam_msgs/Keyframe fit for conversion (returns it)."""
    what = f"keyframe {int(msg.kf_id)}"
    _id(msg.kf_id, "keyframe id")
    _pose(msg.pose, what)
    K = [float(x) for x in msg.intrinsics]
    if not all(math.isfinite(x) for x in K) or K[0] <= 0 or K[1] <= 0:
        raise ConversionError(f"{what}: intrinsics {K} must be finite with fx, fy > 0")
    _side(msg.width, msg.height, what)
    _side(msg.disp_width, msg.disp_height, f"{what} disparity")
    for name in ("disparity", "confidence"):      # mono depth may hold inf (sky): not checked
        _finite(getattr(msg, name), f"{what} {name}")
    if int(msg.batch_size) > MAX_BATCH or int(msg.batch_id) > MAX_ID:
        raise ConversionError(f"{what}: batch {int(msg.batch_id)} of size {int(msg.batch_size)} "
                              f"is out of range (at most {MAX_BATCH} keyframes)")
    return msg


def check_update(msg):
    """A splat_slam_msgs/PoseGraphUpdate fit for conversion (returns it)."""
    what = f"PoseGraphUpdate {int(msg.seq)}"
    _id(msg.seq, "PoseGraphUpdate seq", MAX_SEQ)
    if len(msg.kf_ids) and int(max(msg.kf_ids)) > MAX_ID:
        raise ConversionError(f"{what}: keyframe id {int(max(msg.kf_ids))} is out of range")
    for p in msg.poses:
        _pose(p, what)
    _finite(msg.disparities, f"{what} disparities")
    return msg


def check_proxy_depth(msg):
    """A splat_slam_msgs/ProxyDepth fit for conversion (returns it)."""
    what = f"proxy depth {int(msg.kf_id)}"
    _id(msg.kf_id, "proxy depth keyframe id")
    _id(msg.update_seq, f"{what} update_seq", MAX_SEQ)
    _id(msg.revision, f"{what} revision")
    _pose(msg.pose, what)
    _side(msg.width, msg.height, what)
    src = msg.source
    if len(src) and int(np.frombuffer(memoryview(src).cast("B"), np.uint8).max()) > msg.SOURCE_BA:
        raise ConversionError(f"{what}: source values must be 0..{msg.SOURCE_BA} (SOURCE_*)")
    return msg
