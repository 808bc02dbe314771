"""Mapping policy for the keyframes offered to the map: revisits, merges and held keyframes.

A keyframe that sees what a mapped keyframe already sees (``mapping.revisit_cull_deg``: a
mapped keyframe near it looking the same way, or, without one, a map that already covers
``mapping.revisit_coverage`` of its view) is consumed without being mapped, so a map of a
revisited room stays bounded (:func:`revisit_reason`). When a later pose update shows that
two mapped keyframes see the same, the newer is merged into the older (:func:`merge_pair`,
``Mapper.merge_keyframe``). A keyframe waits (acked) while its proxy depth anchors
(almost) no Gaussians (:func:`anchoring_fraction`) or, in revisit mode with a loop closer,
until loop closure has corrected its pose (:func:`waits_for_loop_closure`).
"""
from __future__ import annotations

from typing import Dict, Optional, Tuple

import numpy as np

from splat_slam_ros.types import ProxyDepth

MIN_DEPTH_FRACTION = 0.01   # a proxy depth anchoring fewer pixels is held by the mapper


def anchoring_fraction(pd: ProxyDepth, ba_weight: float) -> float:
    """Share of pixels whose depth anchors new Gaussians: full-weight depth (the mapper
    seeds none from down-weighted BA depth in multi-view holes)."""
    d = np.asarray(pd.depth)
    ok = np.isfinite(d) & (d > 0) & (np.asarray(pd.depth_weight(ba_weight)) >= 1)
    return float(ok.mean()) if ok.size else 0.0


def waits_for_loop_closure(mc, mapper, k: int, loop_seen: bool, settled: set,
                           newest_kf: int) -> bool:
    """Revisit mode (``mapping.revisit_cull_deg``) with a loop closer: mapped with the
    tracker's drifting pose a revisit looks like a new place (duplicate Gaussians). Such a
    keyframe waits, acked, for a depth revision made after a loop-closure update, for at
    most ``mapping.window_size`` newer keyframes (then mapped, merged later if need be),
    or the final digest; the map's first keyframe never waits."""
    return (mc.revisit_cull_deg > 0 and loop_seen and
            mapper is not None and bool(mapper.keyframes) and
            k not in settled and newest_kf - k < mc.window_size)


def revisit_of(mc, keyframes: Dict, pd: ProxyDepth, exclude: Optional[int] = None
               ) -> Optional[int]:
    """The mapped keyframe (other than ``exclude``) nearest to ``pd``'s keyframe that sees
    what it sees (``mapping.revisit_cull_deg``: centre within kf_translation x median
    depth, optical axes within that angle); None when there is none or the test is off."""
    if mc.revisit_cull_deg <= 0 or not keyframes:
        return None
    d = np.asarray(pd.depth, np.float32)
    ok = (d > 0) if pd.valid is None else (np.asarray(pd.valid, bool) & (d > 0))
    med = float(np.median(d[ok])) if ok.any() else 0.0
    T = np.asarray(pd.pose, np.float64)
    cos_max = np.cos(np.radians(mc.revisit_cull_deg))
    best = None
    for k, m in keyframes.items():
        if k == exclude:
            continue
        P = np.asarray(m.pose, np.float64)
        dist = float(np.linalg.norm(P[:3, 3] - T[:3, 3]))
        if dist < mc.kf_translation * med and float(P[:3, 2] @ T[:3, 2]) > cos_max and \
                (best is None or dist < best[0]):
            best = (dist, k)
    return None if best is None else best[1]


def revisit_reason(mc, mapper, pd: ProxyDepth) -> Optional[str]:
    """Why ``pd``'s keyframe is a revisit (consumed, not mapped: a bounded map), or None:
    a mapped keyframe sees what it sees (:func:`revisit_of`), or else the map already
    covers ``mapping.revisit_coverage`` of its view (a render, in revisit mode only)."""
    twin = revisit_of(mc, mapper.keyframes, pd)
    cov = 0.0                           # a render, only when the pose test found no twin
    if twin is None and mc.revisit_cull_deg > 0:
        cov = mapper.coverage(pd.pose)
    if twin is not None or cov >= mc.revisit_coverage:
        return f"revisit of {twin}" if twin is not None else f"map covers {cov:.0%} of its view"
    return None


def merge_pair(mc, mapper, k: int, pd: ProxyDepth) -> Optional[Tuple[int, int]]:
    """Keyframe ``k`` (mapped) moved: a new keyframe is mapped with the tracker's pose
    before loop closure corrects it, so a revisit is often recognised only after a later
    update. When ``k`` now sees what another mapped keyframe sees: (newer, older) of the
    two, the newer to be merged into the older (``Mapper.merge_keyframe``: its Gaussians in
    the older view are removed as duplicates, the rest follow the older keyframe), so
    keyframes and Gaussians stay bounded in a revisited room; the first keyframe (the
    exposure gauge) always stays. None when there is no such keyframe."""
    twin = revisit_of(mc, mapper.keyframes, pd, exclude=k)
    if twin is None:
        return None
    drop, keep = max(k, twin), min(k, twin)
    if mapper.keyframes[drop].index == 0:            # the exposure gauge stays
        drop, keep = keep, drop
    return drop, keep
